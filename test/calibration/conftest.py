"""A small trained model shared by the calibration tests (trained once per session, for real)."""

from __future__ import annotations

from dataclasses import replace

import pytest

from hybrid_kinematics_ros.calibration import train
from hybrid_kinematics_ros.calibration.fit import fit, split
from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.simulation.cell import VirtualCell

SAMPLES = 4000
SECONDS = 12.0


@pytest.fixture(scope="session")
def ur10():
    return load_robot_config("ur10")


@pytest.fixture(scope="session")
def virtual_pairs(ur10):
    cell = VirtualCell.from_config(ur10, noise=False)
    q, T = next(cell.samples(SAMPLES, seed=5, block=SAMPLES))
    return Pairs(q, T, 10**9 + 10**7 * __import__("numpy").arange(SAMPLES), ur10.chain.joint_names, "base_link")


@pytest.fixture(scope="session")
def trained(ur10, virtual_pairs, tmp_path_factory):
    out = tmp_path_factory.mktemp("models") / "small"
    tr, va, te = split(virtual_pairs, seed=0)
    preset = replace(train.PRESETS["fast"], arch="mlp:64x2:silu")
    model, manifest = fit(ur10.chain, tr, va, te, out, preset, SECONDS / 60.0, seed=0)
    return out, model, manifest, te
