"""The Projects page in a real browser: drop a template archive, build (live output), run it to
RUN on the bench; a compile error is clickable and shows the source line; a renamed Ros2Xeno
field shows up as the dashboard's setpoint control after a rebuild; 20-sim facts of a new
project from the 20-sim template."""

from __future__ import annotations

import base64
import io
import tarfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from xrf_testing.harness import Server, shared_builds_root, start_server, stop_server
from xrf_testing.projects_support import reachable_tmp

REPO = Path(__file__).resolve().parents[2]

BASE = REPO / "student_projects/templates/base"
SHOTS = REPO / "test-results"


@pytest.fixture(scope="module")
def server() -> Iterator[Server]:
    # A data folder the build user (xrf-build) can reach: not under root's private /tmp/pytest-of-root.
    s = start_server(reachable_tmp("ui-data"), shared_builds_root())
    yield s
    stop_server(s)


def targz(edit: dict[str, tuple[str, str]] | None = None) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as t:
        for p in sorted(BASE.rglob("*")):
            if not p.is_file() or "build" in p.relative_to(BASE).parts:
                continue
            rel = p.relative_to(BASE).as_posix()
            data = p.read_text()
            for old, new in [(edit or {}).get(rel, ("", ""))]:
                if old:
                    data = data.replace(old, new)
            raw = data.encode()
            info = tarfile.TarInfo(f"my_base/{rel}")
            info.size = len(raw)
            t.addfile(info, io.BytesIO(raw))
    return buf.getvalue()


def drop(page, selector: str, data: bytes, name: str) -> None:  # noqa: ANN001
    dt = page.evaluate_handle(
        """([b64, name]) => { const bin = atob(b64); const a = new Uint8Array(bin.length);
             for (let i = 0; i < bin.length; i++) a[i] = bin.charCodeAt(i);
             const dt = new DataTransfer(); dt.items.add(new File([a], name)); return dt; }""",
        [base64.b64encode(data).decode(), name],
    )
    page.dispatch_event(selector, "drop", {"dataTransfer": dt})


def build_ok(page) -> None:  # noqa: ANN001
    page.click("#proj-build")
    page.wait_for_selector("#proj-builds tr.current.st-ok", timeout=180_000)


def run_to_RUN(page) -> None:  # noqa: ANN001
    page.click("#proj-builds tr.current [data-run]")
    page.wait_for_function("location.hash === '#bench'")
    page.wait_for_function("document.getElementById('state-name').textContent === 'IDLE'", timeout=30_000)
    page.click("#commands [data-cmd=initialise]")
    page.wait_for_function("document.getElementById('state-name').textContent === 'INITIALISED'")
    page.click("#commands [data-cmd=start]")
    page.wait_for_function("document.getElementById('state-name').textContent === 'RUN'")


def test_projects_page_upload_build_run(server: Server, browser) -> None:  # noqa: ANN001
    server.stop_run()
    page = browser.new_page(viewport={"width": 1400, "height": 1000})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(server.url + "/#projects")
    page.wait_for_selector("#proj-drop")

    # drag-and-drop the base template
    drop(page, "#proj-drop", targz(), "my_base.tar.gz")
    page.wait_for_function("document.getElementById('proj-name').textContent.startsWith('my_base')")
    assert "steer_left" in page.inner_text("#msg-Ros2Xeno")
    build_ok(page)
    assert "Linking CXX executable" in page.inner_text("#proj-log")  # streamed output
    run_to_RUN(page)
    assert page.is_visible("#sp-steer_left")
    page.click("#btn-estop")
    page.wait_for_function("document.getElementById('state-name').textContent === 'STOPPED'")
    server.stop_run()

    # a compile error: the location is a link to the source line
    page.goto(server.url + "/#projects")
    page.wait_for_selector("#proj-list li[data-id]")
    page.click("#proj-list li[data-id]")
    page.wait_for_selector("#proj-update-file", state="attached")
    page.set_input_files(
        "#proj-update-file",
        files=[
            {
                "name": "my_base.tar.gz",
                "mimeType": "application/gzip",
                "buffer": targz(
                    {
                        "src/Template.cpp": (
                            "xeno_msg.pos_left = ros_msg.steer_left;",
                            "xeno_msg.pos_left = ros_msg.no_such_field;",
                        )
                    }
                ),
            }
        ],
    )
    page.wait_for_function("document.getElementById('proj-status').textContent.includes('ready to build')")
    page.click("#proj-build")
    page.wait_for_selector("#proj-builds tr.current.st-failed", timeout=120_000)
    page.wait_for_selector("#proj-diags li.diag.error.clickable")
    assert "src/Template.cpp:" in page.inner_text("#proj-diags li.diag.error.clickable >> nth=0")
    page.click("#proj-diags li.diag.error.clickable >> nth=0")
    page.wait_for_selector("#proj-source .srcline.hl")
    assert "no_such_field" in page.inner_text("#proj-source .srcline.hl")
    SHOTS.mkdir(exist_ok=True)
    page.screenshot(path=str(SHOTS / "projects.png"), full_page=True)

    # rename a Ros2Xeno field: after the rebuild the dashboard's setpoint control has the new name
    renamed = targz(
        {
            "msg/Ros2Xeno.msg": ("steer_left", "wheel_speed_left"),
            "src/Template.cpp": ("ros_msg.steer_left", "ros_msg.wheel_speed_left"),
        }
    )
    drop(page, "#proj-detail", renamed, "my_base.tar.gz")
    page.wait_for_function("document.getElementById('msg-Ros2Xeno').textContent.includes('wheel_speed_left')")
    build_ok(page)
    run_to_RUN(page)
    page.wait_for_selector("#sp-wheel_speed_left")
    assert not page.query_selector("#sp-steer_left")
    server.stop_run()

    # a new project from the 20-sim template shows the model's facts
    page.goto(server.url + "/#projects")
    page.select_option("#proj-template", "20sim")
    page.fill("#proj-new-name", "pan_tilt")
    page.click("#proj-new")
    page.wait_for_function("document.getElementById('proj-name').textContent.startsWith('pan_tilt')")
    assert page.inner_text("#ts-step") == "0.001 s"
    assert page.inner_text("#ts-freq") == "1000 Hz"
    assert page.inner_text("#ts-method") == "Euler"
    assert page.inner_text("#ts-inputs") == "SetPoint1, Position1, SetPoint2, Position2"
    assert page.inner_text("#ts-outputs") == "Steer1, Steer2"
    assert page.get_attribute("#proj-tpl-download", "href") == "/api/project-templates/20sim/download"
    assert not errors, errors
    page.close()
