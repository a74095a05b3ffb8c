"""Error bounds on each answer: the conformal quantile, the distance they grow with, and their coverage on
pairs the model never saw."""

from __future__ import annotations

import numpy as np
import pytest

from hybrid_kinematics_ros.calibration import bounds as calibration_bounds
from hybrid_kinematics_ros.calibration.evaluate import pose_errors_of
from hybrid_kinematics_ros.model.bounds import Bounds, Distance
from hybrid_kinematics_ros.model.errors import ModelError


def test_conformal_quantile_is_the_finite_sample_order_statistic():
    scores = np.random.default_rng(0).permutation(np.arange(1.0, 101.0))
    assert calibration_bounds.conformal_quantile(scores, 0.9) == 91.0  # ⌈101 · 0.9⌉ = 91st smallest
    assert calibration_bounds.conformal_quantile(scores, 0.95) == 96.0
    assert calibration_bounds.conformal_quantile(scores[:10], 0.95) == scores[:10].max()  # too few: the largest


def test_growth_length_recovers_the_trend_of_the_errors():
    d = np.random.default_rng(1).uniform(0.0, 0.4, 4000)
    true = 0.12
    error = 1e-4 * np.sqrt(1.0 + (d / true) ** 2) * np.random.default_rng(2).uniform(0.5, 1.5, len(d))
    length = calibration_bounds.growth_length(d, error)
    assert 0.8 * true < length < 1.25 * true
    # errors that do not grow with the distance give no growth within a robot's reach
    assert calibration_bounds.growth_length(d, np.random.default_rng(3).uniform(0.5, 1.5, len(d))) > 5.0


def test_distance_weighs_each_joint_by_its_lever_arm_and_a_whole_turn_is_no_move(ur10):
    chain = ur10.chain
    q0 = np.array([0.3, -1.2, 1.0, -0.5, 0.7, 0.2])
    arms = calibration_bounds.lever_arms(chain, np.random.default_rng(0).uniform(-2.0, 2.0, (500, 6)))
    assert arms[0] > 0.5 and arms[1] > 0.5 and arms[5] < 0.2  # the shoulder moves the tip most, the flange least
    distance = Distance(q0[None], arms, chain.revolute)
    for j in range(6):
        moved = q0.copy()
        moved[j] += 1e-3
        np.testing.assert_allclose(distance(moved), 1e-3 * arms[j], rtol=1e-6)
        moved[j] = q0[j] + 2 * np.pi
        assert distance(moved)[0] < 1e-12


def test_manifest_round_trip_and_a_malformed_section_names_the_fix():
    made = Bounds(0.95, np.array([1.0, 0.5]), calibration_bounds.ErrorBound(1e-4, 0.3), None, {"validation_pairs": 7})
    again = Bounds.from_manifest(made.manifest())
    assert again.position == made.position and again.orientation is None and again.figures == made.figures
    np.testing.assert_array_equal(again.lever_arms, made.lever_arms)
    with pytest.raises(ModelError, match="retrain"):
        Bounds.from_manifest({"level": 0.95, "position": {"quantile_m": 1e-4}})


def test_bounds_hold_on_pairs_the_model_never_saw(trained):
    _, model, manifest, test_pairs = trained
    assert model.bounds is not None and manifest["bounds"]["level"] == 0.95
    pos_mm, rot_deg = pose_errors_of(model, test_pairs)["hybrid"]
    position, orientation = model.error_bounds(test_pairs.q)
    covered = np.mean(pos_mm <= 1e3 * position), np.mean(rot_deg <= np.degrees(orientation))
    # calibrated at 95 % on the validation blocks; these test blocks never reached the model
    assert min(covered) >= 0.85, covered
    assert np.median(1e3 * position) < 5.0 * np.median(pos_mm)  # a bound, not a wall
    # growth away from the data is measured on the real UR10 (trained on C, tested on B) by bench_bounds
