"""The ground-truth robot: exact when off, each effect of the expected size, gravity-consistent."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from hybrid_kinematics_ros.kinematics import fk, se3
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.simulation.cell import VirtualCell
from hybrid_kinematics_ros.simulation.tracker import Tracker
from hybrid_kinematics_ros.simulation.truth import TrueRobot

EFFECTS = ("geometric", "compliance", "gear", "bending")


@pytest.fixture(scope="module", params=["ur10", "rx160"])
def cfg(request):
    return load_robot_config(request.param)


def joints(cfg, n=2000, seed=0):
    return np.random.default_rng(seed).uniform(cfg.chain.lower, cfg.chain.upper, (n, cfg.chain.dof))


def test_all_effects_off_equals_analytic_fk(cfg):
    robot = TrueRobot.from_config(cfg, enabled=dict.fromkeys(EFFECTS, False))
    q = joints(cfg)
    np.testing.assert_allclose(robot.fk(q), fk.fk(cfg.chain, q), atol=1e-12, rtol=0)


@pytest.mark.parametrize(
    ("effect", "pos_range_mm", "rot_range_deg"),
    [
        ("geometric", (0.2, 5.0), (0.01, 0.5)),
        ("compliance", (0.1, 5.0), (0.005, 0.5)),
        ("gear", (0.01, 0.5), (0.002, 0.05)),
        ("bending", (0.005, 0.5), (0.0005, 0.05)),
    ],
)
def test_each_effect_alone_has_the_expected_size(cfg, effect, pos_range_mm, rot_range_deg):
    robot = TrueRobot.from_config(cfg, enabled={e: e == effect for e in EFFECTS})
    q = joints(cfg)
    pos, rot = se3.pose_errors(robot.fk(q), fk.fk(cfg.chain, q))
    assert pos_range_mm[0] < pos.mean() < pos_range_mm[1]
    assert rot_range_deg[0] < rot.mean() < rot_range_deg[1]


def test_all_effects_are_of_the_papers_order(cfg):
    robot = TrueRobot.from_config(cfg)
    q = joints(cfg, 5000)
    pos, rot = se3.pose_errors(robot.fk(q), fk.fk(cfg.chain, q))
    assert 0.9 < pos.mean() < 3.6  # paper's virtual RX160: 1.8 mm
    assert 0.08 < rot.mean() < 0.35  # and 0.17 degrees


def test_compliance_deflection_changes_sign_with_gravity(cfg):
    robot = TrueRobot.from_config(cfg, enabled={e: e == "compliance" for e in EFFECTS})
    q = joints(cfg, 200, seed=3)
    deflection = robot.effective_joints(q)[0] - q
    torques = robot.gravity_torques(q)
    assert np.all(np.sign(deflection[np.abs(torques) > 1e-3]) == np.sign(torques[np.abs(torques) > 1e-3]))
    upside_down = replace(robot, elastic=replace(robot.elastic, gravity=-robot.elastic.gravity))
    flipped = upside_down.effective_joints(q)[0] - q
    np.testing.assert_allclose(flipped, -deflection, rtol=1e-9, atol=1e-15)


def test_gravity_torque_matches_virtual_work(cfg):
    """τ = -∂V/∂q with V the potential energy: checked by finite differences."""
    robot = TrueRobot.from_config(cfg, enabled=dict.fromkeys(EFFECTS, False))
    q = joints(cfg, 5, seed=4)
    chain = robot.actual

    def potential(qs):
        frames = fk.joint_frames(chain, qs)
        n = chain.dof
        com = np.einsum("bkij,kj->bki", frames[:, :n, :3, :3], chain.segment_com) + frames[:, :n, :3, 3]
        tip = frames[:, n, :3, :3] @ robot.elastic.payload_com + frames[:, n, :3, 3]
        return 9.81 * (com[..., 2] @ chain.segment_mass + robot.elastic.payload_mass * tip[:, 2])

    eps = 1e-6
    numeric = np.stack(
        [-(potential(q + eps * np.eye(6)[j]) - potential(q - eps * np.eye(6)[j])) / (2 * eps) for j in range(6)], 1
    )
    np.testing.assert_allclose(robot.gravity_torques(q), numeric, atol=1e-5)


def test_seeded_and_reproducible(cfg):
    q = joints(cfg, 50)
    a = TrueRobot.from_config(cfg).fk(q)
    np.testing.assert_array_equal(a, TrueRobot.from_config(cfg).fk(q))
    assert np.abs(a - TrueRobot.from_config(cfg, seed=99).fk(q)).max() > 1e-6


def test_tracker_frames_and_noise(cfg):
    rng = np.random.default_rng(0)
    q = joints(cfg, 4000)
    tip = TrueRobot.from_config(cfg).fk(q)
    exact = Tracker(position_noise=0.0, orientation_noise=0.0).measure(tip, rng)
    np.testing.assert_allclose(exact, tip, atol=1e-15)
    noisy = Tracker().measure(tip, rng)
    pos, rot = se3.pose_errors(noisy, tip)
    # per-axis sigma 15 µm: the norm's RMS is sqrt(3) * 15 µm
    assert np.sqrt(np.mean(pos**2)) == pytest.approx(np.sqrt(3) * 0.015, rel=0.05)
    assert np.sqrt(np.mean(rot**2)) == pytest.approx(np.sqrt(3) * 0.001, rel=0.05)
    frames = {
        "base_to_tracker": {"xyz": [2.0, 1.0, 0.5], "rpy": [0.1, 0.2, 3.0]},
        "flange_to_target": {"xyz": [0.0, 0.05, 0.1]},
    }
    tracker = Tracker.from_config(frames, noise=False)
    assert tracker.frame_id == "tracker"
    measured = tracker.measure(tip, rng)
    np.testing.assert_allclose(
        tracker.base_to_tracker @ measured @ se3.inverse(tracker.flange_to_target), tip, atol=1e-12
    )


def test_cell_frame_defaults_to_base_link(cfg):
    cell = VirtualCell.from_config(cfg)
    assert cell.frame_id == cfg.base_link
    blocks = list(cell.samples(1200, seed=1, block=500))
    assert [len(b[0]) for b in blocks] == [500, 500, 200]
