"""Shared fixtures. Every test session gets its own ROS domain and stays on localhost.

``trained`` is a small hybrid model, trained for real once per session on the virtual UR10.
"""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from hybrid_kinematics_ros.calibration import train
from hybrid_kinematics_ros.calibration.fit import fit, split
from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.simulation.cell import VirtualCell

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


SAMPLES = 4000
SECONDS = 12.0


@pytest.fixture(scope="session")
def ur10():
    return load_robot_config("ur10")


@pytest.fixture(scope="session")
def virtual_pairs(ur10):
    cell = VirtualCell.from_config(ur10, noise=False)
    q, T = next(cell.samples(SAMPLES, seed=5, block=SAMPLES))
    return Pairs(q, T, 10**9 + 10**7 * np.arange(SAMPLES), ur10.chain.joint_names, "base_link")


@pytest.fixture(scope="session")
def trained(ur10, virtual_pairs, tmp_path_factory):
    out = tmp_path_factory.mktemp("models") / "small"
    tr, va, te = split(virtual_pairs, seed=0)
    preset = replace(train.PRESETS["fast"], arch="mlp:64x2:silu")
    model, manifest = fit(ur10.chain, tr, va, te, out, preset, SECONDS / 60.0, seed=0)
    return out, model, manifest, te
