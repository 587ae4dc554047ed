"""Enrolment: one-time join codes shown on the room page, and ``xrf room join`` on a bench.

The room makes a code (``JoinCodes.new``: 10 characters from an unambiguous alphabet, valid
``CODE_TTL_S``, good for one bench). On the bench, ``xrf room join ROOM_URL CODE --name NAME``
makes the bench's own Ed25519 key pair and posts the code, the name, the bench's public key and
its dashboard address (``EnrolRequest``) to the room (``POST /api/room/enrol``, public but
rate-limited like a login). The room records the bench -- its name, public key and address: what
the room believes about a bench from then on, whatever the bench later says -- and answers
(``EnrolAnswer``) with the bench's broker credentials (a new random password, added with
mosquitto_passwd and live after mosquitto's reload), the broker's address and the room's CA
certificate (TLS), and the room's public signing key (sso.py).

The bench keeps all of it in ``<data>/room/enrolment.json`` (``Enrolment``): 0600 in a 0700
folder, owned by the appliance's user (the owner of the data folder, also when `xrf room join`
runs as root), in the data folder no run's guest can see. A running appliance picks the file up
within seconds. ``read_enrolment`` refuses a file that is not the appliance's own and makes one
that others could read private again (with a warning: its secrets may have been read; re-enrol).

An enrolment made before signed tokens (issue 26: it holds the HMAC ``sso_key`` shared with the
room) is ``Outdated``: the bench still reports to the room and obeys its commands with it, but
sign-on from the room, assignment fetches and collections need ``xrf room join`` again (both
sides say so).
"""

from __future__ import annotations

import ipaddress
import json
import logging
import os
import secrets
import socket
import stat
import time
from pathlib import Path
from typing import Annotated, Any, Literal
from urllib.parse import urlsplit

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from .topics import NAME_RE

log = logging.getLogger(__name__)

CODE_TTL_S = 15 * 60
CODE_ALPHABET = "abcdefghjkmnpqrstuvwxyz23456789"
REENROL = "re-enrol it: make a join code on the room page and run `xrf room join` on the bench"

BenchName = Annotated[str, Field(pattern=NAME_RE.pattern)]
Key = Annotated[str, Field(min_length=40, max_length=48, pattern=r"^[A-Za-z0-9_-]+$")]  # sso.py: 32 bytes
Url = Annotated[str, Field(max_length=200)]


class JoinCodes:
    def __init__(self) -> None:
        self._codes: dict[str, float] = {}

    def new(self, ttl_s: float = CODE_TTL_S) -> tuple[str, float]:
        code = "".join(secrets.choice(CODE_ALPHABET) for _ in range(10))
        expires = time.time() + ttl_s
        self._codes[code] = expires
        return code, expires

    def take(self, code: str) -> bool:
        """True once for a valid, unexpired code (then it is gone)."""
        now = time.time()
        for c in [c for c, t in self._codes.items() if t < now]:
            del self._codes[c]
        code = (code or "").strip().lower()
        for known in list(self._codes):
            if secrets.compare_digest(known, code):
                del self._codes[known]
                return True
        return False

    def pending(self) -> list[dict[str, Any]]:
        now = time.time()
        return [{"code": c, "expires": t} for c, t in self._codes.items() if t >= now]


def check_url(url: str) -> str:
    """A bench's dashboard address as the room records it: http(s)://host[:port], nothing else
    (no user, path, query or fragment); ValueError otherwise."""
    url = (url or "").strip().rstrip("/")
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError:
        raise ValueError(f"dashboard address {url[:80]!r}: not a URL") from None
    if (
        len(url) > 200
        or parts.scheme not in ("http", "https")
        or not parts.hostname
        or parts.username is not None
        or parts.password is not None
        or parts.path not in ("", "/")
        or parts.query
        or parts.fragment
        or (port is not None and not 0 < port < 65536)
    ):
        raise ValueError(f"dashboard address {url[:80]!r}: expected http(s)://host[:port]")
    return url


def default_dashboard_url(room_url: str, port: int) -> str:
    """This bench's address as the room reaches it: the address it reaches the room from."""
    parts = urlsplit(room_url)
    host = parts.hostname or "127.0.0.1"
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    try:
        with socket.socket(family, socket.SOCK_DGRAM) as s:
            s.connect((host, parts.port or 80))  # UDP: nothing is sent; the kernel picks the route
            addr = s.getsockname()[0]
    except OSError:
        addr = "127.0.0.1"
    if ipaddress.ip_address(addr).version == 6:
        addr = f"[{addr}]"
    return f"http://{addr}:{port}"


# ---- the exchange (HTTP) and the file ------------------------------------------------------


class EnrolRequest(BaseModel):
    """``POST /api/room/enrol``: what a joining bench tells the room."""

    code: str = Field(max_length=64)
    name: str = Field(max_length=64)
    bench_key: Key = Field(description="the bench's Ed25519 public key (its tokens to the room)")
    url: Url = Field(description="the bench's dashboard address: where the room sends its educators")


class BrokerLogin(BaseModel):
    model_config = ConfigDict(extra="ignore")

    host: Annotated[str, Field(min_length=1, max_length=253)]
    port: Annotated[int, Field(gt=0, lt=65536)]
    username: BenchName
    password: Annotated[str, Field(min_length=1, max_length=128)]
    ca_pem: Annotated[str, Field(max_length=16384)] = ""  # the room's CA: TLS when set


class EnrolAnswer(BaseModel):
    """The room's answer to a bench it enrolled."""

    model_config = ConfigDict(extra="ignore")

    name: BenchName
    broker: BrokerLogin
    room_key: Key = Field(description="the room's Ed25519 public key: it checks the room's sign-on tokens")


class Enrolment(BaseModel):
    """``<data>/room/enrolment.json``: everything the bench keeps of its room. Secrets: the broker
    password and ``bench_key`` (the bench's private key)."""

    model_config = ConfigDict(extra="ignore")

    version: Literal[2] = 2
    name: BenchName
    room_url: Url = ""
    dashboard_url: Url = ""
    broker: BrokerLogin
    room_key: Key
    bench_key: Key


class Outdated(BaseModel):
    """An enrolment from before signed tokens: the broker login still works, nothing else."""

    model_config = ConfigDict(extra="ignore")

    name: BenchName
    room_url: Url = ""
    broker: BrokerLogin


def enrolment_path(data_dir: Path) -> Path:
    return data_dir / "room" / "enrolment.json"


def _owner(data_dir: Path) -> tuple[int, int]:
    st = data_dir.stat()
    return st.st_uid, st.st_gid


def write_enrolment(data_dir: Path, enrolment: Enrolment) -> Path:
    """Write the file 0600 from its first byte, in a 0700 folder, both owned by the owner of the
    data folder (the appliance's user)."""
    data_dir.mkdir(parents=True, exist_ok=True)
    uid, gid = _owner(data_dir)
    folder = data_dir / "room"
    folder.mkdir(exist_ok=True)
    os.chmod(folder, 0o700)
    if os.geteuid() == 0 and (uid, gid) != (0, 0):
        os.chown(folder, uid, gid)
    path = enrolment_path(data_dir)
    tmp = folder / f".enrolment.json.{secrets.token_hex(4)}"
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
    try:
        os.fchmod(fd, 0o600)
        if os.geteuid() == 0:
            os.fchown(fd, uid, gid)
        with os.fdopen(fd, "w") as f:
            f.write(enrolment.model_dump_json())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


class EnrolmentError(Exception):
    """The file is there but not usable (the message says why and what to do)."""


def read_enrolment(data_dir: Path) -> Enrolment | Outdated | None:
    """The bench's enrolment; None when there is none; EnrolmentError when it is not this
    appliance's own or not readable as one."""
    folder, path = data_dir / "room", enrolment_path(data_dir)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise EnrolmentError(f"{path}: {exc.strerror}; {REENROL} as the appliance's user") from None
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(f.fileno())
        if not stat.S_ISREG(st.st_mode) or st.st_uid != os.geteuid():
            raise EnrolmentError(f"{path} is not a file of this appliance's user (uid {os.geteuid()}); {REENROL}")
        if st.st_mode & 0o077:
            os.fchmod(f.fileno(), 0o600)
            log.warning("room: %s was readable by others (now 0600): its secrets may have been read; %s", path, REENROL)
        text = f.read(1 << 20)
    try:
        if stat.S_IMODE(folder.stat().st_mode) & 0o077:
            os.chmod(folder, 0o700)
    except OSError:
        pass
    try:
        raw = json.loads(text)
    except ValueError:
        raise EnrolmentError(f"{path} is not JSON; {REENROL}") from None
    try:
        if isinstance(raw, dict) and "sso_key" in raw and "bench_key" not in raw:
            return Outdated.model_validate(raw)
        return Enrolment.model_validate(raw)
    except ValidationError as exc:
        raise EnrolmentError(f"{path}: {exc.errors()[0]['msg']}; {REENROL}") from None


def join(
    room_url: str, code: str, name: str, data_dir: Path, dashboard_url: str = "", timeout: float = 20.0
) -> Enrolment:
    """`xrf room join`: ask the room, store what it gives. Raises RuntimeError with the room's
    reason, ValueError for a bad name or address."""
    import httpx

    from ..server.settings import Settings
    from . import sso, topics

    name = topics.check_bench_name(name)
    room_url = room_url.rstrip("/")
    data_dir.mkdir(parents=True, exist_ok=True)
    if os.geteuid() not in (0, _owner(data_dir)[0]):
        raise RuntimeError(f"{data_dir} belongs to another user: run xrf room join as the appliance's user (or root)")
    url = check_url(dashboard_url or default_dashboard_url(room_url, Settings().port))
    key = sso.new_private_key()
    request = EnrolRequest(code=code, name=name, bench_key=sso.public_text(key), url=url)
    r = httpx.post(
        f"{room_url}/api/room/enrol", json=request.model_dump(), timeout=timeout, headers={"Origin": room_url}
    )
    if r.status_code != 200:
        try:
            detail = r.json().get("detail")
        except ValueError:
            detail = r.text[:300]
        raise RuntimeError(f"the room refused: {r.status_code} {detail}")
    try:
        answer = EnrolAnswer.model_validate(r.json())
    except (ValueError, ValidationError):
        raise RuntimeError("the room's answer has no signing key: update the room to this version") from None
    enrolment = Enrolment(
        name=answer.name,
        room_url=room_url,
        dashboard_url=url,
        broker=answer.broker,
        room_key=answer.room_key,
        bench_key=sso.private_text(key),
    )
    write_enrolment(data_dir, enrolment)
    return enrolment
