"""The room's tests: a real mosquitto on loopback (started here with the files xrflab.room.broker
writes), real appliances and a real room service. Helpers live in room_support.py."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "appliance"))

from room_support import broker_files, start_broker  # noqa: E402


@pytest.fixture
def broker(tmp_path: Path) -> Iterator[object]:
    """A mosquitto of its own (plain and TLS listeners on free loopback ports)."""
    files = broker_files(tmp_path / "broker")
    proc = start_broker(files)
    yield proc
    proc.stop()
