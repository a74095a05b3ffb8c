"""Alignment of 110 Hz joints with 3 kHz tracker poses, on synthetic streams with a known truth."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from hybrid_kinematics_ros.calibration.alignment import AlignOptions, align
from hybrid_kinematics_ros.calibration.clock import estimate_offset
from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.io.raw_bag import RawRecording
from hybrid_kinematics_ros.kinematics import se3
from hybrid_kinematics_ros.simulation.recording import PLACED, START_NS, RecordingSpec, simulated_recording

T0 = START_NS


def recording(**kwargs):
    """(config, cell, trajectory, raw recording) of :func:`simulated_recording`."""
    sim = simulated_recording(RecordingSpec(**kwargs))
    return sim.cfg, sim.cell, sim.trajectory, sim.recording


def test_clock_offset_is_recovered_to_a_fifth_of_a_millisecond():
    for offset in (0.0123, -0.0371):
        cfg, _, _, rec = recording(offset_s=offset)
        assert abs(estimate_offset(cfg.chain, rec) - offset) < 2e-4


def test_offset_is_recovered_with_the_tracker_in_its_own_frame():
    """Tracker positions against base-frame FK gave 106-118 ms here; speed profiles and the fitted frame
    don't care where the tracker stands."""
    cfg, cell, _, rec = recording(frames=PLACED)
    assert cell.frame_id == "tracker"
    result = align(cfg.chain, rec)
    assert abs(result.offset_s - 0.0123) < 2e-4, result.offset_s


def test_long_recordings_keep_the_offset_exact():
    """Over minutes the robot crosses the workspace: one error model for all of it biased the offset by
    0.05 ms after 2 min and 0.12 ms after 10; per-window models keep it within tens of microseconds (24 µs
    with the tracker frame and the skew fitted too, 20 µs with an offset only)."""
    cfg, _, _, rec = recording(seconds=120.0, noise=False, seed=3)
    assert abs(estimate_offset(cfg.chain, rec) - 0.0123) < 5e-5


def test_alignment_error_is_far_below_the_tracker_noise():
    cfg, cell, _, rec = recording(noise=False)
    result = align(cfg.chain, rec, AlignOptions(offset_s=0.0123), frame_id="base_link")
    truth = cell.robot.fk(result.pairs.q)
    pos, _ = se3.pose_errors(result.pairs.T, truth)
    assert np.mean(pos) < 0.001 and np.percentile(pos, 99) < 0.003  # mm: well below 15 µm noise
    assert result.pairs.frame_id == "base_link"
    np.testing.assert_array_equal(result.pairs.stamps, rec.joint_stamps[: len(result.pairs)])


def test_gaps_are_not_bridged_and_nothing_is_extrapolated():
    cfg, _, _, rec = recording(gap=(10.0, 10.3), noise=False)
    result = align(cfg.chain, rec, AlignOptions(offset_s=0.0123, max_gap_s=0.02))
    stamps_s = (result.pairs.stamps - T0) * 1e-9
    assert not np.any((stamps_s > 10.0) & (stamps_s < 10.3))
    assert result.rejected["tracker_gap"] == pytest.approx(0.3 * 110, abs=2)
    # tracker stream starts 0.1 s before the joints and ends 0.1 s after: shift it so joints overhang
    late = RawRecording(
        rec.joint_stamps,
        rec.joint_names,
        rec.q,
        rec.pose_stamps + 500_000_000,
        rec.pose_frame,
        rec.positions,
        rec.quats,
        False,
        Counter(),
    )
    result = align(cfg.chain, late, AlignOptions(offset_s=0.0123))
    assert result.rejected["outside_tracker_stream"] > 0
    assert result.pairs.stamps.min() >= late.pose_stamps[0] - 12_300_000


def test_fast_motion_is_rejected():
    cfg, _, _, rec = recording(speed=1.5, noise=False, seconds=10)
    result = align(cfg.chain, rec, AlignOptions(offset_s=0.0123, max_joint_speed=0.5))
    assert result.rejected["moving_too_fast"] > 0


def test_static_mode_averages_still_windows():
    cfg, cell, traj, rec = recording(seconds=30, speed=1.0)
    result = align(cfg.chain, rec, AlignOptions(offset_s=0.0123, still_min_s=0.2, max_joint_speed=5.0))
    assert 3 <= len(result.pairs) <= len(traj.waypoints) + 1
    pos, _ = se3.pose_errors(result.pairs.T, cell.robot.fk(result.pairs.q))
    assert np.mean(pos) < 0.01  # averaging 0.3 s of 3 kHz samples removes most of the 15 µm noise


def test_static_mode_works_with_encoder_noise_and_quantisation():
    """A 20-bit encoder (6e-6 rad a count) with 2e-6 rad of noise: its 110 Hz derivative is 7e-4 rad/s of
    noise, so a speed threshold of 1e-4 rad/s never saw the robot stand still."""
    encoder = (2e-6, 2 * np.pi / 2**20)
    cfg, cell, traj, rec = recording(seconds=30, speed=1.0, encoder=encoder)
    result = align(cfg.chain, rec, AlignOptions(offset_s=0.0123, still_min_s=0.2, max_joint_speed=5.0))
    assert 0.8 * 30 / traj.period * len(traj.waypoints) <= len(result.pairs) <= len(traj.waypoints) + 1
    pos, _ = se3.pose_errors(result.pairs.T, cell.robot.fk(result.pairs.q))
    assert np.mean(pos) < 0.01


def test_robot_standing_still_cannot_give_an_offset():
    cfg, _, _, rec = recording(seconds=5)
    still = RawRecording(
        rec.joint_stamps,
        rec.joint_names,
        np.repeat(rec.q[:1], len(rec.q), 0),
        rec.pose_stamps,
        rec.pose_frame,
        np.repeat(rec.positions[:1], len(rec.positions), 0),
        np.repeat(rec.quats[:1], len(rec.quats), 0),
        False,
        Counter(),
    )
    with pytest.raises(CalibrationError, match="does not move"):
        estimate_offset(cfg.chain, still)


def position_only(rec):
    """The same recording from a plain reflector: the contract's zero quaternions."""
    return RawRecording(
        rec.joint_stamps,
        rec.joint_names,
        rec.q,
        rec.pose_stamps,
        rec.pose_frame,
        rec.positions,
        np.zeros_like(rec.quats),
        False,
        Counter(),
    )


def test_position_only_recordings_align_without_orientation():
    cfg, cell, _, rec = recording(noise=False)
    plain = position_only(rec)
    for options in (AlignOptions(), AlignOptions(offset_s=0.0123), AlignOptions(offset_s=0.0123, still_min_s=0.2)):
        result = align(cfg.chain, plain, options, frame_id="base_link")
        assert result.pairs.position_only and abs(result.offset_s - 0.0123) < 2e-4
        np.testing.assert_array_equal(
            result.pairs.T[:, :3, :3], np.broadcast_to(np.eye(3), result.pairs.T[:, :3, :3].shape)
        )
        if options == AlignOptions(offset_s=0.0123):  # the estimate is ±0.1 ms: some µm at these speeds
            pos, _ = se3.pose_errors(result.pairs.T, cell.robot.fk(result.pairs.q))
            assert np.mean(pos) < 0.001  # mm


def test_bad_raw_samples_are_dropped_and_counted_by_reason():
    cfg, _, _, rec = recording(noise=False, seconds=20)
    n = len(rec.joint_stamps)
    rec.joint_stamps[101] = rec.joint_stamps[100]  # a duplicate stamp: np.gradient divides by zero
    rec.q[200, 2] = np.nan  # NaN joints crashed FK
    rec.positions[5000] = np.nan
    rec.pose_stamps[7001] = rec.pose_stamps[7000]
    rec.quats[9000] = [0.0, 0.0, 0.0, 2.0]
    for options in (AlignOptions(offset_s=0.0123), AlignOptions()):
        result = align(cfg.chain, rec, options)
        assert result.rejected["joint_state_duplicate_stamp"] == 1
        assert result.rejected["joint_state_nan_or_inf"] == 1
        assert result.rejected["tracker_nan_or_inf"] == 1
        assert result.rejected["tracker_duplicate_stamp"] == 1
        assert result.rejected["tracker_non_unit_quaternion"] == 1
        assert np.all(np.isfinite(result.pairs.T)) and np.all(np.isfinite(result.pairs.q))
        assert len(result.pairs) >= n - 2 - result.rejected["moving_too_fast"]
        assert abs(result.offset_s - 0.0123) < 2e-4


def test_clock_drift_of_20_ppm_over_ten_minutes():
    """20 ppm is 12 ms after 10 minutes. The tracker runs at 500 Hz here to keep the test quick."""
    cfg, _, _, rec = recording(seconds=600.0, drift_ppm=20.0, frames=PLACED, waypoints=200, tracker_hz=500.0)
    result = align(cfg.chain, rec)
    assert abs(result.skew_ppm - 20.0) < 2.0, result.skew_ppm
    t = (rec.joint_stamps - rec.joint_stamps[0]) * 1e-9
    found = result.offset_s + result.skew_ppm * 1e-6 * t
    assert np.max(np.abs(found - (0.0123 + 20e-6 * t))) < 2e-4
