"""The calibration-pairs contract: a rosbag2 bag (MCAP storage) with two topics of equal stamps.

- ``/calibration/joint_states`` (``sensor_msgs/msg/JointState``): one message per sample, with joint names;
- ``/calibration/tracker_pose`` (``geometry_msgs/msg/PoseStamped``): the measured pose, with the same
  ``header.stamp``; ``frame_id`` is the base link when in the base frame, else the tracker's frame.
  A target without orientation (a plain reflector) writes the zero quaternion ``(0, 0, 0, 0)`` in
  every sample: the bag is then position-only.
- optional condition channels, one topic per condition with the same ``header.stamp`` as the pairs:
  ``/calibration/temperature`` (``sensor_msgs/msg/Temperature``, °C), ``/calibration/fluid_pressure``
  (``sensor_msgs/msg/FluidPressure``, Pa), ``/calibration/relative_humidity``
  (``sensor_msgs/msg/RelativeHumidity``, 0-1). Bags without them are complete pairs bags.

This module is the only reader and writer of pairs. Alignment is on ``header.stamp``, never on bag time.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from hybrid_kinematics_ros.io.errors import DataError
from hybrid_kinematics_ros.kinematics.approach import approach_directions, channel_names, is_channel
from hybrid_kinematics_ros.kinematics.se3 import matrix_from_pose, pose_from_matrix

JOINTS_TOPIC = "/calibration/joint_states"
POSE_TOPIC = "/calibration/tracker_pose"
RAW_JOINTS_TOPIC = "/joint_states"
RAW_POSE_TOPIC = "/tracker/pose"
JOINT_STATE = "sensor_msgs/msg/JointState"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
QUAT_TOLERANCE = 1e-6  # |‖q‖ − 1| above this is a non-unit quaternion

CONDITION_PREFIX = "/calibration/"
# condition name -> (message type, its value field); the message's unit is the condition's unit
CONDITION_TYPES: dict[str, tuple[str, str]] = {
    "temperature": ("sensor_msgs/msg/Temperature", "temperature"),
    "fluid_pressure": ("sensor_msgs/msg/FluidPressure", "fluid_pressure"),
    "relative_humidity": ("sensor_msgs/msg/RelativeHumidity", "relative_humidity"),
}

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
_T = TYPESTORE.types


def condition_topic(name: str) -> str:
    return CONDITION_PREFIX + name


@dataclass
class Pairs:
    """Calibration pairs: joints ``q (N, n)`` rad, measured poses ``T (N, 4, 4)`` m, stamps ``(N,)`` ns."""

    q: np.ndarray
    T: np.ndarray
    stamps: np.ndarray
    joint_names: tuple[str, ...]
    frame_id: str
    dropped: Counter = field(default_factory=Counter)
    position_only: bool = False  # the target gives no orientation: rotations are identity placeholders
    # condition channels (name -> (N,) values, e.g. "temperature" in °C), one value per sample
    conditions: dict[str, np.ndarray] = field(default_factory=dict)
    # (N, 4, 4): where the measured target sits in the tip frame, set by referencing (each tracker station
    # has its own); None: at the tip. Position-only pairs in the base frame hold that target's points.
    target: np.ndarray | None = None
    # (m, rad; NaN rad position-only): one measurement's mean error from the tracker's own scatter, where the
    # export tells it (the spread of rigid reflectors, :mod:`io.importer`); None: not known
    floor: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        for name, values in self.conditions.items():
            if np.shape(values) != (len(self.q),):
                raise DataError(f"condition '{name}' has shape {np.shape(values)}, expected ({len(self.q)},)")

    def __len__(self) -> int:
        return len(self.q)

    def subset(self, index: np.ndarray) -> Pairs:
        return replace(
            self,
            q=self.q[index],
            T=self.T[index],
            stamps=self.stamps[index],
            dropped=Counter(),
            conditions={k: v[index] for k, v in self.conditions.items()},
            target=None if self.target is None else self.target[index],
        )

    @property
    def targets(self) -> np.ndarray:
        """``(N, 4, 4)``: :attr:`target`, identity where none is set."""
        return np.tile(np.eye(4), (len(self), 1, 1)) if self.target is None else self.target

    def with_approach(self) -> Pairs:
        """The same samples with each joint's approach direction (:mod:`kinematics.approach`) as condition
        channels ``approach_<joint>``, from the order of the samples: call it on one recording, in stamp
        order, before it is concatenated or split."""
        directions = approach_directions(self.q)
        channels = dict(zip(channel_names(self.joint_names), directions.T, strict=True))
        return replace(self, conditions={**self.conditions, **channels})

    def with_poses(self, T: np.ndarray, frame_id: str) -> Pairs:
        """The same samples with the poses expressed in another frame."""
        return replace(self, T=T, frame_id=frame_id)

    @staticmethod
    def concatenate(parts: Sequence[Pairs]) -> Pairs:
        """One set of pairs from several; only the condition channels that every part carries are kept
        (a channel some samples lack cannot be an input for all of them)."""
        first = parts[0]
        for p in parts[1:]:
            if (p.joint_names, p.frame_id, p.position_only) != (first.joint_names, first.frame_id, first.position_only):
                raise DataError(
                    f"bags disagree: joints {p.joint_names} in frame '{p.frame_id}' "
                    f"(position only: {p.position_only}) against {first.joint_names} in frame "
                    f"'{first.frame_id}' (position only: {first.position_only})"
                )
        dropped = sum((p.dropped for p in parts), Counter())
        names = [n for n in first.conditions if all(n in p.conditions for p in parts)]
        return Pairs(
            np.concatenate([p.q for p in parts]),
            np.concatenate([p.T for p in parts]),
            np.concatenate([p.stamps for p in parts]),
            first.joint_names,
            first.frame_id,
            dropped,
            first.position_only,
            {n: np.concatenate([p.conditions[n] for p in parts]) for n in names},
            None if all(p.target is None for p in parts) else np.concatenate([p.targets for p in parts]),
            pooled_floor(parts),
        )


def _stamp(ns: int):
    return _T["builtin_interfaces/msg/Time"](sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))


def joint_state_msg(ns: int, names: Sequence[str], position: np.ndarray):
    empty = np.zeros(0)
    header = _T["std_msgs/msg/Header"](stamp=_stamp(ns), frame_id="")
    return _T[JOINT_STATE](header=header, name=list(names), position=position, velocity=empty, effort=empty)


def pose_stamped_msg(ns: int, frame_id: str, position: np.ndarray, quat_xyzw: np.ndarray):
    point = _T["geometry_msgs/msg/Point"](x=float(position[0]), y=float(position[1]), z=float(position[2]))
    quat = _T["geometry_msgs/msg/Quaternion"](
        x=float(quat_xyzw[0]), y=float(quat_xyzw[1]), z=float(quat_xyzw[2]), w=float(quat_xyzw[3])
    )
    header = _T["std_msgs/msg/Header"](stamp=_stamp(ns), frame_id=frame_id)
    return _T[POSE_STAMPED](header=header, pose=_T["geometry_msgs/msg/Pose"](position=point, orientation=quat))


def condition_msg(ns: int, name: str, value: float):
    msgtype, value_field = CONDITION_TYPES[name]
    header = _T["std_msgs/msg/Header"](stamp=_stamp(ns), frame_id="")
    return _T[msgtype](header=header, **{value_field: float(value)}, variance=0.0)


def pooled_floor(parts: Sequence[Pairs]) -> tuple[float, float] | None:
    """The parts' tracker floor, each weighted by its pairs; None unless every part has one."""
    if any(p.floor is None for p in parts):
        return None
    counts = np.array([len(p) for p in parts], dtype=float)
    floors = np.array([p.floor for p in parts])
    return float(counts @ floors[:, 0] / counts.sum()), float(counts @ floors[:, 1] / counts.sum())


def floor_summary(floor: tuple[float, float]) -> dict[str, Any]:
    """A tracker floor (m, rad: :attr:`Pairs.floor`) as summaries and ``model.json`` give it (mm, deg)."""
    position, orientation = floor
    return {
        "position_mm": 1e3 * position,
        "orientation_deg": None if np.isnan(orientation) else float(np.degrees(orientation)),
        "from": "the export: the spread of its reflectors about their rigid layout, or its uncertainty columns",
    }


FLOOR_KEYS = ("tracker_floor_position_m", "tracker_floor_orientation_rad")  # the bag's custom data


def bag_floor(path: str | Path) -> tuple[float, float] | None:
    """The tracker floor a pairs bag records in its metadata (rosbag2's ``custom_data``), or None."""
    path = Path(path)
    meta = (path if path.is_dir() else path.parent) / "metadata.yaml"
    if not meta.is_file():
        return None
    info = yaml.safe_load(meta.read_text()).get("rosbag2_bagfile_information", {})
    custom = info.get("custom_data") or {}
    if not all(key in custom for key in FLOOR_KEYS):
        return None
    try:
        return float(custom[FLOOR_KEYS[0]]), float(custom[FLOOR_KEYS[1]])
    except ValueError as exc:
        raise DataError(f"bag {path}: custom data {FLOOR_KEYS}: {exc}") from exc


class PairsWriter:
    """Streams pairs into a new bag; use as a context manager so a crash still closes the file."""

    def __init__(
        self,
        path: str | Path,
        joint_names: Sequence[str],
        frame_id: str,
        position_only: bool = False,
        conditions: Sequence[str] = (),
        floor: tuple[float, float] | None = None,
    ) -> None:
        self.path = Path(path)
        self.position_only = position_only
        self.floor = floor
        unknown = sorted(set(conditions) - set(CONDITION_TYPES))
        if unknown:
            raise DataError(f"unknown condition channel(s) {unknown}; known: {', '.join(CONDITION_TYPES)}")
        self.conditions = list(conditions)
        if self.path.exists():
            raise DataError(f"{self.path} exists already, not overwriting")
        if not self.path.parent.is_dir():
            raise DataError(f"cannot write {self.path}: folder {self.path.parent} does not exist")
        self.joint_names = list(joint_names)
        self.frame_id = frame_id
        self._writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        self.count = 0

    def __enter__(self) -> PairsWriter:
        self._writer.open()
        if self.floor is not None:
            for key, value in zip(FLOOR_KEYS, self.floor, strict=True):
                self._writer.set_custom_data(key, repr(float(value)))
        self._joints = self._writer.add_connection(JOINTS_TOPIC, JOINT_STATE, typestore=TYPESTORE)
        self._poses = self._writer.add_connection(POSE_TOPIC, POSE_STAMPED, typestore=TYPESTORE)
        self._conditions = {
            name: self._writer.add_connection(condition_topic(name), CONDITION_TYPES[name][0], typestore=TYPESTORE)
            for name in self.conditions
        }
        return self

    def __exit__(self, *exc: object) -> None:
        self._writer.close()

    def write(
        self, q: np.ndarray, T: np.ndarray, stamps: Iterable[int], conditions: Mapping[str, np.ndarray] | None = None
    ) -> None:
        """Append samples; ``conditions`` gives one value per sample for each channel named at construction."""
        conditions = conditions or {}
        if set(conditions) != set(self.conditions):
            raise DataError(f"{self.path}: condition values for {sorted(conditions)}, expected {self.conditions}")
        positions, quats = pose_from_matrix(T)
        if self.position_only:
            quats = np.zeros_like(quats)
        for i, (qi, p, quat, ns) in enumerate(zip(q, positions, quats, stamps, strict=True)):
            ns = int(ns)
            js = joint_state_msg(ns, self.joint_names, np.asarray(qi, dtype=float))
            ps = pose_stamped_msg(ns, self.frame_id, p, quat)
            self._writer.write(self._joints, ns, TYPESTORE.serialize_cdr(js, JOINT_STATE))
            self._writer.write(self._poses, ns, TYPESTORE.serialize_cdr(ps, POSE_STAMPED))
            for name, conn in self._conditions.items():
                msg = condition_msg(ns, name, conditions[name][i])
                self._writer.write(conn, ns, TYPESTORE.serialize_cdr(msg, conn.msgtype))
        self.count += len(q)


def write_pairs(path: str | Path, pairs: Pairs) -> None:
    """Approach directions are not written: they are derived from the order of the samples when read."""
    conditions = {k: v for k, v in pairs.conditions.items() if not is_channel(k)}
    with PairsWriter(
        path, pairs.joint_names, pairs.frame_id, pairs.position_only, list(conditions), pairs.floor
    ) as writer:
        writer.write(pairs.q, pairs.T, pairs.stamps, conditions)


def _ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def open_bag(path: str | Path) -> Reader:
    path = Path(path)
    if not path.exists():
        raise DataError(f"bag {path} does not exist")
    try:
        reader = Reader(path)
        reader.open()
    except Exception as exc:  # rosbags raises its own ReaderError and OS errors
        raise DataError(f"cannot open bag {path}: {exc}") from exc
    return reader


def bag_topics(path: str | Path) -> dict[str, str]:
    reader = open_bag(path)
    try:
        return {c.topic: c.msgtype for c in reader.connections}
    finally:
        reader.close()


def read_pairs(path: str | Path, joint_names: Sequence[str] | None = None) -> Pairs:
    """Read and check a pairs bag. Unusable samples are dropped and counted by reason in ``Pairs.dropped``.

    Args:
        path: the bag directory (or its .mcap file).
        joint_names: the model's joints; messages are reordered to them. ``None``: the bag's first order.

    Raises:
        DataError: missing topics, wrong types, unknown or missing joint names, or no usable pair left.
    """
    path = Path(path)
    reader = open_bag(path)
    try:
        conns = {c.topic: c for c in reader.connections}
        channels = _checked_topics(path, conns)
        read = _Read(path, tuple(joint_names) if joint_names is not None else None, channels)
        wanted = [conns[JOINTS_TOPIC], conns[POSE_TOPIC], *(conns[t] for t in channels)]
        for conn, _, raw in reader.messages(connections=wanted):
            read.take(conn.topic, TYPESTORE.deserialize_cdr(raw, conn.msgtype))
    finally:
        reader.close()
    return replace(read.pairs(), floor=bag_floor(path))


def _checked_topics(path: Path, conns: dict) -> dict[str, str]:
    """Refuse a bag without the pairs' topics or with other types; its condition topics -> condition names."""
    for topic, msgtype in ((JOINTS_TOPIC, JOINT_STATE), (POSE_TOPIC, POSE_STAMPED)):
        if topic not in conns:
            raw = (
                " (a raw recording: align it first with `hybrid-kinematics align`)" if RAW_JOINTS_TOPIC in conns else ""
            )
            raise DataError(f"bag {path} has no topic {topic}{raw}; topics: {', '.join(sorted(conns)) or 'none'}")
        if conns[topic].msgtype != msgtype:
            raise DataError(f"bag {path}: topic {topic} has type {conns[topic].msgtype}, expected {msgtype}")
    channels: dict[str, str] = {}
    for name, (msgtype, _) in CONDITION_TYPES.items():
        conn = conns.get(condition_topic(name))
        if conn is not None:
            if conn.msgtype != msgtype:
                raise DataError(f"bag {path}: topic {conn.topic} has type {conn.msgtype}, expected {msgtype}")
            channels[conn.topic] = name
    return channels


class _Read:
    """A pairs bag's messages as they are read, by stamp; then its pairs."""

    def __init__(self, path: Path, names: tuple[str, ...] | None, channels: dict[str, str]) -> None:
        self.path, self.names, self.channels = path, names, channels
        self.values: dict[str, dict[int, float]] = {name: {} for name in channels.values()}
        self.joints: dict[int, np.ndarray] = {}
        self.poses: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.frames: set[str] = set()
        self.dropped: Counter = Counter()

    def take(self, topic: str, msg) -> None:
        ns = _ns(msg.header)
        if topic in self.channels:
            name = self.channels[topic]
            self.values[name][ns] = float(getattr(msg, CONDITION_TYPES[name][1]))
        elif topic == JOINTS_TOPIC:
            self._joint_state(msg, ns)
        else:
            self.frames.add(msg.header.frame_id)
            p = msg.pose.position
            o = msg.pose.orientation
            self.poses[ns] = (np.array([p.x, p.y, p.z]), np.array([o.x, o.y, o.z, o.w]))

    def _joint_state(self, msg, ns: int) -> None:
        """A joint state's positions, in the model's joint order."""
        msg_names = tuple(msg.name)
        if self.names is None:
            self.names = msg_names
        names, order = self.names, None
        if msg_names != names:
            if set(msg_names) != set(names) or len(msg_names) != len(names):
                unknown = sorted(set(msg_names) - set(names))
                missing = sorted(set(names) - set(msg_names))
                raise DataError(
                    f"bag {self.path}: joint state at stamp {ns} has joints {list(msg_names)}; "
                    f"unknown {unknown}, missing {missing} (the model has {list(names)})"
                )
            order = [msg_names.index(n) for n in names]
        position = np.asarray(msg.position, dtype=float)
        if len(position) != len(msg_names):
            self.dropped["joint_state_length_mismatch"] += 1
            return
        if order is not None:
            position = position[order]
        if ns in self.joints:
            self.dropped["duplicate_stamp"] += 1
            return
        self.joints[ns] = position

    def _common_stamps(self) -> list[int]:
        """The stamps with a joint state, a tracker pose and every condition value."""
        path, joints, poses, dropped = self.path, self.joints, self.poses, self.dropped
        if len(self.frames) > 1:
            raise DataError(f"bag {path}: tracker poses come in several frames {sorted(self.frames)}; expected one")
        common = sorted(set(joints) & set(poses))
        if len(joints) - len(common):
            dropped["joint_state_without_pose"] += len(joints) - len(common)
        if len(poses) - len(common):
            dropped["pose_without_joint_state"] += len(poses) - len(common)
        if not common:
            raise DataError(f"bag {path}: no joint state has a tracker pose with the same header.stamp")
        for name, by_stamp in self.values.items():  # a pair without its condition value cannot be used with it
            missing = sum(1 for s in common if s not in by_stamp)
            if missing:
                dropped[f"without_{name}"] += missing
                common = [s for s in common if s in by_stamp]
        if not common:
            raise DataError(f"bag {path}: no usable pair left after dropping {dict(+dropped)}")
        return common

    def pairs(self) -> Pairs:
        """The usable pairs: finite, with a unit quaternion (or a plain reflector's zero one throughout)."""
        common, dropped = self._common_stamps(), self.dropped
        q = np.array([self.joints[s] for s in common])
        pos = np.array([self.poses[s][0] for s in common])
        quat = np.array([self.poses[s][1] for s in common])
        stamps = np.array(common, dtype=np.int64)
        cond = {name: np.array([by_stamp[s] for s in common]) for name, by_stamp in self.values.items()}
        finite = np.all(np.isfinite(q), axis=1) & np.all(np.isfinite(pos), axis=1) & np.all(np.isfinite(quat), axis=1)
        for v in cond.values():
            finite &= np.isfinite(v)
        dropped["nan_or_inf"] += int(np.sum(~finite))
        position_only = bool(np.all(quat[finite] == 0.0))  # a plain reflector: the zero quaternion means none
        if position_only:
            keep = finite
            quat = np.tile([0.0, 0.0, 0.0, 1.0], (len(quat), 1))
        else:
            norms = np.linalg.norm(np.where(np.isfinite(quat), quat, 0.0), axis=1)
            unit = np.abs(norms - 1.0) <= QUAT_TOLERANCE
            dropped["non_unit_quaternion"] += int(np.sum(finite & ~unit))
            keep = finite & unit
            quat = quat / np.where(unit, norms, 1.0)[:, None]
        if not np.any(keep):
            raise DataError(f"bag {self.path}: no usable pair left after dropping {dict(+dropped)}")
        T = matrix_from_pose(pos[keep], quat[keep])
        kept = {k: v[keep] for k, v in cond.items()}
        frame = self.frames.pop()
        return Pairs(
            q[keep], T, stamps[keep], self.names, frame, +dropped, position_only=position_only, conditions=kept
        )
