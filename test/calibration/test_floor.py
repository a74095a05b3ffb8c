"""The measurement floor told from the data itself: repeated configurations of one station."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from hybrid_kinematics_ros.calibration.fit import reference_all
from hybrid_kinematics_ros.calibration.floor import measurement_floor
from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.simulation.cell import VirtualCell
from hybrid_kinematics_ros.simulation.recording import PLACED
from hybrid_kinematics_ros.simulation.sampling import sample_joints
from hybrid_kinematics_ros.simulation.tracker import Tracker


def _measured_twice(ur10, count: int = 300, noise: bool = True) -> Pairs:
    cell = VirtualCell.from_config(ur10, noise=noise)
    cell = VirtualCell(ur10, cell.robot, Tracker.from_config({**ur10.tracker, **PLACED}, noise=noise))
    q = sample_joints(ur10.chain, count, np.random.default_rng(0))
    return cell.pairs(np.concatenate([q, q]), seed=1)


def test_the_floor_of_a_tracker_with_known_noise_is_what_its_noise_gives(ur10):
    pairs = _measured_twice(ur10)
    floor = measurement_floor([pairs], ur10.chain, reference_all(ur10.chain, [pairs]))
    sigma = 1e-3 * ur10.tracker.get("position_noise_mm", 0.015)  # per axis, m
    expected_mm = 1e3 * sigma * np.sqrt(8.0 / np.pi)  # the mean length of a 3-D Gaussian error
    assert floor.pairs == 300
    assert floor.position_mm == pytest.approx(expected_mm, rel=0.15)
    assert "x the floor of this data" in floor.line(2 * floor.position_mm)


def test_without_noise_the_floor_is_nothing_and_without_repeats_it_is_unknown(ur10):
    quiet = _measured_twice(ur10, 200, noise=False)  # each pose again 2 s later
    assert measurement_floor([quiet], ur10.chain, reference_all(ur10.chain, [quiet])).position_mm < 1e-6
    once = quiet.subset(np.arange(200))
    assert measurement_floor([once], ur10.chain, reference_all(ur10.chain, [once])) is None
    # the same joints read again within a second are one stop, not a repeat
    stop = replace(quiet, stamps=quiet.stamps // 1000)
    assert measurement_floor([stop], ur10.chain, reference_all(ur10.chain, [stop])) is None


def test_a_model_of_data_without_repeats_records_no_floor(trained):
    _, _, manifest, _ = trained
    assert "floor" in manifest and manifest["floor"] is None
