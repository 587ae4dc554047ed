"""The room's signed tokens in-process (xrflab/room/sso.py): a token is honoured once, by the
bench it names, for its use, with the key that signed it, until it expires; anything else is the
one "invalid" answer. test_room_security.py attacks the same through a room and benches."""

from __future__ import annotations

import base64
import json
import stat
from pathlib import Path

import pytest

from xrflab.room import sso


@pytest.fixture(scope="module")
def room_key():
    return sso.new_private_key()


def _verifier(key, bench: str = "b1", use: str = "sso") -> sso.Verifier:
    return sso.Verifier(sso.load_public(sso.public_text(key)), bench, use)


def _refused(v: sso.Verifier, token: str) -> str:
    with pytest.raises(sso.SsoError) as err:
        v.verify(token)
    return str(err.value)


def test_a_token_names_its_subject_once(room_key) -> None:
    v = _verifier(room_key)
    token = sso.mint(room_key, "b1", "ann")
    assert v.verify(token) == "ann"
    assert "used already" in _refused(v, token)
    assert v.verify(sso.mint(room_key, "b1", "ann")) == "ann"  # a new link works


def test_wrong_bench_use_or_key_is_invalid(room_key) -> None:
    v = _verifier(room_key)
    assert "invalid" in _refused(v, sso.mint(room_key, "b2", "ann"))  # another bench's
    assert "invalid" in _refused(v, sso.mint(room_key, "b1", "a1", use="assignment"))  # another use
    bench_key = sso.new_private_key()
    assert "invalid" in _refused(v, sso.mint(bench_key, "b1", "ann"))  # a bench's own key mints nothing here
    # and the bench's key is honoured where it is expected, for its own uses only
    assert _verifier(bench_key, use="assignment").verify(sso.mint(bench_key, "b1", "a1", use="assignment")) == "a1"


def test_expired_and_too_long_lived_tokens(room_key) -> None:
    v = _verifier(room_key)
    assert "expired" in _refused(v, sso.mint(room_key, "b1", "ann", ttl_s=-1))
    assert "invalid" in _refused(v, sso.mint(room_key, "b1", "ann", ttl_s=sso.TTL_S + sso.SKEW_S + 60))


def test_tampered_or_malformed_tokens_are_the_same_invalid(room_key) -> None:
    v = _verifier(room_key)
    body, sig = sso.mint(room_key, "b1", "ann").split(".")
    claims = json.loads(base64.urlsafe_b64decode(body + "=" * (-len(body) % 4)))
    claims["user"] = "admin"
    forged = base64.urlsafe_b64encode(json.dumps(claims).encode()).decode().rstrip("=")
    # The signature's last two characters changed (to "AA", or "BB" where they were "AA" already:
    # a random signature ends so once in 256 runs, and the token was then the valid one).
    tampered = sig[:-2] + ("BB" if sig.endswith("AA") else "AA")
    for token in (f"{forged}.{sig}", f"{body}.{tampered}", body, f"{body}.{sig}.x", "", "." * 3, "a" * 2000):
        assert _refused(v, token) == "invalid sign-on link", token


def test_the_room_key_is_made_once_and_private(tmp_path: Path) -> None:
    key = sso.room_key(tmp_path / "room")
    path = tmp_path / "room" / "signing.key"
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert sso.public_text(sso.room_key(tmp_path / "room")) == sso.public_text(key)  # read back, not remade
