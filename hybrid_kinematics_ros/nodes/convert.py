"""Messages to core arrays and back. Every check a request needs lives here, with messages that say what
to fix; nodes turn :class:`RequestError` into ``success = false``."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, TransformStamped
from scipy.stats import chi2
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from hybrid_kinematics_ros.kinematics.se3 import matrix_of_pose_one, pose_from_matrix, quat_of_rows
from hybrid_kinematics_ros.model.bounds import in_report_units

QUAT_TOLERANCE = 1e-3  # |‖q‖ − 1| accepted (and normalised) in requests


class RequestError(ValueError):
    """A request the node cannot answer; the message says what to fix."""


def joint_list_from_msg(msg: JointState, names: Sequence[str], what: str = "joint state") -> list[float]:
    """Joint values in the model's order, as Python floats (the services' path, where each numpy call
    costs microseconds). Empty names mean the model's order."""
    position = list(msg.position)
    given = list(msg.name)
    if not (len(given) == len(position) == len(names) and given == list(names)):  # else the common case
        if not given:
            if len(position) != len(names):
                raise RequestError(
                    f"{what} has {len(position)} positions and no names; the model has {len(names)} "
                    f"joints ({', '.join(names)})"
                )
        else:
            if len(given) != len(position):
                raise RequestError(f"{what} has {len(given)} names but {len(position)} positions")
            if len(set(given)) != len(given):
                dup = sorted({n for n in given if given.count(n) > 1})
                raise RequestError(f"{what} names joint(s) {', '.join(dup)} more than once")
            index = {n: i for i, n in enumerate(given)}
            missing = [n for n in names if n not in index]
            if missing:
                unknown = [n for n in given if n not in names]
                raise RequestError(
                    f"{what} lacks joint(s) {', '.join(missing)}"
                    + (f" and has unknown joint(s) {', '.join(unknown)}" if unknown else "")
                )
            position = [position[index[n]] for n in names]
    if not all(map(math.isfinite, position)):
        raise RequestError(f"{what} has NaN or infinite positions")
    return position


def joints_from_msg(msg: JointState, names: Sequence[str], what: str = "joint state") -> np.ndarray:
    """:func:`joint_list_from_msg` as an array ``(n,)``."""
    return np.array(joint_list_from_msg(msg, names, what), dtype=float)


def joints_from_msg_lenient(msg: JointState, names: Sequence[str]) -> np.ndarray | None:
    """For topics: the model's joints picked from a possibly larger joint state; None if some are missing."""
    index = {n: i for i, n in enumerate(msg.name)}
    if len(msg.name) != len(msg.position) or any(n not in index for n in names):
        return None
    q = np.array([msg.position[index[n]] for n in names], dtype=float)
    return q if np.all(np.isfinite(q)) else None


def matrix_from_msg(msg: PoseStamped, frames: Sequence[str]) -> np.ndarray:
    """The pose as a 4x4 in its own frame, which must be ``''`` or one of ``frames`` (the first is the base)."""
    if msg.header.frame_id not in ("", *frames):
        raise RequestError(
            f"target is in frame '{msg.header.frame_id}', which is not a link of the chain; give it in "
            f"'{frames[0]}' (or leave it empty) or in one of {', '.join(frames[1:])}"
        )
    p, o = msg.pose.position, msg.pose.orientation
    position, quat = (p.x, p.y, p.z), (o.x, o.y, o.z, o.w)
    if not all(map(math.isfinite, position + quat)):
        raise RequestError("target pose has NaN or infinite values")
    norm = math.sqrt(sum(v * v for v in quat))
    if abs(norm - 1.0) > QUAT_TOLERANCE:
        raise RequestError(f"target orientation is not a unit quaternion (norm {norm:.6g})")
    return matrix_of_pose_one(position, [v / norm for v in quat])


def pose_msg(T: np.ndarray, frame_id: str, stamp: Time, quat: np.ndarray | None = None) -> PoseStamped:
    """A PoseStamped of one 4x4; pass ``quat`` when it was computed in a batch already. One numpy call
    (``tolist``), the rest in Python floats. (Fields are set on a default message: passing sub-messages
    to a constructor would build its default sub-messages as well.)"""
    return pose_msg_of_rows(T.tolist(), frame_id, stamp, quat)


def pose_msg_of_rows(
    rows: list[list[float]],
    frame_id: str,
    stamp: Time,
    quat: np.ndarray | None = None,
    out: PoseStamped | None = None,
) -> PoseStamped:
    """:func:`pose_msg` of a pose's rows as nested lists (``T.tolist()``, or :meth:`HybridModel.fk_rows`).
    ``out``: a message to overwrite and return instead of a new one (building a PoseStamped, six nested
    messages, costs more than the FK)."""
    msg = PoseStamped() if out is None else out
    msg.header.frame_id = frame_id
    msg.header.stamp = stamp
    p, o = msg.pose.position, msg.pose.orientation
    p.x, p.y, p.z = rows[0][3], rows[1][3], rows[2][3]
    o.x, o.y, o.z, o.w = quat_of_rows(rows) if quat is None else quat.tolist()
    return msg


def set_bounds(response, model, q: np.ndarray | Sequence[float]) -> None:
    """Fill a response's ``position_bound_mm`` and ``orientation_bound_deg`` with the error bounds of the
    model's answers at ``q`` (one configuration or ``(B, n)``); left empty when the model carries none."""
    bounds = model.error_bounds(np.atleast_2d(np.asarray(q, dtype=float)))
    if bounds is not None:
        for name, values in in_report_units(bounds).items():
            setattr(response, name, values.tolist())


def pose_with_covariance_msg(
    pose: PoseStamped, position_bound: float, orientation_bound: float | None, level: float
) -> PoseWithCovarianceStamped:
    """The pose with the covariance its error bounds (m, rad, at ``level``) imply: an isotropic Gaussian per
    part whose error norm stays under the bound with that probability (σ = bound / √χ²₃(level)). Without an
    orientation bound (position-only model) the orientation's variance is −1 on the diagonal: unknown."""
    msg = PoseWithCovarianceStamped(header=pose.header)
    msg.pose.pose = pose.pose
    scale = chi2.ppf(level, 3)
    cov = np.zeros((6, 6))
    cov[:3, :3] = np.eye(3) * position_bound**2 / scale
    cov[3:, 3:] = np.eye(3) * (-1.0 if orientation_bound is None else orientation_bound**2 / scale)
    msg.pose.covariance = cov.ravel().tolist()
    return msg


def transform_msg_of_pose(pose: PoseStamped, child_frame_id: str) -> TransformStamped:
    """The same pose as a TransformStamped, which names the frame it places (``child_frame_id``)."""
    msg = TransformStamped(header=pose.header, child_frame_id=child_frame_id)
    p, t = pose.pose.position, msg.transform.translation
    t.x, t.y, t.z = p.x, p.y, p.z
    msg.transform.rotation = pose.pose.orientation
    return msg


def pose_msgs(T: np.ndarray, frame_id: str, stamps: list[Time]) -> list[PoseStamped]:
    """PoseStamped messages of a batch ``(B, 4, 4)``, quaternions converted in one call."""
    if len(T) == 1:
        return [pose_msg(T[0], frame_id, stamps[0])]
    _, quats = pose_from_matrix(T)
    return [pose_msg(t, frame_id, stamp, q) for t, stamp, q in zip(T, stamps, quats, strict=True)]


def joint_state_msg(q: np.ndarray, names: Sequence[str], stamp: Time) -> JointState:
    msg = JointState()
    msg.header.stamp = stamp
    msg.name = list(names)
    msg.position = [float(v) for v in q]
    return msg


def stamp_ns(stamp: Time) -> int:
    """A header stamp in nanoseconds."""
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def stamp_is_zero(stamp: Time) -> bool:
    return stamp.sec == 0 and stamp.nanosec == 0


def trajectory_arrays(
    msg: JointTrajectory, names: Sequence[str]
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Positions ``(N, n)`` in the model's joint order, times ``(N,)`` (s), and the velocities and
    accelerations when every point has them (None when no point has them)."""
    if not msg.points:
        raise RequestError("trajectory has no points")
    given = list(msg.joint_names)
    if len(set(given)) != len(given):
        raise RequestError("trajectory joint_names name a joint more than once")
    missing = [n for n in names if n not in given]
    unknown = [n for n in given if n not in names]
    if missing or unknown:
        problems = [f"missing {', '.join(missing)}"] * bool(missing) + [f"unknown {', '.join(unknown)}"] * bool(unknown)
        raise RequestError(
            f"trajectory joint_names must be the chain's joints ({', '.join(names)}): {'; '.join(problems)}"
        )
    order = [given.index(n) for n in names]
    out = {}
    for field in ("positions", "velocities", "accelerations"):
        lengths = {len(getattr(p, field)) for p in msg.points}
        if field != "positions" and lengths == {0}:
            out[field] = None
            continue
        if lengths != {len(given)}:
            i = next(i for i, p in enumerate(msg.points) if len(getattr(p, field)) != len(given))
            raise RequestError(
                f"trajectory point {i} has {len(getattr(msg.points[i], field))} {field} for {len(given)} joints"
                + ("" if field == "positions" else " (give them for every point or for none)")
            )
        out[field] = np.array([getattr(p, field) for p in msg.points], dtype=float)[:, order]
    times = np.array([p.time_from_start.sec + 1e-9 * p.time_from_start.nanosec for p in msg.points])
    return out["positions"], times, out["velocities"], out["accelerations"]


def trajectory_msg(
    request: JointTrajectory,
    names: Sequence[str],
    positions: np.ndarray,
    velocities: np.ndarray | None,
    accelerations: np.ndarray | None,
) -> JointTrajectory:
    """The corrected trajectory: the request's header, joint order and ``time_from_start``."""
    given = list(request.joint_names)
    order = [list(names).index(n) for n in given]
    msg = JointTrajectory(header=request.header, joint_names=given)
    for i, point in enumerate(request.points[: len(positions)]):
        out = JointTrajectoryPoint(time_from_start=point.time_from_start)
        out.positions = positions[i, order].tolist()
        if velocities is not None:
            out.velocities = velocities[i, order].tolist()
        if accelerations is not None:
            out.accelerations = accelerations[i, order].tolist()
        msg.points.append(out)
    return msg
