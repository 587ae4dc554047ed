"""Single sign-on from the room to a bench's dashboard: a short-lived token the bench verifies.

The room signs ``{bench, user, exp, nonce}`` with the key it shares with that bench alone (made at
enrolment, HMAC-SHA256): a bench cannot mint tokens for another bench, and a token for one bench is
worthless on the next. The bench checks the signature, its own name, the expiry (``TTL_S``) and
that the nonce was not used before, then opens an ordinary session for that user, who must exist
and be enabled in the bench's own accounts (the class list put them there). Being an ordinary
session, every rule of the bench holds as for a password login: someone else's project or run
still answers as a missing one.

The same tokens, with another ``use``, let a bench prove who it is to the room over HTTP (a bench
signs with its own key; the room checks it with the key it keeps for that bench): ``assignment``
to fetch an assignment's archive too large for MQTT, ``collect`` to upload its runs of an
assignment. A token of one use is refused for any other.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import secrets
import time
from collections import OrderedDict
from typing import Any

TTL_S = 60.0


def _b64(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode()


def _unb64(text: str) -> bytes:
    return base64.urlsafe_b64decode(text + "=" * (-len(text) % 4))


def mint(key: str, bench: str, username: str, ttl_s: float = TTL_S, use: str = "sso") -> str:
    """`username`: who signs on (use ``sso``), or what the bench asks for (an assignment's or a
    collection's id)."""
    body = _b64(
        json.dumps(
            {
                "bench": bench,
                "user": username,
                "exp": time.time() + ttl_s,
                "use": use,
                "nonce": secrets.token_urlsafe(12),
            },
            separators=(",", ":"),
        ).encode()
    )
    mac = _b64(hmac.new(key.encode(), body.encode(), hashlib.sha256).digest())
    return f"{body}.{mac}"


class SsoError(Exception):
    pass


class Verifier:
    def __init__(self, key: str, bench: str, use: str = "sso") -> None:
        self.key = key
        self.bench = bench
        self.use = use
        self._used: OrderedDict[str, float] = OrderedDict()

    def verify(self, token: str) -> str:
        """The username a valid token names; SsoError otherwise (one message for every failure
        but expiry, so a guesser learns nothing)."""
        if not token or len(token) > 1000 or token.count(".") != 1:
            raise SsoError("invalid sign-on link")
        body, mac = token.split(".")
        want = _b64(hmac.new(self.key.encode(), body.encode(), hashlib.sha256).digest())
        if not hmac.compare_digest(mac, want):
            raise SsoError("invalid sign-on link")
        try:
            claims: dict[str, Any] = json.loads(_unb64(body))
        except ValueError:
            raise SsoError("invalid sign-on link") from None
        now = time.time()
        if claims.get("bench") != self.bench or claims.get("use", "sso") != self.use:
            raise SsoError("invalid sign-on link")
        if not isinstance(claims.get("exp"), (int, float)) or claims["exp"] < now:
            raise SsoError("this sign-on link has expired; click the bench in the room again")
        nonce = str(claims.get("nonce", ""))
        while self._used and next(iter(self._used.values())) < now:
            self._used.popitem(last=False)
        if nonce in self._used:
            raise SsoError("this sign-on link was used already; click the bench in the room again")
        self._used[nonce] = claims["exp"]
        return str(claims.get("user", ""))
