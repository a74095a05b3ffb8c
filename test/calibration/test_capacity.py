"""The capacity selection's folds: which pairs each holds out, and normal equations equal to those of the
pairs it keeps (each fold's are formed as every pair's less its held-out ones'); the orientation residuals'
weight, chosen from the noise each kind carries."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hybrid_kinematics_ros.calibration.capacity import (
    FOLDS,
    MAP_BLOCKS,
    Capacity,
    _Folds,
    _normal,
    _Selection,
    curve_line,
    learning_curve,
    select_capacity,
)
from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.calibration.parametric import linearise
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.simulation.truth import TrueRobot


@pytest.fixture(scope="module")
def lin():
    cfg = load_robot_config("ur10")
    robot = TrueRobot.from_config(cfg)
    q = np.random.default_rng(3).uniform(cfg.chain.lower, cfg.chain.upper, (700, cfg.chain.dof))
    T = robot.fk(q)
    T[::97, :3, 3] += 2e-3  # a few outliers, so that the robust weights are not all one
    return linearise(cfg.chain, q, T, payload_mass=cfg.payload_mass, payload_com=cfg.payload_com, harmonics=2)


def _stretches(mask: np.ndarray) -> int:
    """How many separate runs of held-out pairs ``mask`` holds."""
    return int(np.count_nonzero(np.diff(mask.astype(int)) == 1) + mask[0])


@pytest.mark.parametrize("interleaved", [False, True])
def test_each_fold_holds_out_its_blocks_and_solves_the_rest(lin, interleaved):
    total = len(lin.pick)
    blocks = MAP_BLOCKS if interleaved else 20
    folds = _Folds.build(lin, total, interleaved=interleaved, base=_normal(lin), blocks=blocks)
    held = np.array(folds.held)
    in_order = held[:, np.argsort(lin.pick)]  # the pairs as recorded
    assert (held.sum(axis=0) == 1).all()  # every pair held out exactly once
    for f in range(FOLDS):
        # a contiguous fifth of the recording, or every fifth short block of it
        assert _stretches(in_order[f]) == (blocks // FOLDS if interleaved else 1)
        assert abs(held[f].sum() - total / FOLDS) <= blocks / FOLDS + 1
    # each fold's normal equations are those of the pairs it keeps, with the same robust weights
    base = _normal(lin)
    assert base.weight.min() < 0.9  # the outliers are down-weighted
    for f in (0, FOLDS - 1):
        keep = ~held[f]
        a = base.jacobian[keep].reshape(-1, len(base.columns))
        w = base.weight[keep].reshape(-1)
        np.testing.assert_allclose(folds.normal[f], a.T @ (w[:, None] * a), rtol=1e-8, atol=1e-8 * np.abs(a).max() ** 2)
        np.testing.assert_allclose(folds.gradient[f], a.T @ (w * lin.residual[keep].reshape(-1)), rtol=1e-8, atol=1e-14)


def test_a_few_pairs_still_get_every_fold():
    """20 pairs (the fewest a stage takes): the map's folds use as many blocks as there are pairs, so each
    holds out some and keeps some, and the selection runs through."""
    cfg = load_robot_config("ur10")
    q = np.random.default_rng(4).uniform(cfg.chain.lower, cfg.chain.upper, (20, cfg.chain.dof))
    T = TrueRobot.from_config(cfg).fk(q)
    few = linearise(cfg.chain, q, T, payload_mass=cfg.payload_mass, payload_com=cfg.payload_com, harmonics=2)
    chosen = select_capacity(few, len(q))
    assert [d["setting"] for d in chosen.decisions][-2:] == ["map_step", "orientation_length"]
    folds = _Folds.build(few, len(q), interleaved=True, base=_normal(few), blocks=MAP_BLOCKS)
    assert all(0 < h.sum() < len(q) for h in folds.held)


def test_reweighting_is_the_problem_linearised_at_that_weight():
    cfg = load_robot_config("ur10")
    q = np.random.default_rng(5).uniform(cfg.chain.lower, cfg.chain.upper, (60, cfg.chain.dof))
    T = TrueRobot.from_config(cfg).fk(q)
    options = {"payload_mass": cfg.payload_mass, "payload_com": cfg.payload_com, "harmonics": 2}
    at_one = linearise(cfg.chain, q, T, **options)
    direct = linearise(cfg.chain, q, T, orientation_length=0.25, **options)
    moved = at_one.reweighted(0.25)
    assert moved.orientation_length == direct.orientation_length == 0.25
    for name in ("residual", "jacobian", "joint_rows"):
        np.testing.assert_allclose(getattr(moved, name), getattr(direct, name), rtol=1e-9, atol=1e-15)
    assert not np.allclose(at_one.residual[:, 3:], direct.residual[:, 3:])


def _noisy(position_noise: float, orientation_noise: float, count: int = 400):
    """A UR10 cell measured with the given noise per axis (m, rad), linearised for the selection."""
    cfg = load_robot_config("ur10")
    rng = np.random.default_rng(6)
    q = rng.uniform(cfg.chain.lower, cfg.chain.upper, (count, cfg.chain.dof))
    T = TrueRobot.from_config(cfg).fk(q)
    T[:, :3, :3] = T[:, :3, :3] @ Rotation.from_rotvec(rng.normal(0.0, orientation_noise, (count, 3))).as_matrix()
    T[:, :3, 3] += rng.normal(0.0, position_noise, (count, 3))
    return linearise(cfg.chain, q, T, payload_mass=cfg.payload_mass, payload_com=cfg.payload_com, harmonics=2)


@pytest.mark.parametrize("orientation_noise", [2e-4, 2e-6])
def test_the_orientation_weight_follows_the_noise_of_each_kind(orientation_noise):
    """20 µm per axis in position: 200 µrad in orientation makes the data's ratio about 0.1 m per rad, 2 µrad
    about 10 (less what the stage cannot fit of the truth, which adds to the position residuals); a fixed
    weight of 1 would be 10x off either way."""
    lin = _noisy(2e-5, orientation_noise)
    chosen = select_capacity(lin, len(lin.pick))
    decision = chosen.decisions[-1]
    assert decision["setting"] == "orientation_length"
    expected = 2e-5 / orientation_noise
    settled = decision["ratios"][-1]["weight"]
    assert expected / 2 < settled < expected * 2
    # the kept weight is one of those tried, and the stage is identified with it
    assert chosen.orientation_length == decision["chosen"] in [c["candidate"] for c in decision["candidates"]]
    assert chosen.identify_options()["orientation_length"] == chosen.orientation_length


def test_a_given_orientation_weight_is_kept_and_a_bad_one_refused(lin):
    chosen = select_capacity(lin, len(lin.pick), {"orientation_length": 0.3})
    assert chosen.orientation_length == 0.3
    assert chosen.decisions[-1] == {"setting": "orientation_length", "chosen": 0.3, "given": True}
    with pytest.raises(CalibrationError, match="orientation_length -1: give a positive weight"):
        select_capacity(lin, len(lin.pick), {"orientation_length": -1.0})


def test_a_thinned_fold_is_the_fit_on_the_blocks_it_keeps(lin):
    selection = _Selection(lin, len(lin.pick), {}, None)
    use = selection.stage_columns("bending", 2)
    prior = selection.prior(30.0)
    left, _ = selection.thinned_residuals(use, prior, 2)
    folds, base = selection.folds, selection.base
    for f in (0, FOLDS - 1):
        training = ~folds.held[f]
        keep = training & np.isin(folds.block, np.unique(folds.block[training])[::2])
        assert 0 < keep.sum() < training.sum()
        idx = np.flatnonzero(use)
        a = base.jacobian[keep][:, :, idx].reshape(-1, len(idx))
        w = base.weight[keep].reshape(-1)
        z = np.zeros(len(folds.columns))
        normal = a.T @ (w[:, None] * a) + np.diag(prior[idx])
        z[idx] = -np.linalg.solve(normal, a.T @ (w * lin.residual[keep].reshape(-1)))
        np.testing.assert_allclose(left[folds.held[f]], folds.residual(f, z), atol=1e-8)


def test_the_learning_curve_falls_with_more_poses_and_says_so(lin):
    curve = learning_curve(_Selection(lin, len(lin.pick), {}, None), Capacity("bending", 2, 30.0, 0.0, 0.03))
    held, fitted = curve["held_out_position_mm"], curve["fitted_position_mm"]
    assert curve["shares"] == sorted(curve["shares"]) and curve["shares"][-1] == 1.0
    assert held[0] > held[-1]  # a quarter of the poses pins the stage down worse than all of them
    assert fitted[-1] <= held[-1]
    line = curve_line(curve, floor_mm=fitted[-1] / 2)
    assert "2.0x the floor" in line and ("would help" in line or "would not measurably help" in line)
