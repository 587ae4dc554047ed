"""Helpers of the room tests: a broker on free loopback ports and MQTT clients that keep what they
receive, so tests wait for conditions instead of sleeping."""

from __future__ import annotations

import json
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from xrflab.room import mqtt, payloads, topics
from xrflab.room.broker import ROOM_USER, BrokerFiles, BrokerProcess


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def broker_files(folder: Path, bind: str = "127.0.0.1", names: list[str] | None = None) -> BrokerFiles:
    files = BrokerFiles(
        folder, port=free_port(), tls_port=free_port(), bind=bind, names=names or ["127.0.0.1", "localhost"]
    )
    files.write()
    return files


def start_broker(files: BrokerFiles) -> BrokerProcess:
    proc = BrokerProcess(files)
    proc.start()
    return proc


def room_endpoint(files: BrokerFiles, tls: bool = False) -> mqtt.Endpoint:
    return mqtt.Endpoint(
        "127.0.0.1",
        files.tls_port if tls else files.port,
        ROOM_USER,
        files.room_password(),
        files.ca_cert.read_text() if tls else "",
    )


class Recorder:
    """A connected MQTT client that records every message it receives and every PUBACK."""

    def __init__(
        self,
        endpoint: mqtt.Endpoint,
        client_id: str,
        subscribe: list[str] | None = None,
        will: tuple[str, bytes] | None = None,
        listens: bool = False,
    ) -> None:
        """`listens`: play the room's presence (payloads.RoomOnline true once subscribed, false as
        the will), without which benches hold their events."""
        self.messages: list[tuple[str, bytes, bool]] = []
        self.acks: dict[int, Any] = {}
        self.connected = threading.Event()
        self.subscribed = threading.Event()
        self.refused: Any = None
        self._lock = threading.Lock()
        if listens:
            will = (topics.ROOM_ONLINE, payloads.RoomOnline.make(online=False, conn="fe").wire())
        self.c = mqtt.client(endpoint, client_id, will)
        subs = subscribe or []
        sub_mid: list[int] = []

        def on_connect(c: Any, _u: Any, _f: Any, rc: Any, _p: Any = None) -> None:
            if not mqtt.reason_ok(rc):
                self.refused = rc
                return
            if subs:
                sub_mid[:] = [c.subscribe([(s, 1) for s in subs])[1]]
            else:
                self.subscribed.set()
            if listens:
                c.publish(topics.ROOM_ONLINE, payloads.RoomOnline.make(online=True, conn="fe").wire(), 1, True)
            self.connected.set()

        def on_subscribe(_c: Any, _u: Any, mid: int, _rc: Any, _p: Any = None) -> None:
            if mid in sub_mid:
                self.subscribed.set()

        def on_message(_c: Any, _u: Any, msg: Any) -> None:
            with self._lock:
                self.messages.append((msg.topic, msg.payload, bool(msg.retain)))

        def on_publish(_c: Any, _u: Any, mid: int, rc: Any, _p: Any = None) -> None:
            self.acks[mid] = rc

        self.c.on_connect, self.c.on_message, self.c.on_publish = on_connect, on_message, on_publish
        self.c.on_subscribe = on_subscribe
        mqtt.connect_async(self.c, endpoint)
        self.c.loop_start()

    def wait_connected(self, timeout: float = 5.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.subscribed.is_set():
                return True
            if self.refused is not None:
                return False
            time.sleep(0.02)
        return False

    def publish(self, topic: str, payload: Any, qos: int = 1, retain: bool = False) -> int:
        data = payload if isinstance(payload, bytes) else json.dumps(payload).encode()
        info = self.c.publish(topic, data, qos=qos, retain=retain)
        return info.mid

    def wait_ack(self, mid: int, timeout: float = 5.0) -> Any:
        deadline = time.monotonic() + timeout
        while mid not in self.acks:
            assert time.monotonic() < deadline, f"no PUBACK for {mid}"
            time.sleep(0.01)
        return self.acks[mid]

    def received(self, pred: Callable[[str, bytes], bool]) -> list[tuple[str, bytes, bool]]:
        with self._lock:
            return [m for m in self.messages if pred(m[0], m[1])]

    def wait_message(self, pred: Callable[[str, bytes], bool], timeout: float = 5.0) -> tuple[str, bytes, bool]:
        deadline = time.monotonic() + timeout
        while True:
            got = self.received(pred)
            if got:
                return got[0]
            assert time.monotonic() < deadline, "no matching MQTT message"
            time.sleep(0.01)

    def close(self) -> None:
        self.c.disconnect()
        self.c.loop_stop()


def bench_endpoint(files: BrokerFiles, name: str, password: str, tls: bool = False) -> mqtt.Endpoint:
    return mqtt.Endpoint(
        "127.0.0.1", files.tls_port if tls else files.port, name, password, files.ca_cert.read_text() if tls else ""
    )


__all__ = ["Recorder", "broker_files", "start_broker", "room_endpoint", "bench_endpoint", "free_port", "topics"]


# ---- a room and its benches -----------------------------------------------------------------------

import os  # noqa: E402
import re  # noqa: E402
import shutil  # noqa: E402
import signal  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
from dataclasses import dataclass  # noqa: E402

import httpx  # noqa: E402

from xrf_testing.harness import ADMIN_PASSWORD, REPO_ROOT, UNCONFINED_UNLESS_ROOT, Server, login_client  # noqa: E402
from xrf_testing.harness import HERE as APPLIANCE_TESTS  # noqa: E402


def netns_possible() -> bool:
    """Benches as separate hosts (a network namespace each, a veth to this one) need root and `ip`."""
    if os.geteuid() != 0 or not shutil.which("ip"):
        return False
    probe = f"xrf21probe{os.getpid()}"
    ok = subprocess.run(["ip", "netns", "add", probe], capture_output=True).returncode == 0
    subprocess.run(["ip", "netns", "del", probe], capture_output=True)
    return ok


def _used_nets() -> set[int]:
    """Second octets of the 10.x addresses this host's interfaces have now."""
    out = subprocess.run(["ip", "-o", "-4", "addr", "show"], capture_output=True, text=True).stdout
    return {int(m) for m in re.findall(r"inet 10\.(\d+)\.", out)}


class Topology:
    """Where benches live. `netns`: bench i is a host of its own (namespace, veth, 10.N.i.2) that
    reaches the broker at 10.N.0.1 (an address of this host); cut = its interface down. Else all on
    loopback with their own ports; cut = the appliance stopped (SIGSTOP: silent as a pulled cable).
    N is the first of NETS whose broker address this host does not have yet: two test sessions on
    one machine (two checkouts) each get their own network."""

    NETS = range(211, 241)
    _made = 0

    def __init__(self, n: int) -> None:
        self.netns = netns_possible()
        self.n = n
        # Names unique per topology, not per session: a namespace lives on (with its veth) until
        # its last process is gone, which may be after the previous module's topology was closed.
        Topology._made += 1
        self.tag = f"{os.getpid() % 10000}{Topology._made % 100}"
        self.created: list[str] = []
        self.net = f"10.{self.NETS[0]}"
        if self.netns:
            run = lambda *a: subprocess.run(a, check=True, capture_output=True)  # noqa: E731
            used = _used_nets()
            for net in self.NETS:
                if net in used:
                    continue  # another session's, or a closed topology's namespace not gone yet
                self.net = f"10.{net}"
                add = ["ip", "addr", "add", f"{self.BROKER_ADDR}/32", "dev", "lo"]
                if subprocess.run(add, capture_output=True).returncode == 0:
                    break
            else:
                raise RuntimeError(f"every test network 10.{self.NETS[0]}-{self.NETS[-1]}.0.1 is taken on lo")
            try:
                for i in range(1, n + 1):
                    ns, host_if = self.ns(i), f"x{self.tag}h{i}"
                    run("ip", "netns", "add", ns)
                    self.created.append(ns)
                    run("ip", "link", "add", host_if, "type", "veth", "peer", "name", "eth0", "netns", ns)
                    run("ip", "addr", "add", f"{self.net}.{i}.1/30", "dev", host_if)
                    run("ip", "link", "set", host_if, "up")
                    run("ip", "-n", ns, "addr", "add", f"{self.net}.{i}.2/30", "dev", "eth0")
                    run("ip", "-n", ns, "link", "set", "lo", "up")
                    run("ip", "-n", ns, "link", "set", "eth0", "up")
                    run("ip", "-n", ns, "route", "add", "default", "via", f"{self.net}.{i}.1")
            except subprocess.CalledProcessError as exc:
                self.close()  # half made: nothing of it stays on the host
                raise RuntimeError(f"{' '.join(exc.cmd)}: {exc.stderr.decode(errors='replace').strip()}") from exc

    @property
    def BROKER_ADDR(self) -> str:  # noqa: N802 (read like the constant it was)
        return f"{self.net}.0.1"

    @property
    def mode(self) -> str:
        return "network namespaces" if self.netns else "ports on loopback"

    def ns(self, i: int) -> str:
        return f"xrf21-{self.tag}-{i}"

    @property
    def broker_host(self) -> str:
        return self.BROKER_ADDR if self.netns else "127.0.0.1"

    def bench_host(self, i: int) -> str:
        return f"{self.net}.{i}.2" if self.netns else "127.0.0.1"

    def prefix(self, i: int) -> list[str]:
        # Only the network namespace: `ip netns exec` would also give the bench a mount namespace
        # with a fresh /sys and no cgroup file systems, and the run sandbox refuses to start a
        # controller without its cgroup (issue 26). A real bench is a host of its own anyway.
        return ["nsenter", f"--net=/run/netns/{self.ns(i)}", "--"] if self.netns else []

    def cut(self, i: int, server: Server) -> None:
        if self.netns:
            subprocess.run(["ip", "-n", self.ns(i), "link", "set", "eth0", "down"], check=True)
        else:
            os.kill(server.proc.pid, signal.SIGSTOP)

    def heal(self, i: int, server: Server) -> None:
        if self.netns:
            subprocess.run(["ip", "-n", self.ns(i), "link", "set", "eth0", "up"], check=True)
            subprocess.run(
                ["ip", "-n", self.ns(i), "route", "replace", "default", "via", f"{self.net}.{i}.1"], check=True
            )
        else:
            os.kill(server.proc.pid, signal.SIGCONT)

    def close(self) -> None:
        for ns in self.created:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)  # its veth goes with it
        if self.netns:
            subprocess.run(["ip", "addr", "del", f"{self.BROKER_ADDR}/32", "dev", "lo"], capture_output=True)


def start_bench(topo: Topology, i: int, data_dir: Path, builds_root: Path) -> Server:
    """An appliance as harness.start_server starts one, inside bench i's namespace when there is one."""
    host = topo.bench_host(i)
    port = 8000 if topo.netns else free_port()
    config = {
        "data_dir": str(data_dir),
        "builds_root": str(builds_root),
        "port": port,
        "host": host,
        "real_bench": False,
        "allow_unconfined": UNCONFINED_UNLESS_ROOT,  # harness.py says why
    }
    env = dict(
        os.environ,
        PYTHONPATH=os.pathsep.join([str(REPO_ROOT / "appliance"), str(APPLIANCE_TESTS)]),
        XRF_BOOTSTRAP_ADMIN_PASSWORD=ADMIN_PASSWORD,
    )
    proc = subprocess.Popen(
        [*topo.prefix(i), sys.executable, str(APPLIANCE_TESTS / "serve_for_test.py"), json.dumps(config)], env=env
    )
    url = f"http://{host}:{port}"
    _wait_http(url, proc)
    return Server(url, f"ws://{host}:{port}/ws", proc, data_dir, login_client(url, "admin", ADMIN_PASSWORD))


def _wait_http(url: str, proc: subprocess.Popen[bytes], timeout: float = 30) -> None:
    deadline = time.monotonic() + timeout
    with httpx.Client(base_url=url, timeout=5) as probe:
        while True:
            try:
                if probe.get("/api/health").status_code == 200:
                    return
            except httpx.TransportError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                proc.kill()
                raise RuntimeError(f"{url} did not start (exit {proc.poll()})")
            time.sleep(0.1)


@dataclass
class RoomServer:
    url: str
    proc: subprocess.Popen[bytes]
    data_dir: Path
    http: httpx.Client

    def stop(self) -> None:
        self.http.close()
        self.proc.terminate()
        try:
            self.proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


ROOM_RUNNER = """
import json, sys, uvicorn
from pathlib import Path
from xrflab.room.service import RoomConfig, create_room_app
c = json.loads(sys.argv[1]); c["data_dir"] = Path(c["data_dir"])
uvicorn.run(create_room_app(RoomConfig(**c)), host=c["host"], port=c["port"], log_level="warning")
"""


def start_room(data_dir: Path, files: BrokerFiles, **config: Any) -> RoomServer:
    port = free_port()
    cfg = {
        "data_dir": str(data_dir),
        "host": "127.0.0.1",
        "port": port,
        "broker_names": files.names,
        "broker_port": files.port,
        "broker_tls_port": files.tls_port,
        "broker_bind": files.bind,
        "spawn_broker": False,
        **config,
    }
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT / "appliance"), XRF_BOOTSTRAP_ADMIN_PASSWORD=ADMIN_PASSWORD)
    proc = subprocess.Popen([sys.executable, "-c", ROOM_RUNNER, json.dumps(cfg)], env=env)
    url = f"http://127.0.0.1:{port}"
    _wait_http(url, proc)
    return RoomServer(url, proc, data_dir, login_client(url, "admin", ADMIN_PASSWORD))


def join(
    room: RoomServer, name: str, data_dir: Path, dashboard_url: str, room_url: str = ""
) -> subprocess.CompletedProcess[str]:
    """`xrf room join` as an educator would run it on the bench, with a fresh code from the room
    (`room_url`: the room's address as the bench reaches it, default the test's)."""
    code = room.http.post("/api/room/join-codes").json()["code"]
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "xrflab.cli",
            "room",
            "join",
            room_url or room.url,
            code,
            "--name",
            name,
            "--data",
            str(data_dir),
            "--url",
            dashboard_url,
        ],
        capture_output=True,
        text=True,
        timeout=60,
        env=dict(os.environ, PYTHONPATH=str(REPO_ROOT / "appliance")),
    )


def enrol_request(code: str, name: str, url: str = "http://127.0.0.1:9") -> dict[str, str]:
    """What `xrf room join` posts to /api/room/enrol, with a fresh key pair of its own."""
    from xrflab.room import sso

    return {"code": code, "name": name, "bench_key": sso.public_text(sso.new_private_key()), "url": url}


def enrol_fake(room: RoomServer, name: str, url: str = "http://127.0.0.1:9") -> dict[str, Any]:
    """Enrol a bench that is not an appliance (the room then hears its name): the room's answer."""
    code = room.http.post("/api/room/join-codes").json()["code"]
    r = httpx.post(room.url + "/api/room/enrol", json=enrol_request(code, name, url), timeout=30)
    assert r.status_code == 200, r.text
    return r.json()


# ---- a whole lab: broker, room, N enrolled appliances ---------------------------------------------

from collections.abc import Iterator  # noqa: E402
from contextlib import contextmanager  # noqa: E402

from xrf_testing.harness import shared_builds_root  # noqa: E402

TEACHER, TEACHER_PW = "teacher", "teacher-room-pw-1"


@dataclass
class Lab:
    topo: Topology
    broker: BrokerProcess
    room: RoomServer
    benches: list[Server]
    teacher: httpx.Client
    room_url: str  # as the benches reach it

    def views(self) -> dict[str, dict[str, Any]]:
        return {b["name"]: b for b in self.room.http.get("/api/room/benches").json()["benches"]}

    def online(self) -> set[str]:
        return {n for n, b in self.views().items() if b["online"]}


@contextmanager
def room_lab(base: Path, n: int, bench_root: Path | None = None) -> Iterator[Lab]:
    """A broker (TLS, the room's CA), a room with the educator TEACHER, and `n` appliances b1..bn
    enrolled with `xrf room join`. `bench_root`: where the benches' data folders go (a folder the
    build user can reach, for tests that build projects); default `base`. The room listens on every
    address so benches in their own namespaces reach it (assignment fetches, collections)."""
    topo = Topology(n)
    print(f"\nroom test topology: {topo.mode}")
    benches: list[Server] = []
    broker = room = None
    try:
        files = broker_files(base / "room" / "broker", bind="0.0.0.0", names=[topo.broker_host, "127.0.0.1"])
        broker = start_broker(files)
        room = start_room(base / "room", files, tls=True, host="0.0.0.0")
        room_url = f"http://{topo.broker_host}:{room.url.rsplit(':', 1)[1]}"
        r = room.http.post(
            "/api/users", json={"username": TEACHER, "role": "educator", "password": TEACHER_PW, "must_change": False}
        )
        assert r.status_code == 201, r.text
        for i in range(1, n + 1):
            data = (bench_root or base) / f"bench{i}"
            data.mkdir()
            benches.append(start_bench(topo, i, data, shared_builds_root()))
        for i, s in enumerate(benches, 1):
            res = join(room, f"b{i}", s.data_dir, s.url, room_url)
            assert res.returncode == 0, res.stdout + res.stderr
            assert "TLS" in res.stdout
        yield Lab(topo, broker, room, benches, login_client(room.url, TEACHER, TEACHER_PW), room_url)
    finally:
        for s in benches:
            try:
                s.stop_run()
            except Exception:
                pass
            s.http.close()
            s.proc.terminate()
            try:
                s.proc.wait(15)
            except Exception:
                s.proc.kill()
                s.proc.wait()
        if room is not None:
            room.stop()
        if broker is not None:
            broker.stop()
        topo.close()


def held(lab: Lab, i: int) -> dict[str, Any]:
    """Everything bench i keeps of its room, as a student who read its enrolment file has it."""
    return json.loads((lab.benches[i].data_dir / "room" / "enrolment.json").read_text())


def as_bench(lab: Lab, i: int) -> Recorder:
    """An MQTT client elsewhere with bench i's stolen login (another client id: the real bench stays on)."""
    import secrets

    b = held(lab, i)["broker"]
    rec = Recorder(
        mqtt.Endpoint(b["host"], int(b["port"]), b["username"], b["password"], b.get("ca_pem", "")),
        f"stolen-{b['username']}-{secrets.token_hex(3)}",
    )
    assert rec.wait_connected(), "the bench's own login is refused by the broker"
    return rec


def sent(rec: Recorder, topic: str, payload: Any, retain: bool = False) -> None:
    """Published and taken by the broker (the bench's login may write its own topics)."""
    mid = rec.publish(topic, payload, retain=retain)
    assert mqtt.reason_ok(rec.wait_ack(mid))
