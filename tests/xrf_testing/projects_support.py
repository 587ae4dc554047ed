"""Helpers shared by the suites that upload and build projects (tests/projects, tests/sandbox,
tests/ui, tests/room, tests/server)."""

from __future__ import annotations

import io
import os
import tarfile
import time
import uuid
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def reachable_tmp(prefix: str) -> Path:
    """A fresh folder under the repo's ignored .cache/ that the xrf-build user can traverse
    (pytest's tmp folders live under root's private /tmp/pytest-of-root)."""
    root = REPO / ".cache" / "projects-tests"
    root.mkdir(parents=True, exist_ok=True)
    os.chmod(root, 0o755)
    d = root / f"{prefix}-{uuid.uuid4().hex[:8]}"
    d.mkdir()
    os.chmod(d, 0o755)
    return d


def wait_build(store, bid: int, timeout: float = 300):  # noqa: ANN001
    deadline = time.monotonic() + timeout
    while True:
        b = store.build(bid)
        if b.status not in ("queued", "building"):
            return b
        if time.monotonic() > deadline:
            raise AssertionError(f"build {bid} still {b.status} after {timeout} s")
        time.sleep(0.1)


def targz(files: dict[str, bytes], top: str = "proj") -> bytes:
    """A .tar.gz upload of `files` (relative path -> content) under one top folder."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as t:
        for name, data in files.items():
            info = tarfile.TarInfo(f"{top}/{name}")
            info.size = len(data)
            t.addfile(info, io.BytesIO(data))
    return buf.getvalue()


def build_and_wait(http, pid: int, timeout: float = 300) -> dict:  # noqa: ANN001
    """Start a build of project `pid` through the API and wait until it has ended."""
    r = http.post(f"/api/projects/{pid}/builds")
    assert r.status_code == 201, r.text
    b = r.json()
    deadline = time.monotonic() + timeout
    while b["status"] in ("queued", "building"):
        assert time.monotonic() < deadline
        time.sleep(0.2)
        b = http.get(f"/api/projects/{pid}/builds/{b['id']}").json()
    return b


def upload_and_build(http, data: bytes, name: str) -> tuple[int, int]:  # noqa: ANN001
    """Upload the archive `data` as a new project and build it: (project id, build id). A build
    that fails fails the test with the end of its log."""
    r = http.post("/api/projects", files={"file": (name, data, "application/gzip")})
    assert r.status_code == 201, r.text
    pid = r.json()["project"]["id"]
    b = build_and_wait(http, pid)
    if b["status"] != "ok":
        log = http.get(f"/api/projects/{pid}/builds/{b['id']}/log").text
        raise AssertionError(f"build failed: {b.get('result')}\n{log[-3000:]}")
    return pid, b["id"]
