"""Referencing: where the tracker stands relative to the robot base, and where the target sits on the flange.

The tracker measures ``T_meas = T_base_tracker⁻¹ · T_tip(q) · T_flange_target``. Two ways to find both
transforms:

- :func:`reference` (ours): non-linear least squares over all calibration pairs with a robust loss,
  started from a closed-form (Kabsch) fit of the measured positions to the nominal tip positions;
- :func:`reference_by_circles` (the paper's): fit circles to the target's path while joints 1, 2, 5 and
  6 move one at a time, and build the frames from the fitted axes.

A position-only target (a plain reflector) has no orientation: only its offset from the flange is found,
and a position-only model is defined at that point. Its pairs in the base frame are the measured target
points (:meth:`Referencing.to_base`); the parametric stage and the position net fit
``p_tip(q) + R_tip(q) · t`` to them, with ``t`` the target's offset, and the served tip is that corrected
point less ``R_model · t`` (the orientation stays the parametric model's).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.linalg
from scipy.optimize import OptimizeResult, least_squares
from scipy.spatial.transform import Rotation

from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.calibration.parametric import ParametricResult, outliers, robust_scale, robust_sigma
from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.kinematics import fk, se3
from hybrid_kinematics_ros.kinematics.chain import Chain
from hybrid_kinematics_ros.model.parametric import build_model
from hybrid_kinematics_ros.model.referencing import Referencing


def station_labels(refs: Mapping[str, Referencing], base_frame_pairs: bool) -> dict[str, tuple[int, int]]:
    """Each tracker frame's placement and mount label for the parametric stage's station corrections
    (:func:`~hybrid_kinematics_ros.calibration.parametric.identify`; -1: none).

    The first frame is the reference, its placement and mount uncorrected (the robot's own first joint
    origin and flange parameters play that part), unless pairs measured in the base frame are the
    reference. Frames with one ``flange_to_target`` (a target shared by :func:`reference_stations`) share
    a mount label.
    """
    frames = list(refs)
    first = None if base_frame_pairs or not frames else frames[0]
    mounts: list[np.ndarray] = [] if first is None else [refs[first].flange_to_target]
    labels: dict[str, tuple[int, int]] = {}
    placements = 0
    for frame in frames:
        placement = -1
        if frame != first:
            placement, placements = placements, placements + 1
        target = refs[frame].flange_to_target
        mount = next((k for k, m in enumerate(mounts) if np.array_equal(m, target)), None)
        if mount is None:
            mounts.append(target)
            mount = len(mounts) - 1
        labels[frame] = (placement, mount - (first is not None))
    return labels


def refine_stations(
    refs: Mapping[str, Referencing], labels: Mapping[str, tuple[int, int]], result: ParametricResult
) -> dict[str, Referencing]:
    """The referencings with the station corrections identified beside the robot folded in: the stage fits
    ``D⁻¹ · T · E⁻¹``, with ``T = B · T_meas · F⁻¹``, so ``B' = D⁻¹ · B`` and ``F' = E · F``."""
    out = {}
    identity = np.eye(4)[None]
    for frame, ref in refs.items():
        placement, mount = labels[frame]
        base, target, moves = ref.base_to_tracker, ref.flange_to_target, []
        if placement >= 0:
            base = se3.inverse(result.placements[placement]) @ base
            moves.append(("tracker", result.placements[placement]))
        if mount >= 0:
            target = result.mounts[mount] @ target
            moves.append(("target", result.mounts[mount]))
        method = ref.method
        if moves:
            sizes = [(what, *se3.pose_errors(move[None], identity)) for what, move in moves]
            method += (
                ", refined with the parametric stage ("
                + "; ".join(f"{what} moved {mm[0]:.3f} mm, {deg[0]:.4f} deg" for what, mm, deg in sizes)
                + ")"
            )
        out[frame] = replace(ref, base_to_tracker=base, flange_to_target=target, method=method)
    return out


def anchor_base(chain: Chain, ref: Referencing, result: ParametricResult) -> tuple[Referencing, ParametricResult]:
    """:func:`anchor_stations` for one tracker station."""
    refs, result = anchor_stations(chain, [ref], result)
    return refs[0], result


def anchor_stations(
    chain: Chain, refs: Sequence[Referencing], result: ParametricResult
) -> tuple[list[Referencing], ParametricResult]:
    """Define the base frame by the robot's first joint, as its URDF places it and as its encoder counts.

    Least squares on the nominal model puts the base wherever the robot's errors fit best, and the
    parametric stage then corrects the first joint's origin (and zero offset) to match. Both are equally
    good in the tracker frame, but in the robot's base frame only one is right: the frame in which the
    first joint sits where the URDF says, and turns by what its encoder reads (a zero offset of the first
    joint cannot be told from a turn of the base; this is the paper's circle-fit convention too). So the
    first joint origin's correction and its zero offset move into ``base_to_tracker``,
    ``B' = X⁻¹ · B`` with ``X = pre₀' · pre₀⁻¹ · local₀(z₀) · pre₀⁻¹``, and the model keeps the nominal ones.
    ``X`` is the robot's, so every tracker station's ``B`` moves by it.
    """
    first = np.array(
        [
            (p.kind in ("translation", "rotation") and p.index == 0) or (p.kind == "zero" and p.index == 0)
            for p in result.params
        ]
    )
    if not np.any(result.values[first]):
        return list(refs), result
    m = result.model
    z0 = m.zero_offset[0]
    a, b = chain.coefficients(np.full(chain.dof, z0))
    g = chain.generators[0]
    local = g[0] + a[0] * g[1] + b[0] * g[2]  # pre₀ · M₀(z₀)
    inv_pre = se3.inverse(chain.pre[0])
    x = m.chain.pre[0] @ inv_pre @ local @ inv_pre
    values = result.values.copy()
    values[first] = 0.0
    rigid = result.rigid_values.copy()
    rigid[first] -= result.values[first]  # first order: the URDF fit's first joint, relative to the new base
    anchored = build_model(chain, result.params, values, m.payload_mass, m.payload_com, result.joint_map, m.gravity)
    moved = [replace(ref, base_to_tracker=se3.inverse(x) @ ref.base_to_tracker) for ref in refs]
    return moved, replace(result, model=anchored, values=values, rigid_values=rigid)


def _transform(x: np.ndarray) -> np.ndarray:
    return se3.from_rotvec(x[:3], x[3:6])[0]


def reference(
    chain: Chain, pairs: Pairs, tip: np.ndarray | None = None, max_pairs: int = 20_000, seed: int = 0
) -> Referencing:
    """Both transforms from the pairs, by robust non-linear least squares on the nominal model.

    ``tip`` overrides the modelled tip poses (for example a parametric model's). Geometric errors of the
    robot that look like a moved base or a moved target are absorbed here, which is harmless: the base
    and flange transforms cannot be told apart from them by any measurement.
    """
    return reference_stations(chain, [pairs], None if tip is None else [tip], max_pairs, seed)[0]


def reference_stations(
    chain: Chain,
    stations: Sequence[Pairs],
    tips: Sequence[np.ndarray] | None = None,
    max_pairs: int = 20_000,
    seed: int = 0,
) -> list[Referencing]:
    """One tracker placement per station (each in its own frame) and ONE target transform shared by all:
    the target stayed on the flange while the tracker moved. Fitted together by robust least squares,
    each station's base from a closed-form start; see :func:`reference`.

    Poses that keep one tool orientation cannot tell the target's offset from a shift of the tracker:
    the offset's directions the poses do not determine (:func:`undetermined_offsets`) stay at the prior,
    the robot config's tool (the target at the chain's tip), and the referencing says so.
    """
    position_only = stations[0].position_only
    if any(p.position_only != position_only for p in stations):
        raise CalibrationError("stations sharing a target must all be 6-DoF or all position-only")
    problem = _Problem.build(chain, stations, tips, max_pairs, seed)
    fit = problem.solve()
    weak = undetermined_offsets(fit.jac, problem, fit.fun)
    notes: tuple[str, ...] = ()
    if weak.directions.size:
        problem = problem.holding(weak.directions)
        fit = problem.solve()
        notes = (weak.message(),)
    return problem.referencings(stations, fit.x, fit.fun, notes)


TURN_MARGIN = 10.0  # a direction is determined when the tool turns along it this many times the model's error


@dataclass(frozen=True)
class _Problem:
    """The referencing's least squares: per station its measured poses, the modelled tip poses and a start
    for ``base_to_tracker``; the target's start, and the basis of its offset's free directions (tip frame)."""

    parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]]
    start_target: np.ndarray
    position_only: bool
    free: np.ndarray = field(default_factory=lambda: np.eye(3))  # (3, m): the offset's free directions

    @classmethod
    def build(
        cls, chain: Chain, stations: Sequence[Pairs], tips: Sequence[np.ndarray] | None, max_pairs: int, seed: int
    ) -> _Problem:
        rng = np.random.default_rng(seed)
        per_station = max(10, max_pairs // len(stations))
        parts = []
        for k, pairs in enumerate(stations):
            if len(pairs) < 10:
                raise CalibrationError(
                    f"frame '{pairs.frame_id}': only {len(pairs)} pairs; referencing needs at least 10"
                )
            pick = rng.permutation(len(pairs))[:per_station]
            model = fk.fk(chain, pairs.q[pick]) if tips is None else tips[k][pick]
            p_tip = model[:, :3, 3]
            if np.linalg.matrix_rank(p_tip - p_tip.mean(axis=0), tol=1e-3) < 3:
                raise CalibrationError(
                    f"frame '{pairs.frame_id}': the tip positions span less than 3 dimensions; referencing needs "
                    "varied poses"
                )
            meas = pairs.T[pick]
            parts.append((meas, model, se3.fit_rigid(meas[:, :3, 3], p_tip[None])[0][0]))
        # Start: the target near the flange, each tracker from its point clouds; then the target offset.
        in_tip = np.concatenate([se3.inverse(model) @ b @ meas for meas, model, b in parts])
        start_target = np.eye(4)
        start_target[:3, 3] = np.median(in_tip[:, :3, 3], axis=0)
        if not stations[0].position_only:
            start_target[:3, :3] = Rotation.from_matrix(in_tip[:, :3, :3]).mean().as_matrix()
        return cls(parts, start_target, stations[0].position_only)

    def holding(self, directions: np.ndarray) -> _Problem:
        """The problem with the target's offset along ``directions (3, k)`` (tip frame) held at the prior."""
        start = self.start_target.copy()
        start[:3, 3] -= directions @ (directions.T @ start[:3, 3])
        free = scipy.linalg.null_space(directions.T)
        return replace(self, start_target=start, free=free)

    @property
    def n_target(self) -> int:
        return self.free.shape[1] + (0 if self.position_only else 3)

    def unpack(self, x: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
        m, n_target = self.free.shape[1], self.n_target
        t = self.start_target.copy()
        t[:3, 3] += self.free @ x[:m]
        if not self.position_only:
            t = t @ _transform(np.r_[0.0, 0.0, 0.0, x[m:n_target]])
        bases = [b @ _transform(x[n_target + 6 * k : n_target + 6 * k + 6]) for k, (_, _, b) in enumerate(self.parts)]
        return bases, t

    def residual(self, x: np.ndarray) -> np.ndarray:
        bases, t = self.unpack(x)
        out = []
        for (meas, model, _), b in zip(self.parts, bases, strict=True):
            pred = se3.inverse(b) @ model @ t
            dp = meas[:, :3, 3] - pred[:, :3, 3]
            if self.position_only:
                out.append(dp.ravel())
            else:
                dw = se3.rotvec(meas[:, :3, :3] @ np.swapaxes(pred[:, :3, :3], 1, 2))
                out.append(np.concatenate([dp, dw], axis=1).ravel())
        return np.concatenate(out)

    def solve(self) -> OptimizeResult:
        """Twice, robustly: the loss's scale first from the residuals at the start, then from what the first
        fit leaves (:func:`~hybrid_kinematics_ros.calibration.parametric.robust_scale`, on the positions)."""
        x = np.zeros(self.n_target + 6 * len(self.parts))
        for _ in range(2):
            scale = robust_scale(self.residual(x).reshape(-1, self.width)[:, :3])
            fit = least_squares(self.residual, x, loss="soft_l1", f_scale=scale, x_scale="jac")
            x = fit.x
        return fit

    @property
    def width(self) -> int:
        return 3 if self.position_only else 6

    def referencings(
        self, stations: Sequence[Pairs], x: np.ndarray, fun: np.ndarray, notes: tuple[str, ...]
    ) -> list[Referencing]:
        bases, t = self.unpack(x)
        width = self.width
        sigma = robust_sigma(fun.reshape(-1, width)[:, :3])
        out, start = [], 0
        for pairs, (meas, _, _), b in zip(stations, self.parts, bases, strict=True):
            res = fun[start : start + width * len(meas)].reshape(len(meas), width)
            start += width * len(meas)
            inlier = ~outliers(res[:, :3], sigma)
            res = res[inlier]
            rms_deg = (
                float("nan") if self.position_only else float(np.degrees(np.sqrt(np.mean(np.sum(res[:, 3:] ** 2, 1)))))
            )
            rms_mm = float(1e3 * np.sqrt(np.mean(np.sum(res[:, :3] ** 2, axis=1))))
            out.append(
                Referencing(
                    pairs.frame_id,
                    b,
                    t,
                    self.position_only,
                    rms_mm,
                    rms_deg,
                    outliers=int(np.sum(~inlier)),
                    undetermined=notes,
                )
            )
        return out


@dataclass(frozen=True)
class Undetermined:
    """Directions of the target's offset from the flange (tip frame, unit columns) that the poses do not
    determine, how far the tool turns along each (rad, rms over the poses) and the model's own orientation
    error it is judged against (rad)."""

    directions: np.ndarray  # (3, k)
    turns: np.ndarray  # (k,)
    model_error: float

    def message(self) -> str:
        if self.directions.shape[1] == 3:
            names = "every direction"
        else:
            names = " and ".join(_direction_name(d) for d in self.directions.T)
        turned = ", ".join(f"{np.degrees(t):.3f}" for t in self.turns)
        return (
            f"the target's offset from the flange ({names}) is not determined by these poses: the tool turns "
            f"by {turned} deg (rms) about the axes that would determine it, against the model's own "
            f"{np.degrees(self.model_error):.3f} deg orientation error. It is held at the robot config's tool and "
            "the tracker's placement absorbs the rest; to determine it, turn the tool by at least 30 deg about "
            "two different axes in a few poses"
        )


def undetermined_offsets(jac: np.ndarray, problem: _Problem, fun: np.ndarray) -> Undetermined:
    """The target offset's directions the fit does not determine, from its Jacobian ``jac`` at the solution.

    The offset moves each measured point by ``R_tip · δt``; a shift of the tracker moves them all alike. What
    tells the two apart is the part of the offset's columns that no other parameter's columns explain: per
    pose, its singular values are how far the tool turns along each direction (rad). Where that turn is
    less than ``TURN_MARGIN`` times the model's own orientation error, the robot's errors move the offset
    along it freely (a lever of metres fits a few hundredths of a degree), so the direction is held.
    The model's orientation error is the fit's orientation rms; position-only, its position rms over the
    reach of the poses.
    """
    m = problem.free.shape[1]
    offset, others = jac[:, :m] @ problem.free.T, jac[:, m:]
    q, _ = np.linalg.qr(others)
    apart = offset - q @ (q.T @ offset)
    _, sing, vt = np.linalg.svd(apart, full_matrices=False)
    poses = sum(len(meas) for meas, _, _ in problem.parts)
    turns = sing / np.sqrt(poses)
    res = fun.reshape(-1, problem.width)
    inlier = ~outliers(res[:, :3], robust_sigma(res[:, :3]))
    if problem.position_only:
        reach = np.sqrt(np.mean(np.sum(np.concatenate([model[:, :3, 3] for _, model, _ in problem.parts]) ** 2, 1)))
        model_error = float(np.sqrt(np.mean(np.sum(res[inlier] ** 2, 1)))) / reach
    else:
        model_error = float(np.sqrt(np.mean(np.sum(res[inlier, 3:] ** 2, 1))))
    weak = turns < TURN_MARGIN * model_error
    return Undetermined(vt[weak].T, turns[weak], model_error)


def _direction_name(direction: np.ndarray) -> str:
    """``the tip's z axis`` for a direction within a degree of an axis, else its components."""
    axis = int(np.argmax(np.abs(direction)))
    if abs(direction[axis]) > np.cos(np.radians(1.0)):
        return f"the tip's {'xyz'[axis]} axis"
    return "(" + ", ".join(f"{c:+.2f}" for c in direction) + ") in the tip frame"


def fit_circle(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Centre ``(3,)``, unit normal ``(3,)`` and radius of the circle best fitting 3-D ``points``.

    The plane comes from an SVD, the circle in the plane from the algebraic (Kåsa) fit, refined by
    geometric least squares.
    """
    centroid = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centroid)
    u, v, normal = vt
    xy = np.column_stack([(points - centroid) @ u, (points - centroid) @ v])
    a = np.column_stack([2 * xy, np.ones(len(xy))])
    sol = np.linalg.lstsq(a, np.sum(xy**2, axis=1), rcond=None)[0]
    c0 = sol[:2]

    def residual(c: np.ndarray) -> np.ndarray:
        d = np.linalg.norm(xy - c, axis=1)
        return d - d.mean()

    c = least_squares(residual, c0).x
    radius = float(np.linalg.norm(xy - c, axis=1).mean())
    return centroid + c[0] * u + c[1] * v, normal, radius


def _axis_frame(c1: np.ndarray, n1: np.ndarray, c2: np.ndarray, n2: np.ndarray) -> np.ndarray:
    """A frame built from two skew or intersecting axes: origin on axis 1 at the common perpendicular's
    foot, z along axis 1, x towards axis 2's direction made perpendicular to z."""
    n1, n2 = n1 / np.linalg.norm(n1), n2 / np.linalg.norm(n2)
    w = c1 - c2
    b = n1 @ n2
    denom = 1.0 - b**2
    if denom < 1e-6:
        raise CalibrationError("the two joint axes are parallel: they do not define a frame")
    s = (b * (n2 @ w) - (n1 @ w)) / denom
    origin = c1 + s * n1
    x = n2 - b * n1
    x /= np.linalg.norm(x)
    out = np.eye(4)
    out[:3, :3] = np.column_stack([x, np.cross(n1, x), n1])
    out[:3, 3] = origin
    return out


def _joint_axis_world(chain: Chain, q: np.ndarray, joint: int) -> tuple[np.ndarray, np.ndarray]:
    frames = fk.joint_frames(chain, q[None])[0]
    return frames[joint, :3, 3], frames[joint, :3, :3] @ chain.axes[joint]


def _orient(normal: np.ndarray, reference_direction: np.ndarray) -> np.ndarray:
    """A fitted circle's normal has no sign: take the one that agrees with the model's axis."""
    return normal if normal @ reference_direction >= 0 else -normal


def circle_sweeps(chain: Chain, home: np.ndarray, joints: tuple[int, ...], span: float, count: int) -> np.ndarray:
    """Joint configurations ``(len(joints) × count, n)``: each joint swept alone about ``home``."""
    out = []
    for j in joints:
        lo = max(chain.lower[j], home[j] - span / 2) if np.isfinite(chain.lower[j]) else home[j] - span / 2
        hi = min(chain.upper[j], home[j] + span / 2) if np.isfinite(chain.upper[j]) else home[j] + span / 2
        for value in np.linspace(lo, hi, count):
            qi = home.copy()
            qi[j] = value
            out.append(qi)
    return np.array(out)


def reference_by_circles(
    chain: Chain, q: np.ndarray, meas: np.ndarray, home: np.ndarray, count: int, frame_id: str
) -> Referencing:
    """The paper's referencing from the sweeps of :func:`circle_sweeps` with joints ``(0, 1, n-2, n-1)``.

    Base: the axes of joints 1 and 2, fitted in the tracker frame, define a frame whose pose in the base
    frame the nominal model gives. Target: the axes of the last two joints, fitted and moved into the base
    frame, locate the wrist; the target's mean pose over the sweeps relative to the nominal tip gives
    the target transform.
    """
    n = chain.dof
    sweeps = {j: slice(i * count, (i + 1) * count) for i, j in enumerate((0, 1, n - 2, n - 1))}
    fitted = {}
    for j, rows in sweeps.items():
        centre, normal, _ = fit_circle(meas[rows, :3, 3])
        origin, axis = _joint_axis_world(chain, home, j)
        fitted[j] = (centre, normal, origin, axis)

    # Base: frame from axes 1-2 in the tracker frame against the same construction on the nominal model.
    # Circle normals have no sign; the model's axes fix it once the base rotation is roughly known.
    rough = se3.fit_rigid(meas[:, :3, 3], fk.fk(chain, q)[None, :, :3, 3])[0][0]
    c1, n1, o1, a1 = fitted[0]
    c2, n2, o2, a2 = fitted[1]
    n1 = _orient(n1, rough[:3, :3].T @ a1)
    n2 = _orient(n2, rough[:3, :3].T @ a2)
    measured = _axis_frame(c1, n1, c2, n2)
    nominal = _axis_frame(o1, a1, o2, a2)
    base_tracker = nominal @ se3.inverse(measured)

    # Target: the wrist frame from the last two axes, measured (now in the base frame) against nominal.
    c5, n5, o5, a5 = fitted[n - 2]
    c6, n6, o6, a6 = fitted[n - 1]
    bt = base_tracker
    c5, c6 = bt[:3, :3] @ c5 + bt[:3, 3], bt[:3, :3] @ c6 + bt[:3, 3]
    n5, n6 = _orient(bt[:3, :3] @ n5, a5), _orient(bt[:3, :3] @ n6, a6)
    wrist_measured = _axis_frame(c6, n6, c5, n5)
    wrist_nominal = _axis_frame(o6, a6, o5, a5)
    # The target in the measured wrist frame, averaged over the last two sweeps, then moved onto the
    # nominal wrist and expressed in the nominal tip frame.
    rows = np.r_[np.arange(sweeps[n - 2].start, sweeps[n - 2].stop), np.arange(sweeps[n - 1].start, sweeps[n - 1].stop)]
    tip = fk.fk(chain, q[rows])
    target_base = bt @ meas[rows]
    # Each sample: the target relative to the nominal tip after correcting the wrist's measured placement.
    correction = wrist_nominal @ se3.inverse(wrist_measured)
    in_tip = se3.inverse(tip) @ correction @ target_base
    flange_target = np.eye(4)
    flange_target[:3, 3] = in_tip[:, :3, 3].mean(axis=0)
    flange_target[:3, :3] = Rotation.from_matrix(in_tip[:, :3, :3]).mean().as_matrix()
    return Referencing(frame_id, base_tracker, flange_target, False, method="circle fits (paper)")
