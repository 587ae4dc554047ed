"""Fixtures for the log reader/converter suite: a table of edge values for all six types."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))  # writers.py

from log_cases import VARIABLES, edge_rows  # noqa: E402
from writers import xrflog_segment  # noqa: E402


@pytest.fixture
def edge_file(tmp_path: Path) -> Path:
    path = tmp_path / "edge.xrf"
    path.write_bytes(xrflog_segment(VARIABLES, edge_rows()))
    return path
