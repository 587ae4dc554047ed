"""httpx clients for the appliance's own children on 127.0.0.1 (the run's rerun proxy, viser).

The environment's web proxy is not theirs: with HTTP_PROXY/ALL_PROXY set (a lab's network), httpx
sent these requests to the lab's proxy, which cannot reach this machine's 127.0.0.1 (the live
viewer got a 502, the live sender's batches were refused). And plain http needs no certificates:
loading the CA bundle for each client cost 25-110 ms (issue 31 bug 6). One definition, here.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import httpx

_LOOPBACK: dict[str, Any] = {"trust_env": False, "verify": False}


def client(**kw: Any) -> httpx.Client:
    import httpx  # on first use, as where these were made before (not at the appliance's start)

    return httpx.Client(**_LOOPBACK, **kw)


def async_client(**kw: Any) -> httpx.AsyncClient:
    import httpx

    return httpx.AsyncClient(**_LOOPBACK, **kw)


def why_failed(exc: BaseException) -> str:
    """A failed loopback request in words for the one who asked: the error's type and its message
    (a connection closed under the request is an httpx.ReadError with no message at all: CI, a
    live viewer's 502 that said "does not answer:" and nothing more)."""
    text = str(exc).strip()
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__
