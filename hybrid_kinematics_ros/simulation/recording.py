"""A raw recording of the simulated cell, as the recorder would write it: joint states at 110 Hz and tracker
poses at their own rate, each stream in its own clock. The tracker's clock is the robot's plus an offset and a
drift, so the alignment's estimates (offset, skew) can be checked against a known truth."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from hybrid_kinematics_ros.io.raw_bag import RawRecording
from hybrid_kinematics_ros.kinematics.robot_config import RobotConfig, load_robot_config
from hybrid_kinematics_ros.kinematics.se3 import pose_from_matrix
from hybrid_kinematics_ros.simulation.cell import VirtualCell
from hybrid_kinematics_ros.simulation.tracker import Tracker
from hybrid_kinematics_ros.simulation.trajectory import JointStep, random_waypoints, through

START_NS = 1_700_000_000_000_000_000  # the robot clock at the recording's first joint state
JOINT_HZ = 110.0

# A tracker metres away from the robot and turned by 126°, with the target off the flange: a real cell's
# layout, where the tracker measures in its own frame (the tests' and benches' "placed" tracker).
PLACED = {
    "base_to_tracker": {"xyz": [2.4, -1.1, 0.35], "rpy": [0.01, -0.02, 2.2]},
    "flange_to_target": {"xyz": [0.03, 0.02, 0.08], "rpy": [0.3, 0.1, -0.5]},
}


@dataclass(frozen=True)
class SimulatedRecording:
    cfg: RobotConfig
    cell: VirtualCell
    trajectory: Callable[[np.ndarray], np.ndarray]  # joints (T, n) at times (T,), s from the start
    recording: RawRecording


@dataclass(frozen=True)
class RecordingSpec:
    """What the simulated cell records: ``waypoints`` random waypoints (from ``seed``) at ``speed`` rad/s for
    ``seconds``, with ``dwell_s`` still at each.

    The tracker's stamps are ``t + offset_s + drift_ppm·1e-6·t`` (t in s of the robot clock from the start);
    it starts 0.1 s before the joints and ends 0.1 s after, at ``tracker_hz``. ``gap``: a beam break, from
    and to (s), with no tracker poses. ``frames``: the tracker's placement and the target's mount (as
    ``PLACED``; None: the config's). ``encoder``: the joint readings' (noise sigma, quantisation step) in
    rad. ``step``: a joint that slips during the recording (the tracker sees it, the joint readings do not)."""

    offset_s: float = 0.0123
    seconds: float = 30.0
    noise: bool = True
    gap: tuple[float, float] | None = None
    speed: float = 0.25
    seed: int = 1
    frames: dict | None = None
    drift_ppm: float = 0.0
    waypoints: int = 30
    tracker_hz: float = 3000.0
    encoder: tuple[float, float] | None = None
    robot: str = "ur10"
    step: JointStep | None = None
    dwell_s: float = 0.3


def simulated_recording(spec: RecordingSpec) -> SimulatedRecording:
    """The simulated cell's raw recording as ``spec`` describes it, with the cell and the joints' path."""
    cfg = load_robot_config(spec.robot)
    cell = VirtualCell.from_config(cfg, noise=spec.noise)
    if spec.frames is not None:
        cell = VirtualCell(cfg, cell.robot, Tracker.from_config({**cfg.tracker, **spec.frames}, noise=spec.noise))
    rng = np.random.default_rng(spec.seed)
    traj = through(random_waypoints(cfg.chain, spec.waypoints, rng), spec.speed, spec.dwell_s)
    tj = np.arange(0.0, spec.seconds, 1 / JOINT_HZ)
    tp = np.arange(-0.1, spec.seconds + 0.1, 1 / spec.tracker_hz)
    if spec.gap is not None:
        tp = tp[(tp < spec.gap[0]) | (tp >= spec.gap[1])]
    p, quat = pose_from_matrix(cell.measure(traj(tp) if spec.step is None else spec.step.reached(traj(tp), tp), rng))
    q = traj(tj)
    if spec.encoder is not None:
        q = np.round((q + rng.normal(0.0, spec.encoder[0], q.shape)) / spec.encoder[1]) * spec.encoder[1]
    rec = RawRecording(
        START_NS + np.round(tj * 1e9).astype(np.int64),
        cfg.chain.joint_names,
        q,
        START_NS + np.round((tp + spec.offset_s + spec.drift_ppm * 1e-6 * tp) * 1e9).astype(np.int64),
        "tracker",
        p,
        quat,
        False,
        Counter(),
    )
    return SimulatedRecording(cfg, cell, traj, rec)
