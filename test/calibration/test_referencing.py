"""Referencing from the calibration data (robust least squares) and the paper's circle fits."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from hybrid_kinematics_ros.calibration import referencing as ref
from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.kinematics import se3
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.simulation.cell import VirtualCell
from hybrid_kinematics_ros.simulation.tracker import Tracker
from hybrid_kinematics_ros.simulation.truth import TrueRobot

EFFECTS = ("geometric", "compliance", "gear", "bending")
FRAMES = {
    "base_to_tracker": {"xyz": [2.4, -1.1, 0.35], "rpy": [0.01, -0.02, 2.2]},
    "flange_to_target": {"xyz": [0.03, 0.02, 0.08], "rpy": [0.3, 0.1, -0.5]},
}


@pytest.fixture(scope="module")
def cell():
    """A UR10 as its URDF says, seen by a noisy tracker in its own frame: then the frames are unique.

    (With robot errors, referencing absorbs the part that looks like a moved base; the parametric stage
    and the benchmark deal with that.)
    """
    cfg = load_robot_config("ur10")
    tracker = Tracker.from_config({**cfg.tracker, **FRAMES})
    robot = TrueRobot.from_config(cfg, enabled=dict.fromkeys(EFFECTS, False))
    return cfg, VirtualCell(cfg, robot, tracker)


def tracker_pairs(cfg, cell, n=3000, seed=0):
    q = np.random.default_rng(seed).uniform(cfg.chain.lower, cfg.chain.upper, (n, cfg.chain.dof))
    T = cell.measure(q, np.random.default_rng(seed + 1))
    return Pairs(q, T, np.arange(n), cfg.chain.joint_names, cell.frame_id)


def errors(a, b):
    pos, rot = se3.pose_errors(a[None], b[None])
    return pos[0], rot[0]


def test_least_squares_finds_both_frames_despite_outliers(cell):
    cfg, cell = cell
    pairs = tracker_pairs(cfg, cell)
    pairs.T[:30, :3, 3] += np.random.default_rng(3).normal(0, 0.05, (30, 3))  # 1 % broken-beam outliers
    found = ref.reference(cfg.chain, pairs)
    assert errors(found.base_to_tracker, cell.tracker.base_to_tracker)[0] < 0.01  # mm, from 15 µm noise
    assert errors(found.flange_to_target, cell.tracker.flange_to_target)[0] < 0.01
    assert errors(found.flange_to_target, cell.tracker.flange_to_target)[1] < 1e-3  # deg
    assert found.outliers == 30
    base = found.to_base(pairs, cfg.chain.base_link)
    assert base.frame_id == cfg.chain.base_link
    pos, _ = se3.pose_errors(base.T[30:], cell.robot.fk(pairs.q[30:]))
    assert pos.mean() < 0.05  # mm: the tracker data now lies on the robot's tip in its base frame


def test_position_only_referencing(cell):
    cfg, cell = cell
    pairs = replace(tracker_pairs(cfg, cell), position_only=True)
    found = ref.reference(cfg.chain, pairs)
    assert found.position_only and np.isnan(found.rms_orientation_deg)
    offset = found.flange_to_target[:3, 3] - cell.tracker.flange_to_target[:3, 3]
    assert np.linalg.norm(offset) < 1e-5
    np.testing.assert_array_equal(found.flange_to_target[:3, :3], np.eye(3))


def test_circle_fit_recovers_a_circle():
    rng = np.random.default_rng(0)
    normal = np.array([0.3, -0.2, 0.93])
    normal /= np.linalg.norm(normal)
    u = np.cross(normal, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    t = np.linspace(0.0, 1.2, 40)
    centre = np.array([1.0, 2.0, 0.5])
    points = centre + 0.7 * (np.cos(t)[:, None] * u + np.sin(t)[:, None] * v) + rng.normal(0, 1e-6, (40, 3))
    c, n, r = ref.fit_circle(points)
    np.testing.assert_allclose(c, centre, atol=2e-5)
    assert abs(abs(n @ normal) - 1.0) < 1e-8 and r == pytest.approx(0.7, abs=1e-5)


def test_circle_referencing_recovers_the_frames_of_a_noise_free_cell(cell):
    cfg, cell = cell
    exact = VirtualCell(
        cfg,
        TrueRobot.from_config(cfg, enabled=dict.fromkeys(("geometric", "compliance", "gear", "bending"), False)),
        replace(cell.tracker, position_noise=0.0, orientation_noise=0.0),
    )
    home = np.array([0.3, -1.2, 1.0, -0.5, 0.8, 0.2])
    q = ref.circle_sweeps(cfg.chain, home, (0, 1, 4, 5), np.radians(60.0), 25)
    found = ref.reference_by_circles(cfg.chain, q, exact.measure(q, np.random.default_rng(0)), home, 25, "tracker")
    assert errors(found.base_to_tracker, cell.tracker.base_to_tracker)[0] < 1e-6
    assert errors(found.flange_to_target, cell.tracker.flange_to_target)[0] < 1e-6
    assert errors(found.flange_to_target, cell.tracker.flange_to_target)[1] < 1e-6


def test_anchoring_on_joint_1_brings_the_base_frame_closer_to_the_robots():
    """With robot errors, least squares on the nominal model puts the base where those errors fit best.
    Anchoring the base on the first joint (after the parametric stage) halves the base-frame error; what
    remains are robot errors that look exactly like a moved base, which no tracker data can separate."""
    from hybrid_kinematics_ros.calibration.parametric import identify

    cfg = load_robot_config("ur10")
    robot = TrueRobot.from_config(cfg)
    cell = VirtualCell(cfg, robot, Tracker.from_config({**cfg.tracker, **FRAMES}))
    pairs = tracker_pairs(cfg, cell, n=2000)
    found = ref.reference(cfg.chain, pairs)
    base = found.to_base(pairs, cfg.chain.base_link)
    stage = identify(cfg.chain, base.q, base.T, cfg.payload_mass, cfg.payload_com, max_pairs=1500)
    anchored, anchored_stage = ref.anchor_base(cfg.chain, found, stage)
    frame0 = [
        i for i, p in enumerate(anchored_stage.params) if p.index == 0 and p.kind in ("zero", "translation", "rotation")
    ]
    assert not np.any(anchored_stage.values[frame0])  # first joint origin and zero offset now in the base
    q = np.random.default_rng(9).uniform(cfg.chain.lower, cfg.chain.upper, (1000, cfg.chain.dof))
    truth = robot.fk(q)
    before = se3.pose_errors(truth, stage.model.fk(q))[0].mean()
    after = se3.pose_errors(truth, anchored_stage.model.fk(q))[0].mean()
    assert after < 0.7 * before
    # in the tracker frame both describe the measurements equally well
    meas = cell.tracker.measure(truth, np.random.default_rng(0))
    for r, st in ((found, stage), (anchored, anchored_stage)):
        pred = se3.inverse(r.base_to_tracker) @ st.model.fk(q) @ r.flange_to_target
        assert se3.pose_errors(meas, pred)[0].mean() < 0.2
