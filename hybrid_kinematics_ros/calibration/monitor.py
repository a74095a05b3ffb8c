"""Drift noticed while serving: the tracker's live poses judged against the served model.

The monitor takes the joint states and the tracker's poses as they arrive, each in its own clock. It judges
the robot where it stands still (the paper's static measurement): while no joint moves more than
``still_tolerance_rad``, for ``still_s``, the tracker's poses of the run's middle part are averaged into one
pose. ``clock_margin_s`` at each end of that part absorbs a tracker clock offset up to that size. Each still
run gives one pose.

A tracker station the model does not know is placed from the first ``reference_poses`` poses, through the
model (:func:`~hybrid_kinematics_ros.calibration.verify.place_station`); the poses after them are judged. Each
judged pose is compared with the model's own error bounds at its configuration, over the last ``window`` poses.
As in ``verify``, "drifted" needs more poses beyond a bound than the bound's validation pairs had, with a
significance of ``p_value`` (Fisher's exact test, :func:`~.verify.drift_p_value`; position and orientation
each on its own, Bonferroni over the two). The test is repeated at every pose, so its level is stricter than
``verify``'s.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.calibration.evaluate import target_errors
from hybrid_kinematics_ros.calibration.verify import drift_p_value, place_station
from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.model.hybrid import HybridModel
from hybrid_kinematics_ros.model.referencing import Referencing

NS = 1e-9
TRACKER_KEPT_S = 2.0  # tracker poses older than this (tracker clock) are dropped: a still run needs less


@dataclass(frozen=True)
class MonitorOptions:
    window: int = 100  # judged poses the drift test looks back over
    reference_poses: int = 20  # poses that place a station the model does not know
    still_s: float = 0.2  # a still run this long gives a pose
    still_tolerance_rad: float = 2e-5  # still: no joint moves more than this (a few encoder counts)
    clock_margin_s: float = 0.05  # tracker poses this close to a still run's ends are not used
    min_tracker_poses: int = 5  # fewer in a still run's middle part (a beam break): no pose
    p_value: float = 1e-3  # "drifted" when the window's poses beyond their bound are this unlikely

    def __post_init__(self) -> None:
        if self.still_s <= 2 * self.clock_margin_s:
            raise CalibrationError(f"still_s {self.still_s} s must exceed twice clock_margin_s {self.clock_margin_s} s")
        if self.window < 1 or self.reference_poses < 1:
            raise CalibrationError("the monitor's window and reference poses must be at least 1")


@dataclass(frozen=True)
class MonitorStatus:
    """What the monitor says now: ``state`` is ``waiting`` (no pose yet), ``placing`` (collecting the poses
    that place the station), ``no bounds`` (errors only: the model carries no bounds), ``ok`` or ``drifted``."""

    state: str
    poses: int  # still poses seen, placing ones included
    judged: int  # poses judged in the window
    over_bound: int  # of those, beyond the model's position bound or, when more, its orientation bound
    p_value: float
    position_mm_mean: float  # the window's mean error at the target (NaN before any is judged)
    last_position_mm: float
    station: str  # how the station was placed

    @property
    def drifted(self) -> bool:
        return self.state == "drifted"

    def message(self) -> str:
        if self.state in ("waiting", "placing"):
            return f"tracker monitor: {self.state} ({self.poses} still poses so far)"
        text = (
            f"tracker monitor: {self.judged} poses judged, mean {self.position_mm_mean:.4f} mm; "
            f"{self.over_bound} beyond the model's bound (p = {self.p_value:.2g})"
        )
        return ("DRIFTED: " if self.drifted else "") + text


class DriftMonitor:
    """The live check of one served model against one tracker stream. It keeps the stream's state (the
    current still run, recent tracker poses, the window); the model it judges is never changed."""

    def __init__(self, model: HybridModel, options: MonitorOptions = MonitorOptions()) -> None:
        self.model = model
        self.options = options
        self._tracker: deque[tuple[int, np.ndarray, np.ndarray]] = deque()  # (stamp ns, position, quat xyzw)
        self._first: np.ndarray | None = None  # the current still run's first joints, their sum and count
        self._sum = np.zeros(0)
        self._count = 0
        self._run_start = 0
        self._sampled = False
        self._frame: str | None = None
        self._position_only = False
        self._placing: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]] = []
        self._reference: Referencing | None = None
        self._how = ""
        # per judged pose: its position error (mm), beyond the position bound, beyond the orientation bound
        self._errors: deque[tuple[float, bool, bool]] = deque(maxlen=options.window)
        self._poses = 0
        self._last = float("nan")

    def tracker(self, stamp_ns: int, position: np.ndarray, quat_xyzw: np.ndarray, frame_id: str) -> None:
        """A tracker pose (m; a zero quaternion: a reflector without orientation)."""
        if self._frame is None:
            self._frame, self._position_only = frame_id, not np.any(quat_xyzw)
        elif frame_id != self._frame:
            raise CalibrationError(
                f"tracker pose in frame '{frame_id}', the monitor follows '{self._frame}': one station at a time"
            )
        elif not self._position_only and not np.any(quat_xyzw):
            raise CalibrationError("a tracker pose without orientation in a stream of 6-D poses: pose left out")
        self._tracker.append((stamp_ns, np.asarray(position, float), np.asarray(quat_xyzw, float)))
        while self._tracker and self._tracker[0][0] < stamp_ns - TRACKER_KEPT_S / NS:
            self._tracker.popleft()

    def joints(self, stamp_ns: int, q: np.ndarray, conditions: np.ndarray | None = None) -> MonitorStatus | None:
        """A joint state and the model's condition values now (its channels' order; None: its defaults);
        returns the new status when it completed a still pose, else None."""
        q = np.asarray(q, dtype=float)
        o = self.options
        if self._first is None or np.max(np.abs(q - self._first)) > o.still_tolerance_rad:
            self._first, self._sum, self._count, self._run_start, self._sampled = q, q.copy(), 1, stamp_ns, False
            return None
        self._sum += q
        self._count += 1
        if self._sampled or (stamp_ns - self._run_start) * NS < o.still_s:
            return None
        self._sampled = True
        pose = self._tracker_pose(self._run_start + o.clock_margin_s / NS, stamp_ns - o.clock_margin_s / NS)
        if pose is None:
            return None
        self._judge(self._sum / self._count, pose, None if conditions is None else np.asarray(conditions, float))
        return self.status()

    def _tracker_pose(self, start_ns: float, end_ns: float) -> np.ndarray | None:
        """The mean of the tracker's poses stamped within ``[start_ns, end_ns]``, ``(4, 4)``."""
        inside = [(p, quat) for stamp, p, quat in self._tracker if start_ns <= stamp <= end_ns]
        if len(inside) < self.options.min_tracker_poses:
            return None
        out = np.eye(4)
        out[:3, 3] = np.mean([p for p, _ in inside], axis=0)
        if not self._position_only:
            out[:3, :3] = Rotation.from_quat([quat for _, quat in inside]).mean().as_matrix()
        return out

    def _judge(self, q: np.ndarray, measured: np.ndarray, conditions: np.ndarray | None) -> None:
        self._poses += 1
        if self._reference is None:
            self._reference = self.model.referencings.get(self._frame)
            self._how = "the model's referencing" if self._reference is not None else ""
        if self._reference is None:
            self._placing.append((q, measured, conditions))
            if len(self._placing) >= self.options.reference_poses:
                self._reference, target = place_station(self.model, self._pairs(self._placing))
                self._how = f"placed from {len(self._placing)} poses, {target}"
            return
        pairs = self._reference.to_base(self._pairs([(q, measured, conditions)]), self.model.chain.base_link)
        values = self.model.conditions_of(pairs.conditions, 1)
        pos_mm, rot_deg = target_errors(pairs, self.model.fk(pairs.q, conditions=values))
        self._last = float(pos_mm[0])
        bounds = self.model.error_bounds(pairs.q, values)
        over_position = over_orientation = False
        if bounds is not None:
            over_position = bool(pos_mm[0] > 1e3 * bounds[0][0])
            if bounds[1] is not None and not self._position_only:
                over_orientation = bool(rot_deg[0] > np.degrees(bounds[1][0]))
        self._errors.append((self._last, over_position, over_orientation))

    def _pairs(self, poses: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]]) -> Pairs:
        """The still poses as pairs, with the model's condition channels (its defaults where none were given)."""
        q = np.array([p[0] for p in poses])
        T = np.array([p[1] for p in poses])
        names = self.model.condition_names
        defaults = self.model.condition_values
        values = np.array([defaults if p[2] is None else p[2] for p in poses]).reshape(len(poses), len(names))
        conditions = {name: values[:, k] for k, name in enumerate(names)}
        stamps = np.arange(len(poses), dtype=np.int64)
        return Pairs(
            q, T, stamps, self.model.joint_names, self._frame, position_only=self._position_only, conditions=conditions
        )

    def status(self) -> MonitorStatus:
        judged = len(self._errors)
        counts = [sum(e[k] for e in self._errors) for k in (1, 2)]
        over = max(counts)
        mean = float(np.mean([e[0] for e in self._errors])) if judged else float("nan")
        bounds = self.model.bounds
        if self._reference is None:
            state = "placing" if self._poses else "waiting"
            return MonitorStatus(state, self._poses, 0, 0, 1.0, mean, self._last, self._how)
        if bounds is None or not judged:
            state = "no bounds" if bounds is None else "ok"
            return MonitorStatus(state, self._poses, judged, over, 1.0, mean, self._last, self._how)
        kinds = 1 if self._position_only or not self.model.has_orientation else 2  # Bonferroni, as verify
        p = drift_p_value(counts[:kinds], judged, bounds)
        state = "drifted" if p < self.options.p_value else "ok"
        return MonitorStatus(state, self._poses, judged, over, p, mean, self._last, self._how)
