"""The run life cycle (server/runs/lifecycle.py): one ordered list of observers, told in order, none
able to keep the next from hearing; and the app registers host logging, the 3D view, the lease
and the ROS bridge in the documented order."""

from __future__ import annotations

import asyncio
import sqlite3
from pathlib import Path
from typing import Any

import pytest

from xrf_testing.harness import free_port
from xrflab.server.runs.lifecycle import RunLifecycle, RunObserver
from xrflab.server.runs.store import RunRow, RunStore


class Recording(RunObserver):
    def __init__(self, name: str, heard: list[tuple[str, str, Any]], fail: str = "") -> None:
        self.name = name
        self._heard = heard
        self._fail = fail

    def on_started(self, run: Any) -> None:
        self._heard.append((self.name, "started", run.row.id))
        if self._fail == "started":
            raise RuntimeError("broken on start")

    def on_samples(self, run: Any, samples: Any) -> None:
        self._heard.append((self.name, "samples", len(samples)))
        if self._fail == "samples":
            raise RuntimeError("broken on samples")

    async def on_ended(self, row: RunRow, run: Any) -> None:
        self._heard.append((self.name, "ended", row.log_records))
        if self._fail == "ended":
            raise RuntimeError("broken on end")


class CountingLogs(RunObserver):
    """Adds to the record once the loop process is gone, as host logging does."""

    name = "logs"

    def __init__(self, store: RunStore) -> None:
        self._store = store

    async def on_exited(self, run: Any) -> None:
        await asyncio.sleep(0)  # an observer may await (host logging drains in a thread)
        run.row = self._store.update(run.row.id, log_records=42)


class FakeRunHolder:
    """Only what the observers here read of a supervisor.Run: its record."""

    def __init__(self, row: RunRow) -> None:
        self.row = row


def test_observers_are_told_in_order_and_a_broken_one_does_not_stop_the_next(tmp_path: Path) -> None:
    store = RunStore(tmp_path / "runs.db")
    try:
        row = store.create("relbot", "relbot", "", "")
        run = FakeRunHolder(row)
        heard: list[tuple[str, str, Any]] = []
        lc = RunLifecycle()
        lc.register(CountingLogs(store))
        lc.register(Recording("a", heard, fail="started"))
        lc.register(Recording("b", heard, fail="samples"))
        lc.register(Recording("c", heard, fail="ended"))
        lc.register(Recording("d", heard))
        with pytest.raises(ValueError):
            lc.register(lc.observers[1])  # twice would tell it twice

        lc.started(run)  # type: ignore[arg-type]
        lc.samples(run, [1, 2, 3])  # type: ignore[arg-type]
        lc.samples(run, [4])  # type: ignore[arg-type]
        asyncio.run(lc.exited(run))  # type: ignore[arg-type]
        asyncio.run(lc.ended(row, run))  # type: ignore[arg-type]

        assert [h for h in heard if h[1] == "started"] == [
            ("a", "started", row.id),
            ("b", "started", row.id),
            ("c", "started", row.id),
            ("d", "started", row.id),
        ]
        # b broke on its first batch: it gets no more samples, the others get every batch
        assert [h for h in heard if h[1] == "samples"] == [
            ("a", "samples", 3),
            ("b", "samples", 3),
            ("c", "samples", 3),
            ("d", "samples", 3),
            ("a", "samples", 1),
            ("c", "samples", 1),
            ("d", "samples", 1),
        ]
        # every observer sees what host logging added when the process exited; c's failure stops nobody
        assert [h for h in heard if h[1] == "ended"] == [
            ("a", "ended", 42),
            ("b", "ended", 42),
            ("c", "ended", 42),
            ("d", "ended", 42),
        ]
    finally:
        store.close()


def test_a_recovered_run_ends_without_a_run_object(tmp_path: Path) -> None:
    store = RunStore(tmp_path / "runs.db")
    try:
        row = store.create("relbot", "relbot", "", "")
        heard: list[tuple[str, str, Any]] = []
        lc = RunLifecycle()
        lc.register(Recording("a", heard))
        asyncio.run(lc.ended(row, None))
        assert heard == [("a", "ended", row.log_records)]
    finally:
        store.close()


def test_the_app_registers_its_observers_in_the_documented_order(tmp_path: Path) -> None:
    """Host logging first (the ended run's record then has its log counts), then the 3D view,
    the lease, live tuning, the ROS bridge (docs/developers/adding-a-run-observer.md). Nobody else reacts to a
    run's end by reading the hub's messages: the hub's only listener left is the room's."""
    from xrflab.server.app import create_app
    from xrflab.server.settings import Settings

    settings = Settings(data_dir=tmp_path / "data", port=free_port(), prepare_viewer_at_start=False)
    app = create_app(settings)

    async def main() -> tuple[list[str], int]:
        async with app.router.lifespan_context(app):
            sup = app.state.supervisor
            return [o.name for o in sup.lifecycle.observers], len(sup.hub.listeners)

    names, listeners = asyncio.run(main())
    assert names == ["host logging", "3D view", "bench lease", "live tuning", "ROS 2 bridge"]
    assert listeners == 0  # this bench is not enrolled in a room
    with sqlite3.connect(settings.runs_db) as db:  # the lifespan really ran against this folder
        assert db.execute("select count(*) from runs").fetchone() == (0,)
