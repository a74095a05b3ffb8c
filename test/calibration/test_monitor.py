"""The live tracker monitor: still poses out of raw streams in two clocks, a station placed from the first ones,
each judged against the model's own bound; an unchanged robot stays calibrated, a slipped joint is flagged."""

from __future__ import annotations

import pytest

from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.calibration.monitor import DriftMonitor, MonitorOptions
from hybrid_kinematics_ros.simulation.recording import PLACED, RecordingSpec, simulated_recording
from hybrid_kinematics_ros.simulation.trajectory import JointStep

OPTIONS = MonitorOptions(reference_poses=10, window=40)
STEP_AFTER_S = 40.0


def stream(monitor: DriftMonitor, step: JointStep | None = None, seconds: float = 90.0) -> list[tuple[float, object]]:
    """The simulated cell's raw streams fed in stamp order (the tracker's clock 12.3 ms ahead); the statuses
    of the completed still poses with their time (s) on the robot's clock."""
    spec = RecordingSpec(
        seconds=seconds, noise=False, speed=3.0, waypoints=40, tracker_hz=1000.0, frames=PLACED, step=step, seed=3
    )
    rec = simulated_recording(spec).recording
    events = sorted(
        [(int(s), 1, i) for i, s in enumerate(rec.joint_stamps)]
        + [(int(s), 0, i) for i, s in enumerate(rec.pose_stamps)]
    )
    out = []
    for stamp, kind, i in events:
        if kind == 0:
            monitor.tracker(stamp, rec.positions[i], rec.quats[i], rec.pose_frame)
        else:
            status = monitor.joints(stamp, rec.q[i])
            if status is not None:
                out.append(((stamp - rec.joint_stamps[0]) * 1e-9, status))
    return out


def test_an_unchanged_robot_stays_calibrated_from_a_station_placed_on_the_fly(trained):
    _, model, _, _ = trained
    statuses = stream(DriftMonitor(model, OPTIONS))
    assert len(statuses) > OPTIONS.reference_poses + 20
    assert [s.state for _, s in statuses[: OPTIONS.reference_poses - 1]] == ["placing"] * (OPTIONS.reference_poses - 1)
    last = statuses[-1][1]
    assert last.station.startswith("placed from") and last.judged == min(OPTIONS.window, len(statuses) - 10)
    assert not any(s.drifted for _, s in statuses)


def test_a_joint_that_slips_mid_stream_is_flagged_within_the_next_poses(trained):
    _, model, _, _ = trained
    statuses = stream(DriftMonitor(model, OPTIONS), JointStep(1, 1e-3, STEP_AFTER_S), seconds=120.0)
    before = [s for t, s in statuses if t < STEP_AFTER_S]
    after = [s for t, s in statuses if t >= STEP_AFTER_S]
    assert len(before) > OPTIONS.reference_poses and not any(s.drifted for s in before)
    flagged = next(k for k, s in enumerate(after) if s.drifted)
    assert flagged < 30, flagged
    assert "DRIFTED" in after[flagged].message()


def test_options_that_cannot_work_are_refused():
    with pytest.raises(CalibrationError, match="clock_margin_s"):
        MonitorOptions(still_s=0.1, clock_margin_s=0.05)
