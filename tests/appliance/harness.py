"""Test harness: a real appliance in a subprocess (uvicorn on a free port) running real loop
processes built from the bundled examples. No mocks: what the tests see is what a browser sees.
Shared by tests/appliance and tests/ui."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
from websockets.sync.client import ClientConnection, connect

REPO_ROOT = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent


# Debian's chromium for the browser tests and the docs screenshot (never a downloaded browser).
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
]


def shared_builds_root() -> Path:
    """Builds shared by every server of every session (the ignored .cache/ folder): the bundled
    examples compile once, later servers and sessions only re-check them (incremental CMake)."""
    path = REPO_ROOT / ".cache" / "test-builds"
    path.mkdir(parents=True, exist_ok=True)
    return path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class Server:
    url: str
    ws_url: str
    proc: subprocess.Popen[bytes]
    data_dir: Path
    http: httpx.Client

    def ws(self, **kw: Any) -> WsClient:
        return WsClient(connect(self.ws_url, max_size=None, **kw).__enter__())

    def start_run(self, build: str = "relbot", **body: Any) -> dict[str, Any]:
        r = self.http.post("/api/runs", json={"build": build, **body}, timeout=300)
        assert r.status_code == 201, r.text
        return r.json()

    def stop_run(self) -> dict[str, Any] | None:
        r = self.http.post("/api/runs/current/stop", timeout=30)
        return r.json() if r.status_code == 200 else None


class WsClient:
    """A WebSocket client that keeps every message, so tests wait for conditions, not sleeps."""

    def __init__(self, conn: ClientConnection) -> None:
        self.conn = conn
        self.messages: list[dict[str, Any]] = []

    def send(self, obj: Any) -> None:
        self.conn.send(obj if isinstance(obj, (str, bytes)) else json.dumps(obj))

    def wait_for(self, pred: Callable[[dict[str, Any]], bool], timeout: float = 5.0,
                 seen: bool = False) -> dict[str, Any]:
        """The next message matching pred; with seen=True a message already received counts too."""
        if seen:
            for m in self.messages:
                if pred(m):
                    return m
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                kinds = [m.get("type") for m in self.messages[-20:]]
                raise AssertionError(f"no matching message within {timeout} s; last types {kinds}")
            try:
                m = json.loads(self.conn.recv(timeout=left))
            except TimeoutError:
                continue
            self.messages.append(m)
            if pred(m):
                return m

    def wait_type(self, message_type: str, /, timeout: float = 5.0, seen: bool = False,
                  **fields: Any) -> dict[str, Any]:
        return self.wait_for(lambda m: m.get("type") == message_type and all(m.get(k) == v for k, v in fields.items()),
                             timeout, seen)

    def wait_state(self, name: str, timeout: float = 5.0) -> dict[str, Any]:
        """State `name` reached: a state message may come before the ack of the command causing it."""
        return self.wait_type("state", timeout, seen=True, name=name)

    def command(self, cmd: Any, timeout: float = 5.0) -> dict[str, Any]:
        self.send({"type": "command", "cmd": cmd})
        return self.wait_for(lambda m: m.get("type") in ("ack", "error"), timeout)

    def close(self) -> None:
        self.conn.close()

    def __enter__(self) -> WsClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def start_server(data_dir: Path, builds_root: Path, **settings: Any) -> Server:
    port = free_port()
    config = {"data_dir": str(data_dir), "builds_root": str(builds_root), "port": port, "host": "127.0.0.1",
              "real_bench": False, **settings}
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO_ROOT / "appliance"), str(HERE)]))
    proc = subprocess.Popen([sys.executable, str(HERE / "serve_for_test.py"), json.dumps(config)], env=env)
    url = f"http://127.0.0.1:{port}"
    http = httpx.Client(base_url=url, timeout=30)
    deadline = time.monotonic() + 20
    while True:
        try:
            if http.get("/api/bench").status_code == 200:
                break
        except httpx.TransportError:
            pass
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            raise RuntimeError(f"appliance did not start (exit {proc.poll()})")
        time.sleep(0.05)
    return Server(url, f"ws://127.0.0.1:{port}/ws", proc, data_dir, http)


def stop_server(server: Server) -> None:
    server.stop_run()
    server.http.close()
    server.proc.terminate()
    try:
        server.proc.wait(timeout=15)
    except subprocess.TimeoutExpired:
        server.proc.kill()
        server.proc.wait()
