"""The arm64 rehearsal's last step (bench/arm64/rehearse), run inside the emulated root with the
installed venv's python: `xrf serve` as the service would run it (user xrf, /var/lib/xrf-lab,
XRF_CACHE_DIR=/var/cache/xrf-lab, the simulated board), then what a first lab does through the
API - log in with the first-start password, upload and build the base template, a run to RUN,
a self-check, a log download - each timed. One JSON line on stdout; exit 0 when every step
passed.

`--service-user root`: the service runs as root instead of xrf, the run sandbox in its setuid mode.
The rehearsal needs it because under qemu-user every process has a second thread (qemu's own),
and the kernel gives a new user namespace only to a single-threaded process (unshare(2): EINVAL),
so the unprivileged sandbox of user xrf cannot start there; on a Pi it does. Root's data folder is
then /var/lib/xrf-lab-as-root (0755): the service's own /var/lib/xrf-lab is xrf's (0750), which
root's build user (xrf-build) may not pass.

A program, not a test: it runs where only the installed venv is (httpx is one of its
dependencies).
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

SERVICE_ENV = {
    "HOME": "/var/lib/xrf-lab",
    "XRF_CACHE_DIR": "/var/cache/xrf-lab",
    "PYTHONUNBUFFERED": "1",
    # A build's wall-time limit (300 s) is a Pi's; emulated at nice 19 on a shared machine the
    # base template took longer (stopped at its link step).
    "XRF_BUILD_TIMEOUT_S": "1800",
}


def _targz(folder: Path, top: str) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as t:
        for p in sorted(folder.rglob("*")):
            if p.is_file():
                t.add(p, arcname=f"{top}/{p.relative_to(folder)}")
    return buf.getvalue()


def _until(what: str, timeout: float, probe):
    """probe() until it returns something true; polls because the API is polled here (no WebSocket)."""
    deadline = time.monotonic() + timeout
    while True:
        got = probe()
        if got:
            return got
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what}: not within {timeout:.0f} s")
        time.sleep(0.5)  # polling interval


def rehearse(port: int, template: Path, service_user: str, out: dict) -> None:
    seconds: dict[str, float] = out["seconds"]
    lines: list[str] = out["lines"]

    def step(name: str, t0: float) -> None:
        seconds[name] = round(time.monotonic() - t0, 1)
        print(f"on_board: {name}: {seconds[name]} s", file=sys.stderr, flush=True)

    t0 = time.monotonic()
    data = "/var/lib/xrf-lab"
    if service_user == "root":
        data = "/var/lib/xrf-lab-as-root"
        os.makedirs(data, mode=0o755, exist_ok=True)
    cmd = [] if service_user == "root" else ["runuser", "-u", service_user, "--"]
    cmd += ["env", *(f"{k}={v}" for k, v in {**SERVICE_ENV, "HOME": data}.items())]
    cmd += ["/opt/xrf-lab/venv/bin/xrf", "serve", "--port", str(port), "--data", data]
    proc = subprocess.Popen(
        cmd, cwd=data, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True
    )
    out["_proc"] = proc
    threading.Thread(target=lambda: [lines.append(x.rstrip("\n")) for x in proc.stdout], daemon=True).start()
    _until(
        "the first-start password", 900, lambda: proc.poll() is not None or any("not shown again" in x for x in lines)
    )
    if proc.poll() is not None:
        raise RuntimeError(f"xrf serve exited {proc.returncode}")
    secret = [x.split()[-1] for x in lines if x.startswith("XRF Lab:     ")][0]
    step("serve_start", t0)

    t0 = time.monotonic()
    url = f"http://127.0.0.1:{port}"
    http = httpx.Client(base_url=url, timeout=120, headers={"Origin": url})
    r = http.post("/api/auth/login", json={"username": "admin", "password": secret})
    r.raise_for_status()
    http.headers["X-CSRF-Token"] = r.json()["csrf"]
    http.post("/api/auth/password", json={"current": secret, "new": "a new password!"}).raise_for_status()
    http.headers["X-CSRF-Token"] = http.cookies.get("xrf_csrf")
    step("login", t0)

    t0 = time.monotonic()
    r = http.post("/api/projects", files={"file": ("my_base.tar.gz", _targz(template, "my_base"), "application/gzip")})
    r.raise_for_status()
    pid = r.json()["project"]["id"]
    b = http.post(f"/api/projects/{pid}/builds")
    b.raise_for_status()
    bid = b.json()["id"]
    build = _until(
        "the build",
        1800,
        lambda: (lambda j: j if j["status"] not in ("queued", "building") else None)(
            http.get(f"/api/projects/{pid}/builds/{bid}").json()
        ),
    )
    out["build"] = build["status"]
    if build["status"] != "ok":
        out["build_log"] = http.get(f"/api/projects/{pid}/builds/{bid}/log").text[-4000:]
        raise RuntimeError("the build failed")
    step("upload_build", t0)

    t0 = time.monotonic()
    http.post("/api/lease/take")  # an educator may drive without it; taken as a student would
    r = http.post(f"/api/projects/{pid}/builds/{bid}/run", json={}, timeout=300)
    if r.status_code != 201:
        raise RuntimeError(f"start run: {r.status_code} {r.text[:500]}")
    run_id = r.json()["run"]["id"]
    out["run_id"] = run_id
    for cmd_name, state in (("initialise", "INITIALISED"), ("start", "RUN")):

        def reached(cmd_name=cmd_name, state=state):
            rep = http.post("/api/runs/current/command", json={"cmd": cmd_name})
            return rep.status_code == 200 and rep.json()["state_name"] == state

        _until(f"{state} after {cmd_name}", 600, reached)
    out["state"] = "RUN"
    step("run_to_RUN", t0)
    time.sleep(3.0)  # time passing: three seconds of logged cycles in RUN
    http.post("/api/runs/current/stop", timeout=120).raise_for_status()

    t0 = time.monotonic()
    profile = http.get("/api/selfcheck").json()["bench"].get("sim") or "relbot"  # the simulated plant's profile
    r = http.post("/api/selfcheck", json={"profile": profile, "stop_run": True})
    if r.status_code != 202:
        raise RuntimeError(f"self-check: {r.status_code} {r.text[:500]}")
    st = _until(
        "the self-check",
        900,
        lambda: (lambda j: j if j["running"] is None and j["last"] else None)(http.get("/api/selfcheck").json()),
    )
    last = st["last"]
    out["selfcheck"] = {k: v for k, v in last.items() if isinstance(v, (str, int, float, bool)) or k == "counts"}
    if last.get("event") != "report":
        raise RuntimeError(f"the self-check did not report: {last}")
    step("selfcheck", t0)

    t0 = time.monotonic()
    logs = http.get(f"/api/logs/runs/{run_id}").json()
    got = []
    for f in logs["files"]:
        d = http.get(f"/api/logs/runs/{run_id}/files/{f['name']}")
        d.raise_for_status()
        got.append({"name": f["name"], "bytes": len(d.content), "records": f.get("records"), "lost": f.get("lost")})
    out["logs"] = got
    if not got or not any(g["bytes"] > 0 for g in got):
        raise RuntimeError(f"no log to download: {logs}")
    step("log_download", t0)
    out["ok"] = True


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--port", type=int, required=True)
    p.add_argument("--template", type=Path, required=True)
    p.add_argument("--service-user", default="xrf", help="who runs xrf serve (xrf as on a Pi, or root)")
    a = p.parse_args()
    out: dict = {"ok": False, "service_user": a.service_user, "seconds": {}, "lines": []}
    try:
        rehearse(a.port, a.template, a.service_user, out)
    except Exception as exc:  # reported in the JSON, with the appliance's output
        out["error"] = f"{type(exc).__name__}: {exc}"
    finally:
        proc = out.pop("_proc", None)
        if proc is not None and proc.poll() is None:
            os.killpg(proc.pid, signal.SIGINT)
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
    if out["ok"]:
        out["lines"] = out["lines"][-20:]
    print(json.dumps(out), flush=True)
    return 0 if out["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
