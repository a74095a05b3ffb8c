"""Whatever a test started is stopped when it ends, even when it fails half-way."""

from __future__ import annotations

import signal

import pytest

from test.nodes.rosutil import STARTED, stop


@pytest.fixture(autouse=True)
def no_leftover_processes():
    before = len(STARTED)
    yield
    for proc in STARTED[before:]:
        stop(proc, signal.SIGKILL, timeout=5.0)
