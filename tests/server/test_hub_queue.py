"""The per-client queue on its own (no server, no loop): what is dropped, what is kept, when a
client is cut off."""

from __future__ import annotations

import asyncio
import time

import pytest

from xrflab.server.ws.hub import ClientQueue, SlowClient, encode


def test_telemetry_drops_oldest_and_counts() -> None:
    q = ClientQueue(max_telemetry=3, max_total=100, slow_after_s=60)
    for i in range(5):
        q.put("telemetry", f"t{i}")
    assert q.dropped == 2 and len(q) == 3

    async def drain() -> list[str]:
        return [await q.get() for _ in range(3)]

    assert asyncio.run(drain()) == ["t2", "t3", "t4"]


def test_control_messages_jump_the_telemetry_backlog_and_are_never_dropped() -> None:
    q = ClientQueue(max_telemetry=2, max_total=100, slow_after_s=60)
    q.put("telemetry", "t0")
    q.put("state", "s0")
    q.put("alarm", "a0")

    async def drain() -> list[str]:
        return [await q.get() for _ in range(3)]

    assert asyncio.run(drain()) == ["s0", "a0", "t0"]


def test_a_client_behind_for_too_long_is_cut_off() -> None:
    q = ClientQueue(max_telemetry=1, max_total=100, slow_after_s=0.05)
    q.put("telemetry", "t")
    q.put("telemetry", "t")  # first drop: pressure starts
    time.sleep(0.1)  # the point: the pressure lasts longer than slow_after_s
    with pytest.raises(SlowClient):
        q.put("telemetry", "t")


def test_too_many_pending_control_messages_cut_off() -> None:
    q = ClientQueue(max_telemetry=10, max_total=2, slow_after_s=60)
    q.put("state", "1")
    q.put("state", "2")
    with pytest.raises(SlowClient):
        q.put("state", "3")


def test_non_finite_numbers_go_out_as_null() -> None:
    assert (
        encode("telemetry", {"x": float("nan"), "y": [1.0, float("inf")]})
        == '{"type":"telemetry","x":null,"y":[1.0,null]}'
    )
