"""uvicorn's server as `xrf serve` runs it (server/cli/serve.py `quiet_server`) does not tick
(issue 30 item 4): its main loop wakes for a stop request only, not once a second to refresh the
Date header, which is made when a response reads it and is the current second's. A real uvicorn
on a free port, in a thread of its own (no signal handlers there: the stop is handle_exit's,
as a signal's)."""

from __future__ import annotations

import signal
import threading
import time
from email.utils import formatdate, parsedate_to_datetime

import httpx
import uvicorn

from xrf_testing.harness import free_port
from xrflab.server.cli.serve import quiet_server


async def app(scope, receive, send) -> None:  # type: ignore[no-untyped-def]
    if scope["type"] == "lifespan":
        while (await receive())["type"] != "lifespan.shutdown":
            await send({"type": "lifespan.startup.complete"})
        await send({"type": "lifespan.shutdown.complete"})
        return
    await send({"type": "http.response.start", "status": 200, "headers": [(b"content-type", b"text/plain")]})
    await send({"type": "http.response.body", "body": b"ok"})


def test_the_server_does_not_tick_and_its_date_is_current() -> None:
    port = free_port()
    server = quiet_server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    ticks: list[float] = []
    on_tick = server.on_tick

    async def counted(counter: int) -> bool:
        ticks.append(time.monotonic())
        return await on_tick(counter)

    server.on_tick = counted
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        url = f"http://127.0.0.1:{port}/"
        deadline = time.monotonic() + 20
        while not server.started:
            assert time.monotonic() < deadline and thread.is_alive(), "uvicorn did not start"
            time.sleep(0.05)  # polling: the server's start
        time.sleep(2.5)  # the point: seconds of a running server whose ticks are counted
        assert len(ticks) == 1, f"uvicorn's main loop ticked {len(ticks)} times in {time.monotonic() - ticks[0]:.1f} s"
        dates = []
        for _ in range(2):
            r = httpx.get(url)
            now = time.time()
            assert r.status_code == 200 and r.text == "ok"
            date = parsedate_to_datetime(r.headers["date"]).timestamp()
            assert now - 1.5 <= date <= now + 0.5, (r.headers["date"], formatdate(now, usegmt=True))
            assert r.headers["server"] == "uvicorn"  # the configured headers too
            dates.append(date)
            time.sleep(1.2)  # the point: the next response in another second
        assert dates[1] > dates[0], dates  # (the tick's could be up to a second old)
        assert len(ticks) == 1
    finally:
        server.handle_exit(signal.SIGINT, None)
        thread.join(20)
    assert not thread.is_alive(), "the stop request did not end the server"
    assert len(ticks) == 2  # the stop's
