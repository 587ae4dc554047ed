"""Enrolment: one-time join codes shown on the room page, and ``xrf room join`` on a bench.

The room makes a code (``JoinCodes.new``: 10 characters from an unambiguous alphabet, valid
``CODE_TTL_S``, good for one bench). On the bench, ``xrf room join ROOM_URL CODE --name NAME``
posts the code to the room (``POST /api/room/enrol``, public but rate-limited like a login); the
room answers with the bench's broker credentials (a new random password, added with
mosquitto_passwd and live after mosquitto's reload), the broker's address and the room's CA
certificate (TLS), and the key for single sign-on. The bench keeps them in
``<data>/room/enrolment.json`` (0600); a running appliance picks the file up within seconds.
"""

from __future__ import annotations

import json
import os
import secrets
import time
from pathlib import Path
from typing import Any

CODE_TTL_S = 15 * 60
CODE_ALPHABET = "abcdefghjkmnpqrstuvwxyz23456789"


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


def write_enrolment(data_dir: Path, enrolment: dict[str, Any]) -> Path:
    folder = data_dir / "room"
    folder.mkdir(parents=True, exist_ok=True)
    os.chmod(folder, 0o700)
    path = folder / "enrolment.json"
    tmp = folder / ".enrolment.json.tmp"
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        json.dump(enrolment, f)
    os.replace(tmp, path)
    return path


def join(
    room_url: str, code: str, name: str, data_dir: Path, dashboard_url: str = "", timeout: float = 20.0
) -> dict[str, Any]:
    """`xrf room join`: ask the room, store what it gives. Raises RuntimeError with the room's reason."""
    import httpx

    from . import topics

    name = topics.check_bench_name(name)
    room_url = room_url.rstrip("/")
    r = httpx.post(
        f"{room_url}/api/room/enrol", json={"code": code, "name": name}, timeout=timeout, headers={"Origin": room_url}
    )
    if r.status_code != 200:
        try:
            detail = r.json().get("detail")
        except ValueError:
            detail = r.text
        raise RuntimeError(f"the room refused: {r.status_code} {detail}")
    enrolment = r.json()
    enrolment["room_url"] = room_url
    if dashboard_url:
        enrolment["dashboard_url"] = dashboard_url.rstrip("/")
    write_enrolment(data_dir, enrolment)
    return enrolment
