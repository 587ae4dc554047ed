"""Signed tokens between the room and its benches (Ed25519): single sign-on from the room to a
bench's dashboard, and a bench proving who it is to the room over HTTP.

Signing and checking use different keys, so that nothing a bench holds lets anyone mint a token
that is honoured elsewhere -- or on the bench itself:

- **Sign-on** (use ``sso``): the room signs ``{bench, user, exp, use, nonce}`` with its private
  key (``RoomKey``: ``<room data>/signing.key``, 0600, never leaves the room). A bench checks the
  signature with the room's *public* key, received at enrolment, then its own name, the use, the
  expiry (``TTL_S``; a token that claims to live longer is refused) and that the nonce was not used
  before, and opens an ordinary session for that user, who must exist and be enabled in the
  bench's own accounts, put there by the class list. Everything a bench keeps (its enrolment file,
  its broker password, its own key) together cannot make such a token: a student who read all of
  it is still a student on that bench (tests/room/test_room_security.py).
- **A bench's own uses** (``assignment``: fetch an assignment's archive too large for MQTT;
  ``collect``: upload its runs of an assignment): the bench signs with its own private key, made by
  `xrf room join` on the bench (its public half was given to the room at enrolment). The room
  checks it with that bench's public key only, for that bench's name only: the key gives nothing
  on the room beyond that bench's own fetches and uploads.

A token of one use is refused for any other, and one key's tokens are refused where another key is
expected. Tokens are ``<claims>.<signature>``, both unpadded base64url, the claims a JSON object.
"""

from __future__ import annotations

import base64
import binascii
import secrets
import time
from collections import OrderedDict
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from .topics import NAME_RE

if TYPE_CHECKING:
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey


def _ed25519() -> ModuleType:
    """cryptography's Ed25519, imported when a key is first made, read or used: its Rust extension
    is ~6-10 MB of a process's RSS (issue 30 item 4), and a bench never enrolled in a room (the
    appliance imports this module at start, room/bench.py) never needs it."""
    from cryptography.hazmat.primitives.asymmetric import ed25519

    return ed25519


TTL_S = 60.0
SKEW_S = 30.0  # the signer's clock may be this far ahead of the checker's
MAX_TOKEN = 1000
USES = ("sso", "assignment", "collect")


def _b64(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode()


def _unb64(text: str) -> bytes:
    return base64.urlsafe_b64decode(text + "=" * (-len(text) % 4))


# ---- keys: raw 32 bytes, base64url, in JSON files and the enrolment exchange -------------------


def new_private_key() -> Ed25519PrivateKey:
    return _ed25519().Ed25519PrivateKey.generate()


def private_text(key: Ed25519PrivateKey) -> str:
    from cryptography.hazmat.primitives.serialization import Encoding, NoEncryption, PrivateFormat

    return _b64(key.private_bytes(Encoding.Raw, PrivateFormat.Raw, NoEncryption()))


def public_text(key: Ed25519PrivateKey | Ed25519PublicKey) -> str:
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey as Private
    from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

    pub = key.public_key() if isinstance(key, Private) else key
    return _b64(pub.public_bytes(Encoding.Raw, PublicFormat.Raw))


def _raw32(text: str) -> bytes:
    try:
        raw = _unb64(text) if isinstance(text, str) and len(text) < 64 else b""
    except (binascii.Error, ValueError):
        raw = b""
    if len(raw) != 32:
        raise ValueError("not an Ed25519 key (32 bytes, base64url)")
    return raw


def load_private(text: str) -> Ed25519PrivateKey:
    return _ed25519().Ed25519PrivateKey.from_private_bytes(_raw32(text))


def load_public(text: str) -> Ed25519PublicKey:
    return _ed25519().Ed25519PublicKey.from_public_bytes(_raw32(text))


def room_key(data_dir: Path) -> Ed25519PrivateKey:
    """The room's signing key, made on first use in ``<room data>/signing.key`` (0600)."""
    from .broker import private_write

    path = data_dir / "signing.key"
    try:
        return load_private(path.read_text().strip())
    except FileNotFoundError:
        key = new_private_key()
        data_dir.mkdir(parents=True, exist_ok=True)
        private_write(path, private_text(key) + "\n")
        return key


# ---- tokens ---------------------------------------------------------------------------------


class Claims(BaseModel):
    model_config = ConfigDict(strict=True, extra="forbid")

    bench: Annotated[str, Field(pattern=NAME_RE.pattern)]
    user: Annotated[str, Field(min_length=1, max_length=64)]  # who signs on, or the id asked for
    exp: Annotated[float, Field(ge=0, le=1e11, allow_inf_nan=False)]
    use: Literal["sso", "assignment", "collect"]
    nonce: Annotated[str, Field(min_length=8, max_length=32)]


def mint(key: Ed25519PrivateKey, bench: str, subject: str, ttl_s: float = TTL_S, use: str = "sso") -> str:
    """`subject`: who signs on (use ``sso``), or what the bench asks for (an assignment's or a
    collection's id)."""
    claims = Claims.model_validate(
        {"bench": bench, "user": subject, "exp": time.time() + ttl_s, "use": use, "nonce": secrets.token_urlsafe(12)}
    )
    body = _b64(claims.model_dump_json().encode())
    return f"{body}.{_b64(key.sign(body.encode()))}"


class SsoError(Exception):
    pass


class Verifier:
    """Checks tokens signed by the holder of `public_key`, for `bench` and `use` only. Each nonce
    is accepted once; the memory of used nonces is bounded (``MAX_NONCES``, each kept until its
    token expires, which is at most TTL_S + SKEW_S away)."""

    MAX_NONCES = 10_000

    def __init__(self, public_key: Ed25519PublicKey, bench: str, use: str = "sso") -> None:
        assert use in USES, use
        self.public_key = public_key
        self.bench = bench
        self.use = use
        self._used: OrderedDict[str, float] = OrderedDict()

    def verify(self, token: str) -> str:
        """The subject a valid token names; SsoError otherwise (one message for every failure but
        expiry and reuse, so a guesser learns nothing)."""
        from cryptography.exceptions import InvalidSignature

        invalid = SsoError("invalid sign-on link")
        if not isinstance(token, str) or not token or len(token) > MAX_TOKEN or token.count(".") != 1:
            raise invalid
        body, sig = token.split(".")
        try:
            self.public_key.verify(_unb64(sig), body.encode())
            claims = Claims.model_validate_json(_unb64(body))
        except (InvalidSignature, binascii.Error, ValueError, ValidationError):
            raise invalid from None
        now = time.time()
        if claims.bench != self.bench or claims.use != self.use or claims.exp > now + TTL_S + SKEW_S:
            raise invalid
        if claims.exp < now:
            raise SsoError("this sign-on link has expired; click the bench in the room again")
        while self._used and next(iter(self._used.values())) < now:
            self._used.popitem(last=False)
        if claims.nonce in self._used:
            raise SsoError("this sign-on link was used already; click the bench in the room again")
        if len(self._used) >= self.MAX_NONCES:
            raise SsoError("too many sign-ons at once; try again in a minute")
        self._used[claims.nonce] = claims.exp
        return claims.user
