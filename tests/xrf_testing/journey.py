"""The Quick start's main journey as one program: start the appliance as `xrf serve` (or
`./lab serve`) would, log in with the first-start password, change it, upload the base template
as a student would, build it, and say what happened as one JSON line on stdout.

Run as a program, not imported by a test, because it also runs where the suite's own Python is
not: inside the fresh-machine check's system tree, with the venv ./lab made there.

    python journey.py [--port N] -- <command that serves, e.g. ./lab serve --port N>

Exit 0 when the build is ok; the JSON says why not otherwise.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import signal
import subprocess
import sys
import tarfile
import threading
import time
from pathlib import Path

import httpx

REPO = Path(__file__).resolve().parents[2]
TEMPLATE = REPO / "student_projects" / "templates" / "base"


def _targz(folder: Path, top: str) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as t:
        for p in sorted(folder.rglob("*")):
            if p.is_file():
                t.add(p, arcname=f"{top}/{p.relative_to(folder)}")
    return buf.getvalue()


def journey(command: list[str], port: int, start_timeout: float, build_timeout: float, modes: list[str] = ()) -> dict:
    out: dict = {"ok": False, "lines": []}
    proc = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True
    )
    lines: list[str] = out["lines"]
    threading.Thread(target=lambda: [lines.append(line.rstrip("\n")) for line in proc.stdout], daemon=True).start()
    try:
        deadline = time.monotonic() + start_timeout
        while not any("not shown again" in line for line in lines):
            if proc.poll() is not None or time.monotonic() > deadline:
                out["error"] = f"the appliance did not print its first-start password (exit {proc.poll()})"
                return out
            time.sleep(0.1)
        secret = [line.split()[-1] for line in lines if line.startswith("XRF Lab:     ")][0]
        url = f"http://127.0.0.1:{port}"
        http = httpx.Client(base_url=url, timeout=60, headers={"Origin": url})
        r = http.post("/api/auth/login", json={"username": "admin", "password": secret})
        r.raise_for_status()
        http.headers["X-CSRF-Token"] = r.json()["csrf"]
        http.post("/api/auth/password", json={"current": secret, "new": "a new password!"}).raise_for_status()
        http.headers["X-CSRF-Token"] = http.cookies.get("xrf_csrf")
        r = http.post(
            "/api/projects", files={"file": ("my_base.tar.gz", _targz(TEMPLATE, "my_base"), "application/gzip")}
        )
        r.raise_for_status()
        pid = r.json()["project"]["id"]
        b = http.post(f"/api/projects/{pid}/builds")
        b.raise_for_status()
        build = b.json()
        deadline = time.monotonic() + build_timeout
        while build["status"] in ("queued", "building") and time.monotonic() < deadline:
            time.sleep(0.5)
            build = http.get(f"/api/projects/{pid}/builds/{build['id']}").json()
        out["build"] = {k: build.get(k) for k in ("status", "result")}
        if build["status"] != "ok":
            out["build_log"] = http.get(f"/api/projects/{pid}/builds/{build['id']}/log").text[-4000:]
        # Modes of the folders asked for (--mode PATH), e.g. a data folder that exists only here.
        out["modes"] = {m: oct(os.stat(m).st_mode & 0o7777) for m in modes if os.path.exists(m)}
        out["ok"] = build["status"] == "ok"
        return out
    except Exception as exc:  # reported, not raised: the caller reads the JSON
        out["error"] = f"{type(exc).__name__}: {exc}"
        return out
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGINT)
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
        out["exit"] = proc.returncode


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--port", type=int, required=True)
    p.add_argument("--start-timeout", type=float, default=300)
    p.add_argument("--build-timeout", type=float, default=600)
    p.add_argument("--mode", action="append", default=[], metavar="PATH", help="report PATH's mode after the build")
    p.add_argument("command", nargs=argparse.REMAINDER)
    a = p.parse_args()
    command = a.command[1:] if a.command[:1] == ["--"] else a.command
    result = journey(command, a.port, a.start_timeout, a.build_timeout, a.mode)
    print(json.dumps(result), flush=True)
    return 0 if result["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
