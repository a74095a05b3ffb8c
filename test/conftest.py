"""Shared fixtures. Every test session gets its own ROS domain and stays on localhost."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE_ROBOT_DATA = "cmeel.prefix/share/example-robot-data/robots"


@pytest.fixture(scope="session")
def example_robot_data() -> Path:
    import site

    for base in site.getsitepackages():
        path = Path(base) / EXAMPLE_ROBOT_DATA
        if path.is_dir():
            return path
    raise RuntimeError("example-robot-data is not installed; run make bootstrap")
