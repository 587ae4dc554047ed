"""Fixtures of the host-side suites: a real segment, as the appliance maps it."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from xrf_testing.testloop import create_for_test
from xrflab import channels
from xrflab.channels import Channels


@pytest.fixture
def ch(shm_name: str) -> Iterator[Channels]:
    """A segment made for the test (create_for_test: the loop's side played from Python), removed
    after it."""
    c = create_for_test(shm_name)
    yield c
    c.close()
    channels.shm_path(shm_name).unlink(missing_ok=True)
