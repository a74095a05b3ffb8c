"""The capacity selection's folds: which pairs each holds out, and normal equations equal to those of the
pairs it keeps (each fold's are formed as every pair's less its held-out ones')."""

from __future__ import annotations

import numpy as np
import pytest

from hybrid_kinematics_ros.calibration.capacity import FOLDS, MAP_BLOCKS, _Folds, _normal, select_capacity
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
