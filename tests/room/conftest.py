"""The room's tests: a real mosquitto on loopback (started here with the files xrflab.room.broker
writes), real appliances and a real room service. Helpers live in room_support.py."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from xrf_testing.room_support import broker_files, start_broker


@pytest.fixture
def broker(tmp_path: Path) -> Iterator[object]:
    """A mosquitto of its own (plain and TLS listeners on free loopback ports)."""
    files = broker_files(tmp_path / "broker")
    proc = start_broker(files)
    yield proc
    proc.stop()
