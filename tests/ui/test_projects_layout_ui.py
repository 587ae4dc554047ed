"""The Projects page in a real browser, as a TA met it on a first afternoon (issue 31, bug 3 and
the upload friction):

- a long upload refusal is shown where there is room (across the page), wrapped, never
  overflowing the 320 px project list;
- "run N is still active" appears beside the Run button that was clicked, not at the top of the
  other column;
- "Open in editor" opens the Editor page on the project it is next to;
- the upload box says what belongs in the archive before an upload, from the server's own rules;
- a workspace zipped as src/ is named after its controller package, and the page says which
  package of the workspace is built."""

from __future__ import annotations

import base64
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest

from xrf_testing.harness import Server, shared_builds_root, start_server, stop_server
from xrf_testing.projects_support import reachable_tmp, targz

REPO = Path(__file__).resolve().parents[2]
BASE = REPO / "student_projects/templates/base"
V11 = REPO / "tests/fixtures/xrf2_v1_1_project"
XRF2_MSGS_PACKAGE = (
    '<?xml version="1.0"?>\n<package format="3">\n  <name>xrf2_msgs</name>\n'
    "  <version>0.0.0</version>\n  <description>messages</description>\n"
    '  <maintainer email="s@example.org">s</maintainer>\n  <license>MIT</license>\n</package>\n'
)
VIEWPORT = {"width": 1400, "height": 1000}
SHOTS = REPO / "test-results"  # screenshots for a person to look at (not compared)


def shot(page, name: str) -> None:  # noqa: ANN001
    SHOTS.mkdir(exist_ok=True)
    page.screenshot(path=str(SHOTS / name), full_page=True)


@pytest.fixture(scope="module")
def server() -> Iterator[Server]:
    # A data folder the build user (xrf-build) can reach: not under root's private /tmp/pytest-of-root.
    data = reachable_tmp("ui-layout")
    s = start_server(data, shared_builds_root())
    yield s
    stop_server(s)
    shutil.rmtree(data, ignore_errors=True)


def base_files() -> dict[str, bytes]:
    return {
        p.relative_to(BASE).as_posix(): p.read_bytes()
        for p in sorted(BASE.rglob("*"))
        if p.is_file() and "build" not in p.relative_to(BASE).parts
    }


def workspace_files() -> dict[str, bytes]:
    """src/controller (V1.1, package.xml name relbot_v11, no msg/), src/my_interfaces (the
    xrf2_msgs package holding the messages), src/vision_node (another ROS 2 node)."""
    out: dict[str, bytes] = {}
    for p in sorted(V11.rglob("*")):
        if p.is_file() and "build" not in p.relative_to(V11).parts:
            rel = p.relative_to(V11).as_posix()
            out[("my_interfaces/" if rel.startswith("msg/") else "controller/") + rel] = p.read_bytes()
    out["my_interfaces/package.xml"] = XRF2_MSGS_PACKAGE.encode()
    out["vision_node/CMakeLists.txt"] = b"cmake_minimum_required(VERSION 3.8)\nproject(vision_node)\n"
    out["vision_node/package.xml"] = XRF2_MSGS_PACKAGE.replace("xrf2_msgs", "vision_node").encode()
    return out


def drop(page, data: bytes, name: str) -> None:  # noqa: ANN001
    dt = page.evaluate_handle(
        """([b64, name]) => { const bin = atob(b64); const a = new Uint8Array(bin.length);
             for (let i = 0; i < bin.length; i++) a[i] = bin.charCodeAt(i);
             const dt = new DataTransfer(); dt.items.add(new File([a], name)); return dt; }""",
        [base64.b64encode(data).decode(), name],
    )
    page.dispatch_event("#proj-drop", "drop", {"dataTransfer": dt})


def projects_page(server: Server, browser):  # noqa: ANN001, ANN201
    page = browser.new_page(viewport=VIEWPORT)
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(server.url + "/#projects")
    page.wait_for_selector("#proj-drop")
    return page, errors


def box(page, text: str) -> dict:  # noqa: ANN001
    """Where the innermost visible element showing ``text`` is, and whether its text overflows it."""
    got = page.evaluate(
        """(text) => {
          const all = [...document.querySelectorAll('body *')].filter((e) =>
            e.offsetParent !== null && e.textContent.includes(text)
            && ![...e.children].some((c) => c.textContent.includes(text)));
          if (!all.length) return null;
          const e = all[0], r = e.getBoundingClientRect();
          return {x: r.x, y: r.y, right: r.right, bottom: r.bottom, width: r.width, height: r.height,
                  overflow: e.scrollWidth - e.clientWidth, id: e.id,
                  inSide: !!e.closest('#proj-side'), viewport: document.documentElement.clientWidth};
        }""",
        text,
    )
    assert got is not None, f"nothing on the page shows {text!r}"
    return got


def test_a_long_refusal_is_shown_across_the_page_wrapped(server: Server, browser) -> None:  # noqa: ANN001
    page, errors = projects_page(server, browser)
    # No CMakeLists.txt: the refusal lists the top level, here one long name without a space.
    long_name = "lab3_position_controller_final_version_" + "x" * 150
    drop(page, targz({f"{long_name}/notes.txt": b"hi\n", "README.md": b"#\n"}, "handin"), "handin.tar.gz")
    page.wait_for_function("document.body.innerText.includes('archive refused')", timeout=20_000)
    b = box(page, "archive refused")
    assert long_name in page.evaluate("document.body.innerText")  # the whole name, readable
    assert not b["inSide"], "the refusal is in the narrow project-list column"
    assert b["width"] >= 0.6 * b["viewport"], b  # where there is room
    assert b["overflow"] <= 1, b  # wrapped, not spilling out of its box
    side = page.evaluate(
        "(() => { const s = document.getElementById('proj-side'); return s.scrollWidth - s.clientWidth; })()"
    )
    assert side <= 1, "the project list column overflows"
    shot(page, "projects-refusal.png")
    assert not errors, errors
    page.close()


def test_the_upload_box_says_what_belongs_in_the_archive(server: Server, browser) -> None:  # noqa: ANN001
    rules = server.http.get("/api/project-upload-rules").json()
    page, errors = projects_page(server, browser)
    page.wait_for_function("document.getElementById('proj-drop').innerText.includes('MB')")
    text = page.inner_text("#proj-drop")
    assert f"{round(rules['max_upload'] / (1 << 20))} MB" in text
    for layout in rules["layouts"]:
        assert layout in text
    for fmt in rules["formats"]:
        assert fmt in text
    assert page.get_attribute("#proj-file", "accept") == ",".join(rules["formats"])
    assert not errors, errors
    page.close()


def test_a_workspace_is_named_after_its_package_which_the_page_shows(server: Server, browser) -> None:  # noqa: ANN001
    page, errors = projects_page(server, browser)
    drop(page, targz(workspace_files(), "src"), "src.tar.gz")
    page.wait_for_function("document.getElementById('proj-name').textContent.startsWith('relbot_v11')", timeout=30_000)
    # the detail says which package of the workspace is built, without opening a build log
    detail = page.inner_text("#proj-detail")
    assert "relbot_v11" in detail and "controller/" in detail, detail[:500]
    assert "relbot_v11" in page.inner_text("#proj-list")
    shot(page, "projects-workspace.png")
    assert not errors, errors
    page.close()


def test_open_in_editor_opens_that_project(server: Server, browser) -> None:  # noqa: ANN001
    ids = []
    for top in ("first_proj", "second_proj"):
        r = server.http.post(
            "/api/projects", files={"file": (f"{top}.tar.gz", targz(base_files(), top), "application/gzip")}
        )
        assert r.status_code == 201, r.text
        ids.append(r.json()["project"]["id"])
    page, errors = projects_page(server, browser)
    for pid in ids:  # both: the editor's own default (the list's first) cannot pass for both
        page.goto(server.url + "/#projects")
        page.wait_for_selector(f"#proj-list li[data-id='{pid}']")
        page.click(f"#proj-list li[data-id='{pid}']")
        page.wait_for_function(f"window.xrfProjects.detail && window.xrfProjects.detail.id === {pid}")
        page.get_by_role("button", name="Open in editor").click()
        page.wait_for_function("location.hash === '#editor'")
        page.wait_for_function(f"window.xrfEditor.pid === {pid} && window.xrfEditor.path !== null", timeout=20_000)
        assert page.input_value("#ed-project") == str(pid)
    assert not errors, errors
    page.close()


def test_a_run_refusal_is_shown_beside_its_run_button(server: Server, browser) -> None:  # noqa: ANN001
    server.stop_run()
    page, errors = projects_page(server, browser)
    drop(page, targz(base_files(), "runnable"), "runnable.tar.gz")
    page.wait_for_function("document.getElementById('proj-name').textContent.startsWith('runnable')", timeout=30_000)
    page.click("#proj-build")
    page.wait_for_selector("#proj-builds tr.current.st-ok [data-run]", timeout=240_000)
    active = server.start_run("relbot")  # someone's run is on the bench
    try:
        button = page.locator("#proj-builds tr.current [data-run]")
        button.click()
        page.wait_for_function("document.body.innerText.includes('still active')", timeout=20_000)
        assert page.evaluate("location.hash") == "#projects"
        msg = box(page, "still active")
        assert f"run {active['id']} is still active" in page.evaluate("document.body.innerText"), (
            "the refusal names the run"
        )
        btn = button.bounding_box()
        assert btn is not None
        # beside the button: the same row, next to it
        assert abs((msg["y"] + msg["height"] / 2) - (btn["y"] + btn["height"] / 2)) < 30, (msg, btn)
        assert -5 <= msg["x"] - (btn["x"] + btn["width"]) < 60, (msg, btn)
        shot(page, "projects-run-refused.png")
    finally:
        server.stop_run()
    assert not errors, errors
    page.close()
