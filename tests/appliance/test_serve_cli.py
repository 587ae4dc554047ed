"""`xrf serve` itself: prints the URL, serves, stops on Ctrl-C; and the FPGA RESET frame."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx

from harness import REPO_ROOT, free_port

from xrflab.server.safety import reset_frame


def test_xrf_serve_prints_url_and_serves(tmp_path: Path) -> None:
    port = free_port()
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT / "appliance"))
    proc = subprocess.Popen(
        [sys.executable, "-m", "xrflab.cli", "serve", "--data", str(tmp_path / "data"), "--port", str(port),
         "--sim", "jiwy"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    try:
        lines = []
        deadline = time.monotonic() + 20
        while not any("http://" in line for line in lines):
            assert time.monotonic() < deadline and proc.poll() is None, lines
            lines.append(proc.stdout.readline())
        assert f"http://localhost:{port}/" in "".join(lines)
        for _ in range(100):
            try:
                bench = httpx.get(f"http://127.0.0.1:{port}/api/bench").json()
                break
            except httpx.TransportError:
                time.sleep(0.05)
        assert bench["mode"] == "sim" and bench["sim"] == "jiwy"
        assert (tmp_path / "data" / "runs.sqlite3").exists()
        # Ctrl-C with a run active ends the run in order before the appliance exits.
        run = httpx.post(f"http://127.0.0.1:{port}/api/runs", json={"build": "relbot"}, timeout=300).json()
        assert run["status"] == "running"
    finally:
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=20) in (0, 130)  # 130: Ctrl-C after a clean shutdown
    assert not Path(f"/proc/{run['pid']}").exists() or "Z" in Path(f"/proc/{run['pid']}/stat").read_text().split()[2]
    assert not Path(f"/dev/shm/{run['shm']}").exists()


def test_jiwy_example_runs_on_the_jiwy_plant(server) -> None:
    server.stop_run()
    run = server.start_run("jiwy")
    assert run["sim"] == "jiwy" and run["status"] == "running"
    with server.ws() as ws:
        info = ws.wait_type("run")
        assert info["transport"] == "sim"
        assert ws.wait_type("telemetry")["run_id"] == run["id"]
    assert server.stop_run()["status"] == "ended"


def test_reset_frame_is_bit_reversed_reset() -> None:
    frame = reset_frame()
    assert len(frame) == 12
    assert frame[0] == 0b0100_0000  # opcode 2 (RESET) = 0b00000010, mirrored for LSB-first
    assert frame[1:] == bytes(11)
