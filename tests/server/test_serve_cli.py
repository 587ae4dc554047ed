"""`xrf serve` itself: prints the URL, serves, stops on Ctrl-C; and the FPGA RESET path."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx

from xrf_testing.harness import REPO_ROOT, free_port, login_client
from xrflab.server.runs.safety import fpga_reset


def test_xrf_serve_prints_url_and_serves(tmp_path: Path) -> None:
    port = free_port()
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT / "appliance"))
    env.pop("XRF_BOOTSTRAP_ADMIN_PASSWORD", None)
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "xrflab.cli",
            "serve",
            "--data",
            str(tmp_path / "data"),
            "--port",
            str(port),
            "--sim",
            "jiwy",
        ],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        lines = []
        deadline = time.monotonic() + 20
        while not any("not shown again" in line for line in lines):  # the URL, then the first-start secret
            assert time.monotonic() < deadline and proc.poll() is None, lines
            lines.append(proc.stdout.readline())
        assert f"http://localhost:{port}/" in "".join(lines)
        # First start: the educator `admin` and its one-time password, printed once.
        text = "".join(lines)
        assert "one-time password" in text, text
        secret = [line.split()[-1] for line in lines if line.startswith("XRF Lab:     ")][0]
        url = f"http://127.0.0.1:{port}"
        for _ in range(100):
            try:
                assert httpx.get(f"{url}/api/bench").status_code == 401  # nothing without a login
                break
            except httpx.TransportError:
                time.sleep(0.05)
        http = login_client(url, "admin", secret)
        assert http.get("/api/me").json()["must_change"]
        assert http.get("/api/bench").status_code == 403  # the one-time password must be changed first
        assert http.post("/api/auth/password", json={"current": secret, "new": "a new password!"}).status_code == 204
        http.headers["X-CSRF-Token"] = http.cookies.get("xrf_csrf")
        bench = http.get("/api/bench").json()
        assert bench["mode"] == "sim" and bench["sim"] == "jiwy"
        assert (tmp_path / "data" / "runs.sqlite3").exists()
        # Ctrl-C with a run active ends the run in order before the appliance exits.
        run = http.post("/api/runs", json={"build": "relbot"}, timeout=300).json()
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


def test_fpga_reset_goes_through_the_c_transport() -> None:
    """The appliance's RESET is rt_core's own (ico.c frame, spidev.c transport, through cffi):
    the spidev ioctls are tried on what it is given, and a missing device is said plainly. The
    frame's bytes are checked in rt_core/tests/test_ico_frames.c."""
    assert fpga_reset("/nonexistent/spidev9.9") == "no spidev to reset"
    # /dev/null opens but is no SPI device: the first spidev ioctl (SPI_IOC_WR_MODE) fails.
    assert fpga_reset("/dev/null") == "FPGA RESET failed: Inappropriate ioctl for device"


def test_xrf_serve_options_take_their_defaults_from_settings(tmp_path: Path) -> None:
    """In process: every option's default is its Settings field's (server/cli/serve.py reads them),
    so `xrf serve` with no options is Settings' defaults; given options reach their fields."""
    import argparse

    from xrflab.server.cli import serve
    from xrflab.server.settings import Settings

    parser = argparse.ArgumentParser()
    serve.add_arguments(parser)
    assert serve.settings_from(parser.parse_args(["--data", str(tmp_path)])) == Settings(data_dir=tmp_path)
    given = parser.parse_args(
        ["--data", str(tmp_path), "--sim", "jiwy", "--port", "8123", "--lease-idle-min", "5", "--hang-ms", "300"]
        + ["--allow-origin", "https://lab.example.edu/", "--trusted-proxy", "10.0.0.1", "--run-pids", "64"]
    )
    settings = serve.settings_from(given)
    assert (settings.sim, settings.port, settings.lease_idle_s, settings.hang_timeout_ms) == ("jiwy", 8123, 300, 300)
    assert settings.allow_origins == ("https://lab.example.edu",) and settings.trusted_proxies == ("10.0.0.1",)
    assert settings.run_pids == 64 and settings.run_memory_mb == Settings.run_memory_mb
    assert f"default {Settings.telemetry_hz:g})" in parser.format_help()
