"""Input is bounded before anything parses it, against a real appliance (issue 14, item 5):
oversized and endless bodies are refused without the process growing; X-Forwarded-For is
believed only from a configured proxy; an anonymous guesser cannot keep an account locked for
its owner; the data folder's files (SQLite WAL/SHM included) have no 'other' bits whatever the
umask the appliance was started with."""

from __future__ import annotations

import io
import os
import socket
import stat
import tarfile
import threading
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from xrf_testing.harness import (
    ADMIN_PASSWORD,
    ADMIN_USER,
    Server,
    login_client,
    shared_builds_root,
    start_server,
    stop_server,
)

MB = 1 << 20
REPO = Path(__file__).resolve().parents[3]
BASE = REPO / "student_projects/templates/base"


def rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError("no VmRSS")


class RawRequest:
    """A raw connection with the request head sent, and a thread collecting whatever comes back
    (read while we send: a server that closes on an unread body resets the connection, and a
    reset discards what the client had not read yet)."""

    def __init__(self, server: Server, path: str, headers: dict[str, str]) -> None:
        host, port = server.url.removeprefix("http://").split(":")
        self.sock = socket.create_connection((host, int(port)), timeout=30)
        head = f"POST {path} HTTP/1.1\r\nHost: {host}:{port}\r\nOrigin: {server.url}\r\n"
        head += "".join(f"{k}: {v}\r\n" for k, v in headers.items()) + "\r\n"
        self.sock.sendall(head.encode())
        self.received: list[bytes] = []
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self) -> None:
        try:
            while chunk := self.sock.recv(65536):
                self.received.append(chunk)
        except OSError:
            pass

    def response(self, timeout: float = 20) -> tuple[int, bytes]:
        self.reader.join(timeout)
        data = b"".join(self.received)
        self.sock.close()
        assert data.startswith(b"HTTP/1.1 "), data[:200]
        return int(data.split()[1]), data


def _send_until_refused(sock: socket.socket, total: int, chunked: bool) -> int:
    """Send up to `total` bytes of a JSON-looking body; the number sent before the server hung up."""
    block = b'{"username": "admin", "password": "' + b"x" * (MB - 40) + b'"}'
    sent = 0
    try:
        while sent < total:
            sock.sendall(f"{len(block):x}\r\n".encode() + block + b"\r\n" if chunked else block)
            sent += len(block)
        if chunked:
            sock.sendall(b"0\r\n\r\n")
    except OSError:  # the server refused and closed: what we wanted
        pass
    return sent


@pytest.mark.parametrize("path", ["/api/auth/login", "/api/auth/token", "/api/runs"])
def test_oversized_bodies_are_refused_without_growing(server: Server, path: str) -> None:
    pid = server.proc.pid
    before = rss_kb(pid)
    # 1. A declared 300 MB: refused from the header alone, before a byte of body is read.
    req = RawRequest(server, path, {"Content-Type": "application/json", "Content-Length": str(300 * MB)})
    _send_until_refused(req.sock, 300 * MB, chunked=False)
    status, data = req.response()
    assert status == 413 and b"at most 256 KB" in data, data[:300]
    # 2. Chunked, no Content-Length, 300 MB streamed as fast as we can: counted as it comes.
    req = RawRequest(server, path, {"Content-Type": "application/json", "Transfer-Encoding": "chunked"})
    sent = _send_until_refused(req.sock, 300 * MB, chunked=True)
    status, data = req.response()
    assert status == 413 and b"over 256 KB" in data, data[:300]
    assert sent < 300 * MB, "the server read the whole endless body"
    after = rss_kb(pid)
    print(f"{path}: VmRSS {before} kB -> {after} kB")
    assert after - before < 8 * 1024, f"the appliance grew by {(after - before) >> 10} MB"
    assert server.http.get("/api/health").status_code == 200


def test_normal_bodies_and_uploads_still_pass(server: Server) -> None:
    with httpx.Client(base_url=server.url, headers={"Origin": server.url}, timeout=30) as c:
        r = c.post("/api/auth/login", json={"username": ADMIN_USER, "password": ADMIN_PASSWORD})
        assert r.status_code == 200
    # A JSON body just over the limit, from a logged-in educator: still 413 (the limit is for all).
    big_csv = "username,full name,role\n" + "".join(f"s{i:06d},Student {i},student\n" for i in range(12000))
    assert len(big_csv) > 256 * 1024
    r = server.http.post("/api/users/import", json={"csv": big_csv})
    assert r.status_code == 413, r.text
    # An archive upload far over the JSON limit is the upload route's to judge (its own 64 MB).
    files = {
        p.relative_to(BASE).as_posix(): p.read_bytes()
        for p in BASE.rglob("*")
        if p.is_file() and "build" not in p.relative_to(BASE).parts
    }
    files["data/noise.bin"] = os.urandom(MB)
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as t:
        for name, data in files.items():
            info = tarfile.TarInfo(f"proj/{name}")
            info.size = len(data)
            t.addfile(info, io.BytesIO(data))
    assert len(buf.getvalue()) > MB
    r = server.http.post("/api/projects", files={"file": ("proj.tar.gz", buf.getvalue(), "application/gzip")})
    assert r.status_code == 201, r.text


# ---- X-Forwarded-For ---------------------------------------------------------------------------


def _login_address(server: Server, username: str, password: str, **headers: str) -> str:
    with httpx.Client(base_url=server.url, headers={"Origin": server.url, **headers}, timeout=30) as c:
        r = c.post("/api/auth/login", json={"username": username, "password": password})
        assert r.status_code == 200, r.text
    rows = server.http.get("/api/audit", params={"username": username, "action": "auth.login", "limit": 1}).json()
    return rows[0]["address"]


def test_forwarded_for_is_ignored_without_a_trusted_proxy(server: Server) -> None:
    pw = server.create_user("xff-plain", "student")
    assert _login_address(server, "xff-plain", pw, **{"X-Forwarded-For": "10.9.8.7"}) == "127.0.0.1"


def test_forwarded_for_is_honoured_from_the_trusted_proxy(tmp_path: Path) -> None:
    s = start_server(tmp_path, shared_builds_root(), trusted_proxies=["127.0.0.1"])
    try:
        pw = s.create_user("xff-proxied", "student")
        assert _login_address(s, "xff-proxied", pw, **{"X-Forwarded-For": "10.9.8.7"}) == "10.9.8.7"
    finally:
        stop_server(s)


# ---- lock-out ----------------------------------------------------------------------------------


def _from(server: Server, address: str, cookies: httpx.Cookies | None = None) -> httpx.Client:
    """A client whose connections come from `address` (any 127.x.y.z reaches the loopback)."""
    return httpx.Client(
        base_url=server.url,
        headers={"Origin": server.url},
        timeout=30,
        cookies=cookies,
        transport=httpx.HTTPTransport(local_address=address),
    )


def test_a_guesser_cannot_lock_the_educator_out(tmp_path: Path) -> None:
    s = start_server(tmp_path, shared_builds_root(), login_max_failures_account=12, login_lock_s=30.0)
    try:
        good = {"username": ADMIN_USER, "password": ADMIN_PASSWORD}
        bad = {"username": ADMIN_USER, "password": "not-the-password"}
        # A browser of the educator's, used once before the attack (it holds the device cookie).
        laptop = _from(s, "127.0.0.3")
        assert laptop.post("/api/auth/login", json=good).status_code == 200
        # One anonymous attacker: locks admin for itself only (guesses stay bounded: 5).
        with _from(s, "127.0.0.2") as attacker:
            codes = [attacker.post("/api/auth/login", json=bad).status_code for _ in range(8)]
            assert codes == [401] * 5 + [429] * 3
            assert attacker.post("/api/auth/login", json=good).status_code == 429
        # ...while the educator logs in from another address at once.
        http = login_client(s.url, ADMIN_USER, ADMIN_PASSWORD)  # 127.0.0.1
        http.close()
        # Many addresses (a distributed guesser): the account is locked for addresses it does not
        # know; its known address and the browser with the device cookie still get in.
        for i in range(10, 30):
            with _from(s, f"127.0.1.{i}") as c:
                c.post("/api/auth/login", json=bad)
        with _from(s, "127.0.2.1") as stranger:
            assert stranger.post("/api/auth/login", json=good).status_code == 429
        login_client(s.url, ADMIN_USER, ADMIN_PASSWORD).close()
        assert laptop.post("/api/auth/login", json=good).status_code == 200
        # Same address as the attacker (one NAT): the educator's browser with its device cookie
        # gets in, although the address is locked for admin.
        with _from(s, "127.0.0.2", cookies=laptop.cookies) as same_nat:
            assert same_nat.post("/api/auth/login", json=good).status_code == 200
        laptop.close()
    finally:
        stop_server(s)


# ---- file modes --------------------------------------------------------------------------------


@pytest.fixture
def loose_umask_server(tmp_path: Path) -> Iterator[Server]:
    old = os.umask(0)  # the appliance inherits it: it must not matter
    try:
        s = start_server(tmp_path / "data", shared_builds_root())
    finally:
        os.umask(old)
    yield s
    stop_server(s)


def test_data_files_are_never_world_readable(loose_umask_server: Server) -> None:
    s = loose_umask_server
    pw = s.create_user("modes", "student")
    http, _ws = s.login("modes", pw)  # sessions: accounts.sqlite3 and its WAL/SHM
    http.post("/api/auth/login", json={"username": "modes", "password": "wrong-wrong-wrong"})  # audit
    # runs.sqlite3, the run's folder and its log (when a run can start here: the run sandbox may
    # refuse on a machine without what it needs; the databases are checked either way)
    r = s.http.post("/api/runs", json={"build": "relbot"}, timeout=300)
    if r.status_code == 201:
        s.wait_cycles(r.json()["id"], 100)
        s.stop_run()
    http.close()
    data = s.data_dir
    names = {p.name for p in data.iterdir()}
    assert {"accounts.sqlite3-wal", "accounts.sqlite3-shm", "audit.sqlite3", "runs.sqlite3"} <= names, names
    loose = []
    for p in data.rglob("*"):
        mode = p.lstat().st_mode
        if stat.S_ISLNK(mode):
            continue
        # Files: no 'other' bit. Folders: 'other' may at most search (x), never list or write.
        if (mode & 0o007) if not stat.S_ISDIR(mode) else (mode & 0o006):
            loose.append(f"{p.relative_to(data)} {stat.filemode(mode)}")
    assert not loose, loose
