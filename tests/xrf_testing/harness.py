"""Test harness: a real appliance in a subprocess (uvicorn on a free port) running real loop
processes built from the bundled examples. No mocks: what the tests see is what a browser sees.
Shared by every suite that needs a running appliance (tests/server, tests/ui, tests/logs, ...)."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
from websockets.sync.client import ClientConnection, connect

REPO_ROOT = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent


# Debian's chromium for the browser tests and the docs screenshot (never a downloaded browser).
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


def shared_builds_root() -> Path:
    """Builds shared by every server of every session (the ignored .cache/ folder): the bundled
    examples compile once, later servers and sessions only re-check them (incremental CMake).
    One folder per xdist worker: two servers building the same example into one folder at once
    break each other's build (a half-written binary, CMake's cache mid-write)."""
    path = REPO_ROOT / ".cache" / "test-builds" / os.environ.get("PYTEST_XDIST_WORKER", "main")
    path.mkdir(parents=True, exist_ok=True)
    return path


def wait_for(pred: Callable[[], Any], timeout: float = 10.0, what: str = "condition") -> Any:
    """Poll `pred` until it returns something true (returned), failing after `timeout` s."""
    deadline = time.monotonic() + timeout
    while True:
        v = pred()
        if v:
            return v
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.05)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# The harness's educator: created through XRF_BOOTSTRAP_ADMIN_PASSWORD, which only the tests set
# (a production first start prints a one-time secret instead; there is no default password).
ADMIN_USER = "admin"
ADMIN_PASSWORD = "harness-educator-pw"


@dataclass
class Server:
    url: str
    ws_url: str
    proc: subprocess.Popen[bytes]
    data_dir: Path
    http: httpx.Client  # logged in as the harness's educator (ADMIN_USER)

    def ws(self, **kw: Any) -> WsClient:
        """A WebSocket logged in as the harness's educator (cookie and same Origin)."""
        return ws_connect(self.ws_url, self.http, **kw)

    def login(self, username: str, password: str) -> tuple[httpx.Client, Callable[..., WsClient]]:
        """A new logged-in client for `username` and a factory of WebSockets in that session."""
        http = login_client(self.url, username, password)
        return http, lambda **kw: ws_connect(self.ws_url, http, **kw)

    def create_user(self, username: str, role: str = "student", password: str | None = None) -> str:
        """Create an account (as the educator) and return its password, ready to log in with."""
        password = password or f"{username}-pw-{os.urandom(4).hex()}"
        r = self.http.post(
            "/api/users", json={"username": username, "role": role, "password": password, "must_change": False}
        )
        assert r.status_code == 201, r.text
        return password

    def start_run(self, build: str = "relbot", **body: Any) -> dict[str, Any]:
        r = self.http.post("/api/runs", json={"build": build, **body}, timeout=300)
        assert r.status_code == 201, r.text
        return r.json()

    def stop_run(self) -> dict[str, Any] | None:
        r = self.http.post("/api/runs/current/stop", timeout=30)
        return r.json() if r.status_code == 200 else None

    def cycles(self, run_id: int) -> int:
        """The run's cycle count as the appliance reports it (live from the loop's status)."""
        r = self.http.get(f"/api/logs/runs/{run_id}")
        assert r.status_code == 200, r.text
        return int(r.json()["run"]["cycles"])

    def wait_cycles(self, run_id: int, n: int, timeout: float = 30.0) -> int:
        """Wait until the run has cycled `n` more times than now: the loop has done (and logged)
        that much, which a sleep only hopes for on a loaded machine. Returns the count reached."""
        c0 = self.cycles(run_id)
        return int(wait_for(lambda: (c := self.cycles(run_id)) > c0 + n and c, timeout, f"{n} cycles of run {run_id}"))


def login_client(url: str, username: str, password: str, timeout: float = 30) -> httpx.Client:
    """An httpx client holding a session cookie and sending the CSRF header and Origin a browser
    page on the appliance would send."""
    http = httpx.Client(base_url=url, timeout=timeout, headers={"Origin": url})
    r = http.post("/api/auth/login", json={"username": username, "password": password})
    if r.status_code != 200:
        http.close()
        raise AssertionError(f"login as {username} failed: {r.status_code} {r.text}")
    http.headers["X-CSRF-Token"] = r.json()["csrf"]
    return http


def ws_connect(ws_url: str, http: httpx.Client, **kw: Any) -> WsClient:
    """A WebSocket in the session of `http` (its cookie), from the appliance's own Origin."""
    headers = dict(kw.pop("additional_headers", None) or {})
    token = http.cookies.get("xrf_session")
    if token and "Cookie" not in headers:
        headers["Cookie"] = f"xrf_session={token}"
    kw.setdefault("origin", str(http.base_url).rstrip("/"))
    return WsClient(connect(ws_url, max_size=None, additional_headers=headers, **kw).__enter__())


def session_cookies(http: httpx.Client, url: str) -> list[dict[str, Any]]:
    """The session of `http` as Playwright cookies (browser_context.add_cookies)."""
    return [
        {
            "name": "xrf_session",
            "value": http.cookies.get("xrf_session"),
            "url": url,
            "httpOnly": True,
            "sameSite": "Strict",
        },
        {"name": "xrf_csrf", "value": http.cookies.get("xrf_csrf"), "url": url, "sameSite": "Strict"},
    ]


def browser_login(page: Any, url: str, username: str, password: str) -> None:
    """Log a Playwright page in through the login page, as a person would."""
    page.goto(url + "/")  # not logged in: redirected to the login page
    page.wait_for_selector("#login-user")
    page.fill("#login-user", username)
    page.fill("#login-pass", password)
    page.click("#login-submit")
    page.wait_for_function("location.pathname === '/'")
    page.wait_for_function("window.xrf && window.xrf.me && window.xrf.me.username === " + json.dumps(username))


def telemetry_samples(message: dict[str, Any]) -> list[dict[str, Any]]:
    """A telemetry message's samples, oldest first, each with the message's run_id, lost and
    ros2xeno (the Ros2Xeno the loop had at its newest sample)."""
    extra = {"run_id": message["run_id"], "lost": message["lost"], "ros2xeno": message.get("ros2xeno", {})}
    return [{**sample, **extra} for sample in message["samples"]]


class WsClient:
    """A WebSocket client that keeps every message, so tests wait for conditions, not sleeps."""

    def __init__(self, conn: ClientConnection) -> None:
        self.conn = conn
        self.messages: list[dict[str, Any]] = []

    def send(self, obj: Any) -> None:
        self.conn.send(obj if isinstance(obj, (str, bytes)) else json.dumps(obj))

    def wait_for(
        self, pred: Callable[[dict[str, Any]], bool], timeout: float = 5.0, seen: bool = False
    ) -> dict[str, Any]:
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

    def wait_type(
        self, message_type: str, /, timeout: float = 5.0, seen: bool = False, **fields: Any
    ) -> dict[str, Any]:
        return self.wait_for(
            lambda m: m.get("type") == message_type and all(m.get(k) == v for k, v in fields.items()), timeout, seen
        )

    def wait_sample(
        self, pred: Callable[[dict[str, Any]], bool] = lambda s: True, timeout: float = 5.0, seen: bool = False
    ) -> dict[str, Any]:
        """The first telemetry sample matching pred, oldest first, from the next telemetry message
        that has one (a message carries several: server/ws/messages.py TelemetryMessage): the
        sample's fields with its message's run_id, lost and ros2xeno."""
        found: list[dict[str, Any]] = []

        def match(m: dict[str, Any]) -> bool:
            if m.get("type") != "telemetry":
                return False
            for sample in telemetry_samples(m):
                if pred(sample):
                    found.append(sample)
                    return True
            return False

        self.wait_for(match, timeout, seen)
        return found[-1]

    def wait_state(self, name: str, timeout: float = 5.0) -> dict[str, Any]:
        """State `name` reached: a state message may come before the ack of the command causing it."""
        return self.wait_type("state", timeout, seen=True, name=name)

    def command(self, cmd: Any, timeout: float = 5.0) -> dict[str, Any]:
        self.send({"type": "command", "cmd": cmd})
        return self.wait_for(lambda m: m.get("type") in ("ack", "error"), timeout)

    def to_run(self, idle_timeout: float = 60.0) -> None:
        """A run just started, from IDLE to RUN as a student does it: initialise, then start,
        each accepted and its state reached."""
        self.wait_state("IDLE", idle_timeout)
        assert self.command("initialise")["accepted"]
        self.wait_state("INITIALISED")
        assert self.command("start")["accepted"]
        self.wait_state("RUN")

    def close(self) -> None:
        self.conn.close()

    def __enter__(self) -> WsClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# A normal user's appliance on a machine like this one cannot confine a run fully (cgroup v1 takes
# no process of another uid from a non-root user; the run folder's own file system comes from the
# root helper, deploy/systemd/xrf-run-disk.socket, which a test session does not start), so its runs
# are refused unless allowed, as an educator allows them (`xrf serve --allow-unconfined`). Tests that
# need a controller to run (grading, the room's grading) pass this; as root every run is confined
# and nothing is allowed. The refusal itself is tests/sandbox/test_launcher.py's.
UNCONFINED_UNLESS_ROOT = os.geteuid() != 0


def start_server(data_dir: Path, builds_root: Path, env: dict[str, str] | None = None, **settings: Any) -> Server:
    """`env`: added to the appliance's environment (not this process's: its own clients stay as they are)."""
    port = settings.pop("port", None) or free_port()  # a port of its own, or the one given (a restart)
    config = {
        "data_dir": str(data_dir),
        "builds_root": str(builds_root),
        "port": port,
        "host": "127.0.0.1",
        "real_bench": False,
        # Prepared by the first viewer of a test that opens one (test_rerun_viewer_files.py checks the
        # preparation at start): hundreds of test appliances would otherwise each prepare it.
        "prepare_viewer_at_start": False,
        **settings,
    }
    extra = dict(env or {})
    # A PYTHONPATH given goes after the appliance's and this folder's (a benchmark's timer:
    # bench/appliance/task_cpu).
    path = [str(REPO_ROOT / "appliance"), str(HERE), *filter(None, [extra.pop("PYTHONPATH", "")])]
    env = dict(
        os.environ,
        PYTHONPATH=os.pathsep.join(path),
        XRF_BOOTSTRAP_ADMIN_PASSWORD=ADMIN_PASSWORD,
        **extra,
    )
    proc = subprocess.Popen([sys.executable, str(HERE / "serve_for_test.py"), json.dumps(config)], env=env)
    url = f"http://127.0.0.1:{port}"
    probe = httpx.Client(base_url=url, timeout=30)
    deadline = time.monotonic() + 20
    while True:
        try:
            if probe.get("/api/health").status_code == 200:
                probe.close()
                break
        except httpx.TransportError:
            pass
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            raise RuntimeError(f"appliance did not start (exit {proc.poll()})")
        time.sleep(0.05)
    http = login_client(url, ADMIN_USER, ADMIN_PASSWORD)
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
