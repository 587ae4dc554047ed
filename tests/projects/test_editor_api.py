"""The editor's API through the real appliance: files, save = a new source version built at once,
"build and run" running exactly the build of the saved source (even after a later save), version
history and diffs (against the template too), the ownership rule, and refusals that change
nothing (traversal, links, oversize, binary, a stale base)."""

from __future__ import annotations

import os
import secrets
import sqlite3
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from xrf_testing.harness import Server, shared_builds_root, start_server, stop_server

RUN_LINE = "int Template::run()\n{\n"


@pytest.fixture(scope="module")
def server(module_data_dir: Path) -> Iterator[Server]:
    s = start_server(module_data_dir, shared_builds_root())
    yield s
    stop_server(s)


def new_project(http, name: str) -> int:  # noqa: ANN001
    r = http.post("/api/projects/from-template", json={"template": "base", "name": name})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def save(http, pid: int, path: str, text: str | bytes, base: int | None, build: bool = True):  # noqa: ANN001, ANN201
    params = {"build": str(build).lower()}
    if base is not None:
        params["base"] = str(base)
    body = text.encode() if isinstance(text, str) else text
    return http.put(
        f"/api/projects/{pid}/files/{path}",
        params=params,
        content=body,
        headers={"Content-Type": "text/plain; charset=utf-8"},
    )


def project_folder(server: Server, pid: int) -> Path:
    """Where the appliance keeps the project (folder names are random)."""
    db = sqlite3.connect(f"file:{server.data_dir / 'projects.sqlite3'}?mode=ro", uri=True)
    try:
        ((folder,),) = db.execute("SELECT folder FROM projects WHERE id=?", (pid,)).fetchall()
    finally:
        db.close()
    return server.data_dir / "projects" / folder


def wait_build(http, pid: int, bid: int, timeout: float = 300) -> dict:  # noqa: ANN001
    deadline = time.monotonic() + timeout
    while True:
        b = http.get(f"/api/projects/{pid}/builds/{bid}").json()
        if b["status"] not in ("queued", "building"):
            return b
        assert time.monotonic() < deadline, f"build {bid} still {b['status']}"
        time.sleep(0.2)


def with_marker(text: str, marker: str) -> str:
    assert RUN_LINE in text
    return text.replace(RUN_LINE, RUN_LINE + f'    monitor.printf("{marker}\\n");\n', 1)


def test_save_is_a_version_built_and_run_exactly(server: Server) -> None:
    http = server.http
    pid = new_project(http, "edit_run")
    files = http.get(f"/api/projects/{pid}/files").json()
    assert files["version"] == 1
    info = {f["path"]: f for f in files["files"]}
    assert info["src/Template.cpp"]["editable"] and info["CMakeLists.txt"]["editable"]
    f = http.get(f"/api/projects/{pid}/files/src/Template.cpp").json()
    assert f["version"] == 1 and f["editable"] and RUN_LINE in f["content"]
    original = f["content"]

    # A broken edit: the build fails with the error at the line the edit put it on.
    lines = original.splitlines(keepends=True)
    broken_line = lines.index("int Template::run()\n") + 3  # 1-based: the line after "{"
    broken = "".join(lines[: broken_line - 1] + ["    int oops = not_declared_anywhere;\n"] + lines[broken_line - 1 :])
    r = save(http, pid, "src/Template.cpp", broken, base=1)
    assert r.status_code == 200, r.text
    s = r.json()
    assert s["new_version"] and s["version"]["n"] == 2 and s["version"]["origin"] == "edit src/Template.cpp"
    b = wait_build(http, pid, s["build"]["id"])
    assert b["status"] == "failed"
    errs = [d for d in b["details"]["diagnostics"] if d["kind"] == "error" and d["in_project"]]
    assert errs and errs[0]["file"] == "src/Template.cpp" and errs[0]["line"] == broken_line, errs[:2]

    # Fixed, with a marker the run prints; then at once a second save with another marker. Each
    # build compiles its own version: running the first build prints the first marker only.
    # The queue is kept busy first (another project's build that sleeps), so both saves happen
    # before the first of their builds starts: a build of the working copy would see the second.
    m1, m2 = f"EDITOR-A-{secrets.token_hex(4)}", f"EDITOR-B-{secrets.token_hex(4)}"
    blocker = new_project(http, "blocker")
    cmake = http.get(f"/api/projects/{blocker}/files/CMakeLists.txt").json()["content"]
    sb = save(http, blocker, "CMakeLists.txt", cmake + "execute_process(COMMAND sleep 4)\n", base=1).json()
    s1 = save(http, pid, "src/Template.cpp", with_marker(original, m1), base=2).json()
    s2 = save(http, pid, "src/Template.cpp", with_marker(original, m2), base=s1["version"]["n"]).json()
    assert (s1["version"]["n"], s2["version"]["n"]) == (3, 4)
    assert s1["build"]["id"] != s2["build"]["id"]
    assert s1["build"]["status"] == "queued" and s2["build"]["status"] == "queued"
    b1 = wait_build(http, pid, s1["build"]["id"])
    assert b1["status"] == "ok", b1["result"]
    assert b1["source_hash"] == s1["version"]["source_hash"]
    versions = http.get(f"/api/projects/{pid}/versions").json()
    assert [v["n"] for v in versions] == [4, 3, 2, 1]
    assert {v["n"]: (v["build"] or {}).get("id") for v in versions}[3] == b1["id"]

    server.stop_run()
    with server.ws() as ws:
        ws.send({"type": "subscribe", "topics": ["state", "run", "monitor"]})
        r = http.post(f"/api/projects/{pid}/builds/{b1['id']}/run", json={}, timeout=60)
        assert r.status_code == 201, r.text
        assert r.json()["run"]["build"] == f"project-{pid}-build-{b1['id']}"
        ws.wait_state("IDLE", timeout=20)
        for cmd, state in (("initialise", "INITIALISED"), ("start", "RUN")):
            assert ws.command(cmd)["accepted"], cmd
            ws.wait_state(state)
        ws.wait_for(
            lambda m: m.get("type") == "monitor" and any(m1 in ln["text"] for ln in m["lines"]), timeout=15, seen=True
        )
        texts = [ln["text"] for m in ws.messages if m.get("type") == "monitor" for ln in m["lines"]]
        assert not any(m2 in t for t in texts)
    server.stop_run()
    assert wait_build(http, pid, s2["build"]["id"])["status"] == "ok"
    assert wait_build(http, blocker, sb["build"]["id"])["status"] == "ok"

    # Saving the same text again is no new version; the same source reuses its build.
    again = save(http, pid, "src/Template.cpp", with_marker(original, m2), base=4).json()
    assert not again["new_version"] and again["version"]["n"] == 4 and again["build"]["reused"]


def test_history_and_diffs(server: Server) -> None:
    http = server.http
    pid = new_project(http, "history")
    text = http.get(f"/api/projects/{pid}/files/src/main.cpp").json()["content"]
    save(http, pid, "src/main.cpp", text + "// student line one\n", base=1, build=False)
    save(http, pid, "src/extra.hpp", "#pragma once\nint extra();\n", base=2, build=False)
    r = http.delete(f"/api/projects/{pid}/files/README.md", params={"base": 3})
    assert r.status_code == 200 and r.json()["version"]["n"] == 4, r.text
    versions = http.get(f"/api/projects/{pid}/versions").json()
    assert [(v["n"], v["origin"]) for v in versions] == [
        (4, "delete README.md"),
        (3, "edit src/extra.hpp"),
        (2, "edit src/main.cpp"),
        (1, "template:base"),
    ]

    d = http.get(f"/api/projects/{pid}/diff", params={"a": 1, "b": 2}).json()
    assert [(f["path"], f["status"], f["added"], f["removed"]) for f in d["files"]] == [
        ("src/main.cpp", "modified", 1, 0)
    ]
    assert "+// student line one\n" in d["files"][0]["diff"]
    # A template project's first version is the template: nothing between them.
    assert http.get(f"/api/projects/{pid}/diff", params={"a": "template:base", "b": 1}).json()["files"] == []
    # Against the template, the current version shows exactly what the student did.
    d = http.get(f"/api/projects/{pid}/diff", params={"a": "template:base"}).json()
    assert d["b"] == "v4"
    assert {f["path"]: f["status"] for f in d["files"]} == {
        "README.md": "removed",
        "src/extra.hpp": "added",
        "src/main.cpp": "modified",
    }
    # An older version reads as it was.
    old = http.get(f"/api/projects/{pid}/files/src/main.cpp", params={"version": 1}).json()
    assert old["content"] == text
    assert http.get(f"/api/projects/{pid}/files/README.md", params={"version": 3}).status_code == 200
    assert http.get(f"/api/projects/{pid}/files/README.md").status_code == 404
    for bad in ({"a": "99"}, {"a": "template:nope"}, {"a": "x"}):
        assert http.get(f"/api/projects/{pid}/diff", params=bad).status_code in (400, 404), bad


def test_someone_elses_project_is_missing(server: Server) -> None:
    pw_a, pw_b = server.create_user("ed_alice"), server.create_user("ed_bob")
    alice, _ = server.login("ed_alice", pw_a)
    bob, _ = server.login("ed_bob", pw_b)
    pid = new_project(alice, "alices")
    missing = 10**9
    calls = (
        ("GET", "files"),
        ("GET", "files/src/main.cpp"),
        ("PUT", "files/src/main.cpp"),
        ("DELETE", "files/src/main.cpp"),
        ("GET", "versions"),
        ("GET", "diff?a=1"),
    )
    for method, tail in calls:
        theirs = bob.request(method, f"/api/projects/{pid}/{tail}", content=b"int x;\n")
        none = bob.request(method, f"/api/projects/{missing}/{tail}", content=b"int x;\n")
        assert theirs.status_code == 404, (method, tail, theirs.status_code)
        assert theirs.json() == {"detail": f"no project {pid}"} and none.json() == {"detail": f"no project {missing}"}
    # Bob changed nothing; Alice still at version 1, the educator sees her project.
    assert [v["n"] for v in alice.get(f"/api/projects/{pid}/versions").json()] == [1]
    assert server.http.get(f"/api/projects/{pid}/files").status_code == 200
    alice.close()
    bob.close()


def test_refusals_change_nothing(server: Server) -> None:
    http = server.http
    pid = new_project(http, "refusals")
    src = project_folder(server, pid) / "src"
    main = http.get(f"/api/projects/{pid}/files/src/main.cpp").json()["content"]

    def unchanged() -> None:
        assert [v["n"] for v in http.get(f"/api/projects/{pid}/versions").json()] == [1]
        assert http.get(f"/api/projects/{pid}/files/src/main.cpp").json()["content"] == main

    # traversal, absolute names, control characters, left-out folders
    for path in (
        "%2e%2e/%2e%2e/outside.txt",
        "src/%2e%2e/%2e%2e/%2e%2e/outside.txt",
        "/etc/passwd",
        "..%2f..%2foutside.txt",
        "src/a%01b.cpp",
        "build/x.cpp",
        ".git/config",
    ):
        for method in ("GET", "PUT", "DELETE"):
            r = http.request(method, f"/api/projects/{pid}/files/{path}", content=b"x\n")
            assert r.status_code in (400, 404), (method, path, r.status_code, r.text)
    assert not (server.data_dir / "projects" / "outside.txt").exists()
    assert not any(p.name == "outside.txt" for p in server.data_dir.rglob("outside.txt"))
    unchanged()

    # a link planted in the working copy is never followed
    os.symlink("/etc/hostname", src / "src" / "link.cpp")
    try:
        assert http.get(f"/api/projects/{pid}/files/src/link.cpp").status_code == 404
        assert save(http, pid, "src/link.cpp", "int x;\n", base=1).status_code == 404
        assert Path("/etc/hostname").read_text() != "int x;\n"
    finally:
        os.unlink(src / "src" / "link.cpp")
    unchanged()

    # over 1 MB: refused while it streams
    r = save(http, pid, "src/main.cpp", b"/" * ((1 << 20) + 1), base=1)
    assert r.status_code == 413 and "over 1 MB" in r.json()["detail"], r.text
    # binary or not UTF-8: not a text file
    for data in (b"int x;\0\n", b"\xff\xfe\x00bad", "é".encode("latin-1")):
        r = save(http, pid, "src/main.cpp", data, base=1)
        assert r.status_code == 415 and "not a text file" in r.json()["detail"], r.text
    # a stale base for a file that changed since: 409, nothing lost
    assert save(http, pid, "src/main.cpp", main + "// v2\n", base=1, build=False).json()["version"]["n"] == 2
    r = save(http, pid, "src/main.cpp", main + "// from an old tab\n", base=1, build=False)
    assert r.status_code == 409 and r.json()["detail"]["current_version"] == 2, r.text
    assert http.get(f"/api/projects/{pid}/files/src/main.cpp").json()["content"] == main + "// v2\n"
    # a stale base for another file that did not change: saved
    r = save(
        http,
        pid,
        "CMakeLists.txt",
        http.get(f"/api/projects/{pid}/files/CMakeLists.txt").json()["content"] + "# note\n",
        base=1,
        build=False,
    )
    assert r.status_code == 200 and r.json()["version"]["n"] == 3, r.text
    # a binary file of the project is listed and readable as "not editable"
    (src / "data.bin").write_bytes(b"\x00\x01\x02")
    files = {f["path"]: f for f in http.get(f"/api/projects/{pid}/files").json()["files"]}
    assert files["data.bin"]["editable"] is False and "binary" in files["data.bin"]["reason"]
    got = http.get(f"/api/projects/{pid}/files/data.bin").json()
    assert got["editable"] is False and got["content"] == ""
    # that outside change became a version of its own ("existing source")
    assert http.get(f"/api/projects/{pid}/versions").json()[0]["origin"] == "existing source"
    assert not list((server.data_dir / "projects").rglob(".*.xrf-*"))  # no temp file left
