"""Alignment in windows while recording (issue 17, point 6): the same pairs as the whole recording gives,
in memory that does not grow with the recording's length."""

from __future__ import annotations

import tracemalloc
from collections import Counter

import numpy as np

from hybrid_kinematics_ros.calibration.alignment import AlignOptions, align
from hybrid_kinematics_ros.calibration.clock import error_features, estimate_clock
from hybrid_kinematics_ros.calibration.windowed import StreamingAligner
from hybrid_kinematics_ros.io.raw_bag import RawRecording
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.kinematics.se3 import pose_from_matrix
from hybrid_kinematics_ros.simulation.cell import VirtualCell
from hybrid_kinematics_ros.simulation.trajectory import random_waypoints, through
from test.calibration.test_alignment import PLACED, T0, recording


def feed(aligner: StreamingAligner, rec: RawRecording, chunk_s: float = 1.0) -> list:
    """The streams in arrival order, ``chunk_s`` at a time, polling after each chunk as the recorder does."""
    out = []
    jt, pt = rec.joint_stamps, rec.pose_stamps
    ji = pi = 0
    step = int(chunk_s * 1e9)
    for end in range(int(min(jt[0], pt[0])) + step, int(max(jt[-1], pt[-1])) + 2 * step, step):
        while ji < len(jt) and jt[ji] < end:
            aligner.add_joints(int(jt[ji]), rec.q[ji], int(jt[ji]) + 250_000)
            ji += 1
        while pi < len(pt) and pt[pi] < end:
            aligner.add_pose(int(pt[pi]), (*rec.positions[pi], *rec.quats[pi]), rec.pose_frame)
            pi += 1
        out += aligner.poll()
    return out + aligner.poll(final=True)


def joined(segments: list):
    pairs = [s.result.pairs for s in segments]
    return (
        np.concatenate([p.stamps for p in pairs]),
        np.concatenate([p.T for p in pairs]),
        np.concatenate([s.log_ns for s in segments]),
    )


def test_windows_give_the_pairs_of_the_whole_recording():
    """4 minutes with a 20 ppm drift (1.2 ms a minute), tracker in its own frame, a beam break and bad
    samples: the same joint states are paired and rejected for the same reasons, and the poses agree to
    well under the tracker's 15 µm noise (the windows' clocks are within 0.1 ms of the whole one's)."""
    cfg, _, _, rec = recording(
        seconds=240.0, drift_ppm=20.0, frames=PLACED, waypoints=80, tracker_hz=500.0, gap=(100.0, 100.5)
    )
    rec.q[5000] = np.nan
    rec.quats[60000] *= 2.0
    whole = align(cfg.chain, rec)
    segments = feed(StreamingAligner(cfg.chain), rec)
    assert len(segments) == 4  # three of 60 s, and the rest on stop
    stamps, T, log_ns = joined(segments)
    np.testing.assert_array_equal(stamps, whole.pairs.stamps)  # none twice, none missing
    np.testing.assert_array_equal(log_ns, stamps + 250_000)  # each pair logged when its joint state came in
    rejected = sum((s.result.rejected for s in segments), Counter())
    assert rejected == whole.rejected and rejected["tracker_gap"] > 0, (rejected, whole.rejected)
    t = (whole.pairs.stamps - rec.joint_stamps[0]) * 1e-9
    whole_offset = whole.offset_s + whole.skew_ppm * 1e-6 * t
    for s in segments:
        mine = np.isin(whole.pairs.stamps, s.result.pairs.stamps)
        assert np.max(np.abs(s.clock.offset_at(whole.pairs.stamps[mine]) - whole_offset[mine])) < 1e-4
    diff = np.linalg.norm(T[:, :3, 3] - whole.pairs.T[:, :3, 3], axis=1)
    assert np.mean(diff) < 5e-6 and np.percentile(diff, 99) < 15e-6, (np.mean(diff), np.max(diff))


def test_a_recording_shorter_than_a_window_is_aligned_as_a_whole():
    cfg, _, _, rec = recording(seconds=40.0, tracker_hz=1000.0)
    whole = align(cfg.chain, rec)
    aligner = StreamingAligner(cfg.chain)
    stamps, T, _ = joined(feed(aligner, rec))
    np.testing.assert_array_equal(stamps, whole.pairs.stamps)
    np.testing.assert_array_equal(T, whole.pairs.T)
    clock = aligner.summary_clock()
    assert (clock.offset_s, clock.skew_ppm) == (whole.offset_s, whole.skew_ppm)


def test_memory_is_bounded_whatever_the_length():
    """20 simulated minutes in 1 s chunks: the samples held never exceed what a segment and its context
    need (plus the poll interval and a storage block each), and the peak after 20 minutes is that after 5
    but for where the storage blocks happen to end. The clock is given here, to keep the test quick; with
    an estimated one the same trimming runs."""
    cfg = load_robot_config("ur10")
    cell = VirtualCell.from_config(cfg, noise=True)
    rng = np.random.default_rng(4)
    traj = through(random_waypoints(cfg.chain, 300, rng), 0.25, 0.3)
    hz_j, hz_p, segment_s, context_s = 110.0, 500.0, 60.0, 30.0
    aligner = StreamingAligner(cfg.chain, AlignOptions(offset_s=0.0123), segment_s=segment_s, context_s=context_s)
    bound = (segment_s + 2 * context_s + 1.0 + 2.0) * (hz_j + hz_p) + aligner.joints.BLOCK + aligner.poses.BLOCK
    peaks, pairs = {}, 0
    for second in range(20 * 60):
        tj = second + np.arange(0.0, 1.0, 1 / hz_j)
        tp = second + np.arange(0.0, 1.0, 1 / hz_p)
        p, quat = pose_from_matrix(cell.measure(traj(tp), rng))
        for t, q in zip(tj, traj(tj), strict=True):
            aligner.add_joints(T0 + round(t * 1e9), q)
        for t, v in zip(tp, np.hstack([p, quat]), strict=True):
            aligner.add_pose(T0 + round((t + 0.0123) * 1e9), v, "tracker")
        pairs += sum(len(s.result.pairs) for s in aligner.poll())
        assert aligner.retained <= bound, (second, aligner.retained, bound)
        if second + 1 in (5 * 60, 20 * 60):
            peaks[second + 1] = aligner.peak_retained
    pairs += sum(len(s.result.pairs) for s in aligner.poll(final=True))
    assert peaks[1200] <= peaks[300] + aligner.joints.BLOCK + aligner.poses.BLOCK, peaks
    assert pairs + aligner.rejected.total() == 20 * 60 * 110  # every joint state paired or counted


def test_clock_estimate_memory_does_not_hold_the_error_model_of_the_whole_window():
    """The clock estimate of each window ran on 2 minutes of joint states, and held the FK error features
    and their bases for all of them (2 × 38 MB per 2 minutes at 110 Hz): that memory is what kept the
    recorder's resident memory 195 MB above its start. Two more minutes of recording may now cost the
    estimate no more than those features would for them once (traced, so numpy's arrays are counted)."""
    cfg, _, _, short = recording(seconds=60.0, tracker_hz=250.0, waypoints=20)
    _, _, _, long = recording(seconds=180.0, tracker_hz=250.0, waypoints=60)
    peaks = []
    for rec in (short, long):
        tracemalloc.start()
        estimate_clock(cfg.chain, rec)
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
    extra = len(long.joint_stamps) - len(short.joint_stamps)
    features = extra * 3 * error_features(cfg.chain, short.q[:1]).shape[2] * 8  # bytes
    assert peaks[1] - peaks[0] < features, (peaks, features)
