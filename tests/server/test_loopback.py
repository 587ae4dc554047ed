"""loopback.why_failed: a failed request to one of the appliance's children says what failed,
also when httpx's error has no message (a connection closed under the request: CI, a live
viewer's 502 read "does not answer:" and nothing more). Real sockets on 127.0.0.1."""

from __future__ import annotations

import asyncio
import socket
import struct
import threading

import httpx
import pytest

from xrflab import loopback


def _closing_server(reset: bool) -> tuple[socket.socket, threading.Thread]:
    """A listener that takes one connection, reads the request and closes it unanswered (with an
    RST when `reset`)."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)

    def serve() -> None:
        conn, _ = srv.accept()
        conn.recv(65536)
        if reset:
            conn.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        conn.close()

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    return srv, t


@pytest.mark.parametrize("reset", [False, True], ids=["closed", "reset"])
def test_a_connection_closed_under_the_request_is_named(reset: bool) -> None:
    """As the live stream's read route asks (an async client, a streamed POST): httpx's error
    then has no message at all, closed or reset alike."""
    srv, t = _closing_server(reset)
    url = f"http://127.0.0.1:{srv.getsockname()[1]}/rerun.v1alpha1.MessageProxyService/ReadMessages"

    async def ask() -> None:
        async with loopback.async_client(timeout=5) as c:
            await c.send(c.build_request("POST", url, content=b"\0\0\0\0\0"), stream=True)

    try:
        with pytest.raises(httpx.TransportError) as info:
            asyncio.run(ask())
        t.join(5)
    finally:
        srv.close()
    why = loopback.why_failed(info.value)
    assert why.startswith(type(info.value).__name__) and not why.endswith(":"), why
    assert why == type(info.value).__name__ if not str(info.value).strip() else str(info.value).strip() in why


def test_an_error_without_a_message_is_its_type() -> None:
    assert loopback.why_failed(httpx.ReadError("")) == "ReadError"
    assert loopback.why_failed(httpx.ConnectError("refused")) == "ConnectError: refused"


def test_a_refused_connection_keeps_its_message() -> None:
    with socket.socket() as s:  # a port nobody listens on (bound, never listening)
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        with loopback.client(timeout=5) as c, pytest.raises(httpx.ConnectError) as info:
            c.get(f"http://127.0.0.1:{port}/")
    assert loopback.why_failed(info.value).startswith("ConnectError: ") and "refused" in str(info.value).lower()
