"""Benchmark of the lab room: a real `xrf room` (which starts its own mosquitto) and N light
simulated benches (each the real BenchPublisher with its own MQTT connection and a simulated loop
that answers `stop` at once), all on this machine.

Reports: status latency bench -> the room page's WebSocket (p50/p99), stop-all latency room ->
every loop (p50/p99/max over repeated stop-alls), and the broker's and the room's CPU (% of one
core over the measurement) and memory (VmRSS).

    .venv/bin/python bench/room/bench_room.py --benches 20 50 [--seconds 20] [--stops 30]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "appliance"))

import httpx  # noqa: E402
from websockets.sync.client import connect  # noqa: E402

from xrflab.room import mqtt, sso  # noqa: E402
from xrflab.room.publisher import BenchPublisher  # noqa: E402

PASSWORD = "bench-room-admin-pw"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


def pct(xs: list[float], q: float) -> float:
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(round(q * (len(xs) - 1))))]


class SimBench:
    """A bench without an appliance: the publisher and a loop that is in RUN until stopped."""

    def __init__(self, enrolment: dict, loop: asyncio.AbstractEventLoop) -> None:
        b = enrolment["broker"]
        self.state = "RUN"
        self.t0 = time.monotonic()
        endpoint = mqtt.Endpoint(b["host"], b["port"], b["username"], b["password"], b.get("ca_pem", ""))
        self.pub = BenchPublisher(
            enrolment["name"], endpoint, int(time.time() * 1000), self.facts, on_command=self.on_command
        )

    def facts(self) -> dict:
        return {
            "state": self.state,
            "active": True,
            "cycles": int((time.monotonic() - self.t0) * 1000),
            "cycle_rate": 1000.0,
            "misses": 0,
        }

    def on_command(self, command: Any, t_recv: float) -> None:
        # the simulated loop takes the stop as the appliance hands it over: on its event loop
        def done() -> None:
            self.state = "STOPPED"
            self.pub.reply(
                id=command.id,
                cmd=command.cmd,
                ok=True,
                accepted=True,
                t_recv=t_recv,
                t_loop=time.time(),
                t_sent=getattr(command, "t", None),
            )
            self.state = "RUN"

        self.pub._loop.call_soon_threadsafe(done)


def run(n: int, seconds: float, stops: int) -> dict:
    tmp = Path(tempfile.mkdtemp(prefix="xrf-room-bench-"))
    port, mport = free_port(), free_port()
    env = dict(os.environ, PYTHONPATH=str(REPO / "appliance"), XRF_BOOTSTRAP_ADMIN_PASSWORD=PASSWORD)
    room = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "xrflab.cli",
            "room",
            "--data",
            str(tmp),
            "--port",
            str(port),
            "--broker-port",
            str(mport),
            "--broker-tls-port",
            "0",
            "--no-tls",
        ],
        env=env,
        stdout=subprocess.DEVNULL,
    )
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 30
        while True:
            try:
                if httpx.get(url + "/api/health").status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert time.monotonic() < deadline and room.poll() is None, "room did not start"
            time.sleep(0.1)
        http = httpx.Client(base_url=url, headers={"Origin": url}, timeout=30)
        r = http.post("/api/auth/login", json={"username": "admin", "password": PASSWORD})
        http.headers["X-CSRF-Token"] = r.json()["csrf"]
        enrolments = []
        for i in range(n):
            code = http.post("/api/room/join-codes").json()["code"]
            request = {"code": code, "name": f"sim{i:02d}", "url": "http://127.0.0.1:9"}
            request["bench_key"] = sso.public_text(sso.new_private_key())
            enrolments.append(httpx.post(url + "/api/room/enrol", json=request).json())
        broker_pid = int((tmp / "broker" / "mosquitto.pid").read_text())

        loop = asyncio.new_event_loop()
        benches: list[SimBench] = []

        def loop_main() -> None:
            asyncio.set_event_loop(loop)

            async def start() -> None:
                for e in enrolments:
                    b = SimBench(e, loop)
                    b.pub.start()
                    benches.append(b)

            loop.run_until_complete(start())
            loop.run_forever()

        threading.Thread(target=loop_main, daemon=True).start()

        ws = connect(
            url.replace("http", "ws") + "/api/room/ws",
            origin=url,
            additional_headers={"Cookie": f"xrf_session={http.cookies.get('xrf_session')}"},
        )
        lat: list[float] = []
        online = set()
        deadline = time.monotonic() + 30
        while len(online) < n:
            m = json.loads(ws.recv(timeout=5))
            for b in m.get("benches", []) + ([m["bench"]] if "bench" in m else []):
                if b["online"]:
                    online.add(b["name"])
            assert time.monotonic() < deadline, f"only {len(online)} online"
        c0 = {"broker": cpu_s(broker_pid), "room": cpu_s(room.pid)}
        t_start = time.monotonic()
        while time.monotonic() - t_start < seconds:
            try:
                m = json.loads(ws.recv(timeout=1))
            except TimeoutError:
                continue
            if m.get("type") == "bench" and m["bench"].get("t"):
                lat.append(time.time() - m["bench"]["t"])
        elapsed = time.monotonic() - t_start
        cpu = {k: 100 * (cpu_s(p) - c0[k]) / elapsed for k, p in (("broker", broker_pid), ("room", room.pid))}
        mem = {"broker": rss_mb(broker_pid), "room": rss_mb(room.pid)}
        stop_lat: list[float] = []
        for _ in range(stops):
            sent = http.post("/api/room/stop", json={}).json()
            deadline = time.monotonic() + 5
            while True:
                replies = http.get(f"/api/room/commands/{sent['id']}").json()["replies"]
                if len(replies) >= n or time.monotonic() > deadline:
                    break
                time.sleep(0.05)
            assert len(replies) == n, f"{len(replies)} of {n} benches answered"
            stop_lat += [r["t_loop"] - r["t_sent"] for r in replies]
            time.sleep(0.2)
        ws.close()

        async def stop_all() -> None:
            for b in benches:
                await b.pub.stop()

        asyncio.run_coroutine_threadsafe(stop_all(), loop).result(30)
        loop.call_soon_threadsafe(loop.stop)
        return {
            "benches": n,
            "status_n": len(lat),
            "status_p50_ms": 1000 * statistics.median(lat),
            "status_p99_ms": 1000 * pct(lat, 0.99),
            "stop_n": len(stop_lat),
            "stop_p50_ms": 1000 * statistics.median(stop_lat),
            "stop_p99_ms": 1000 * pct(stop_lat, 0.99),
            "stop_max_ms": 1000 * max(stop_lat),
            "broker_cpu_pct": cpu["broker"],
            "room_cpu_pct": cpu["room"],
            "broker_rss_mb": mem["broker"],
            "room_rss_mb": mem["room"],
        }
    finally:
        room.terminate()
        room.wait(15)
        subprocess.run(["rm", "-rf", str(tmp)])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--benches", type=int, nargs="+", default=[20, 50])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--stops", type=int, default=30)
    args = ap.parse_args()
    print(
        "| benches | status p50 / p99 (ms) | stop-all p50 / p99 / max (ms), n | broker CPU % / RSS MB | room CPU % / RSS MB |"
    )
    print("|---|---|---|---|---|")
    for n in args.benches:
        r = run(n, args.seconds, args.stops)
        print(
            f"| {n} | {r['status_p50_ms']:.1f} / {r['status_p99_ms']:.1f} | {r['stop_p50_ms']:.1f} / "
            f"{r['stop_p99_ms']:.1f} / {r['stop_max_ms']:.1f}, {r['stop_n']} | {r['broker_cpu_pct']:.1f} / "
            f"{r['broker_rss_mb']:.1f} | {r['room_cpu_pct']:.1f} / {r['room_rss_mb']:.1f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
