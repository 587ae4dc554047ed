"""Downloads that wait for the heavy-child turn do not take the appliance's default executor.

A class downloading its logs at once queues on the one heavy-child turn (logs/convert_child.py);
each waiting download sat in a thread of asyncio's default executor (6 threads on a 2-core
machine), so everything else the appliance does off the event loop (a run's end, uploads, the
editor) stopped behind them until the turn came round (server/http/logs.py `_downloads`).
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from xrf_testing.writers import xrflog_segment

VARIABLES = [("g_a", 5), ("g_b", 3)]
DOWNLOADS = 10  # more than the default executor's threads here and on a Pi 4 (6 and 8)


# live: each download converts in a child (server/http/logs.py `_cached`, a private name of the
# appliance the fast tier's walk does not see into)
@pytest.mark.live
def test_waiting_downloads_leave_the_default_executor_free(tmp_path: Path) -> None:
    from xrflab.logs.convert_child import acquire_heavy, release_heavy
    from xrflab.server.http import logs

    run_dir = tmp_path / "run"
    run_dir.mkdir()
    for i in range(DOWNLOADS):
        (run_dir / f"log{i}.xrflog").write_bytes(xrflog_segment(VARIABLES, [[r * 0.5, r] for r in range(50 + i)]))
    cache = tmp_path / "cache"

    async def scenario() -> list[Path]:
        assert acquire_heavy(timeout=0), "another test holds the heavy-child turn"
        held = True
        try:
            downloads = [
                asyncio.ensure_future(logs._cached(run_dir, f"log{i}.xrflog", "mat", cache, []))
                for i in range(DOWNLOADS)
            ]
            await asyncio.sleep(1.0)  # every download has reached its wait for the turn
            assert not any(d.done() for d in downloads), "a conversion ran without the turn"
            # The default executor still runs other work while all of them wait (before: every
            # thread of it waited for the turn, HEAVY_WAIT_S = 120 s).
            assert await asyncio.wait_for(asyncio.to_thread(lambda: 42), timeout=30) == 42
            release_heavy()
            held = False
            return list(await asyncio.wait_for(asyncio.gather(*downloads), timeout=240))
        finally:
            if held:
                release_heavy()

    targets = asyncio.run(scenario())
    assert len(targets) == DOWNLOADS
    for t in targets:
        assert t.read_bytes()[:6] == b"MATLAB", t
