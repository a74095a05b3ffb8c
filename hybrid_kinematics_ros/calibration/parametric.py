"""The parametric stage: identify an elasto-geometric model from the pairs, before the residual nets.

Parameters (all small, starting from the nominal URDF):

- zero offsets of every joint;
- joint compliances against the gravity torques computed from the URDF inertials and the payload, and a
  cubic term of each (``c₃ τ³``): gears stiffen with load (against the simulator's spring with
  ``1 + r (τ/τ_ref)²`` stiffening, a linear compliance alone leaves error above the noise floor, the cubic term
  none), and a term in ``|τ|`` (``c±``: a joint stiffer under one sign of torque than under the other);
- link bending: a rotation per Nm of joint torque about the two axes perpendicular to each joint axis;
- a small rigid transform (x, y, z, rx, ry, rz) of every joint origin and of the flange (its rotation
  also tilts the joint's axis: axis misalignment needs no parameters of its own);
- cyclic joint errors: a Fourier series (harmonics 1 … K) in each joint's own angle, the transmission and
  encoder errors of real joints. On a real UR10 (ipa-robot-accuracy) they are most of what the other
  parameters leave: a few arcseconds to an arcminute at 10-40 cycles per turn. Hundreds of coefficients
  are more than the data pins down where a joint barely moved, so they carry a ridge prior towards zero;
- a joint error map: each joint's error against its own angle on a grid of knots, for what is
  left of shorter period (on the real UR10, harmonics 40 to ~300 per turn, spread too widely for a
  few Fourier terms). It is fitted last, linearly on the other parameters' residuals, with a smoothness
  prior and a small pull to zero where a joint never went.

How many harmonics, how strong their prior, the map's step and smoothness, and which elastic terms: the
data decide (:mod:`calibration.capacity`).

Pairs from several tracker stations come referenced each on its own, with the nominal model, and that
referencing absorbs a different share of the robot's errors at each station: their base-frame poses
disagree by a small rigid move at the base and at the target (on the real UR10, series A and C fitted
together do several times worse on held-out poses than each alone). So every station but the first gets a
correction of its placement, and every target mount but the first's a correction of the mount, identified
with the robot's parameters (A and C together then do about as well as each alone); the caller folds them
into the referencings (``calibration.referencing.refine_stations``).

Many of these are not identifiable from end-effector poses (a zero offset is the same as turning the joint
origin about the joint axis; parallel axes leave some translations free). Identifiability is decided by
Gram-Schmidt on the scaled identification Jacobian's columns in a fixed order (:func:`parameter_list`'s,
no pivoting: of two equivalent parameters the earlier is kept); the dependent ones are fixed at zero and
reported, with the parameters each one is equivalent to. The rest is fitted with a robust loss by
:func:`robust_gauss_newton`: the parameters are small, so the problem is nearly linear and one Jacobian
serves several steps (thousands of pairs in seconds, many times faster than ``least_squares`` with a
Jacobian per step).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import sparse
from scipy.linalg import cho_factor, cho_solve, qr, solve_triangular
from scipy.sparse.linalg import spsolve

from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.kinematics import se3
from hybrid_kinematics_ros.kinematics.chain import Chain
from hybrid_kinematics_ros.kinematics.elastic import ElasticChain, JointMap
from hybrid_kinematics_ros.model.parametric import Parameter, build_model

ORIENTATION_LENGTH = 1.0  # m per rad: weighs orientation residuals against position ones, unless chosen (capacity)
RANK_TOLERANCE = 1e-6  # pivots below this fraction of the largest are unidentifiable
CORRELATED_PAIRS = 5  # the most correlated pairs of parameters the manifest and the report name
# The soft-L1 scale, in robust standard deviations of what the fit leaves: the fit's ordinary residuals weigh
# fully (at three, the stage's far residuals lost weight and its error beyond the trained range outgrew the
# bounds, which least squares measures), a broken beam or a bumped reflector little.
ROBUST_SIGMAS = 5.0
ROBUST_MIN_M = 1e-6  # m: the scale of noise-free residuals
# A pair whose position residual is this many robust standard deviations of one component counts as an
# outlier: Gaussian scatter leaves about one pair in 10⁵ beyond it.
OUTLIER_SIGMAS = 5.0
# Scaled unit of each kind of parameter, in SI: what one unit of the optimiser's variable means.
# The capacity of the cyclic errors and of the joint error map is chosen from the data being calibrated
# (calibration.capacity, train's default); called on its own, ``identify`` fits neither.
HARMONICS = 0  # cyclic joint errors: harmonics 1 … HARMONICS of each joint's angle (0: none)
# Ridge prior of each cyclic coefficient, in pairs: it weighs as much as this many poses seen 1 m from the joint.
HARMONIC_PRIOR = 30.0
MAP_STEP = 0.0  # rad between the joint error map's knots (0: no map)
# Weight of the map's second differences: a curvature of 1 rad per step² costs as much as a pose residual of
# this many metres in each of the pairs.
MAP_SMOOTHNESS = 0.03
MAP_RIDGE = 1e-3  # the same for the map's values themselves: where no data is, the map stays at zero
MAP_MAX_PAIRS = 50_000  # a random draw of at most this many pairs fits the map (memory and time stay bounded)
DENSE_MAP_UNKNOWNS = 10_000  # map values (joints × knots) up to which the map is solved dense (800 MB)
SCALE = {
    "zero": 1e-3,
    "compliance": 1e-4,
    "cubic": 1e-10,
    "signed": 1e-5,
    "bending": 1e-6,
    "translation": 1e-3,
    "rotation": 1e-3,
    "harmonic": 1e-4,
    "backlash": 1e-4,
}
UNITS = {
    "zero": "rad",
    "compliance": "rad/Nm",
    "cubic": "rad/Nm³",
    "signed": "rad/Nm",
    "bending": "rad/Nm",
    "translation": "m",
    "rotation": "rad",
    "harmonic": "rad",
    "backlash": "rad",
}
KINDS = tuple(SCALE)
STATION_KINDS = ("placement", "mount")  # per-station corrections of the referencing (see the module text)
STATION_SCALE = 1e-3  # m or rad: the scaled unit of a station's correction
# What robot_calibration or pybotics fit, and what a URDF can carry: joint offsets and joint origins.
GEOMETRY_KINDS = ("zero", "translation", "rotation")


def orientation_length(manifest: dict[str, Any]) -> float:
    """m per rad: the orientation residuals' weight a model's stage was fitted with (chosen from its data)."""
    chosen = (manifest.get("capacity") or {}).get("chosen") or {}
    return float(chosen.get("orientation_length", ORIENTATION_LENGTH))


def parameter_list(chain: Chain, harmonics: int = 0) -> list[Parameter]:
    """Every candidate parameter, in the order identification keeps them when two are equivalent (earlier wins).

    The cyclic joint errors come last: a geometric parameter with the same effect is the one kept.
    """
    names = chain.joint_names
    out = [Parameter(f"zero offset {j}", "zero", k, 0) for k, j in enumerate(names)]
    out += [Parameter(f"compliance {j}", "compliance", k, 0) for k, j in enumerate(names)]
    out += [Parameter(f"cubic compliance {j}", "cubic", k, 0) for k, j in enumerate(names)]
    out += [Parameter(f"signed compliance {j}", "signed", k, 0) for k, j in enumerate(names)]
    out += [Parameter(f"bending {j} {c}", "bending", k, i) for k, j in enumerate(names) for i, c in enumerate("uv")]
    frames = [f"origin {j}" for j in names] + ["flange"]
    for k, frame in enumerate(frames):
        out += [Parameter(f"{frame} {c}", "translation", k, i) for i, c in enumerate("xyz")]
        out += [Parameter(f"{frame} r{c}", "rotation", k, i) for i, c in enumerate("xyz")]
    for k, j in enumerate(names):
        for f in range(1, harmonics + 1):
            out += [
                Parameter(f"joint error {j} {t}({f} q)", "harmonic", k, 2 * (f - 1) + i)
                for i, t in enumerate(("sin", "cos"))
            ]
    return out


def _draw(station: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """At most ``count`` pair indices, shared out evenly among the stations (a station with fewer pairs
    gives all it has, the others share the rest), each station's drawn at random: one large series must
    not decide the robot's parameters alone."""
    order = rng.permutation(len(station))
    groups = [order[station[order] == s] for s in np.unique(station)]
    share = np.zeros(len(groups), dtype=int)
    left = min(count, len(station))
    while left > 0:
        open_ = [k for k, g in enumerate(groups) if share[k] < len(g)]
        each = max(1, left // len(open_))
        for k in open_:
            take = min(each, len(groups[k]) - share[k], left)
            share[k] += take
            left -= take
    return np.concatenate([g[:n] for g, n in zip(groups, share, strict=True)])


def _station_parameters(placements: int, mounts: int) -> list[Parameter]:
    axes = ("x", "y", "z", "rx", "ry", "rz")
    out = [Parameter(f"placement {k} {c}", "placement", k, i) for k in range(placements) for i, c in enumerate(axes)]
    return out + [Parameter(f"mount {k} {c}", "mount", k, i) for k in range(mounts) for i, c in enumerate(axes)]


def station_moves(params: Sequence[Parameter], values: np.ndarray, kind: str, count: int) -> np.ndarray:
    """``(count + 1, 4, 4)``: each station's ``kind`` correction (``placement`` or ``mount``) from the
    parameter values, then the identity, which label -1 (no correction) indexes."""
    x = np.zeros((count + 1, 6))
    for p, v in zip(params, values, strict=True):
        if p.kind == kind:
            x[p.index, p.component] = v
    return se3.from_rotvec(x[:, :3], x[:, 3:])


def _moved_measurements(
    T: np.ndarray,
    target: np.ndarray | None,
    position_only: bool,
    placement: np.ndarray,
    mount: np.ndarray,
    placements: np.ndarray,
    mounts: np.ndarray,
) -> tuple[np.ndarray, np.ndarray | None]:
    """The measurements as corrected referencings give them: ``D⁻¹ · T · E⁻¹`` for a 6-DoF pose, with ``D``
    the pair's placement correction and ``E`` its mount's; a point is moved by ``D⁻¹`` and its target
    offset by ``E`` instead (a point has no orientation to carry ``E⁻¹``)."""
    moved = se3.inverse(placements)[placement] @ T
    if not position_only:
        return moved @ se3.inverse(mounts)[mount], target
    offset = np.zeros(3) if target is None else target
    return moved, se3.point_at(mounts[mount], np.broadcast_to(offset, (len(T), 3)))


def pose_residuals(
    model: ElasticChain,
    q: np.ndarray,
    T: np.ndarray,
    position_only: bool,
    target: np.ndarray | None = None,
    orientation_length: float = ORIENTATION_LENGTH,
) -> np.ndarray:
    """``(N, 3)`` or ``(N, 6)``: measured minus modelled position (m), then rotation (rad × ``orientation_length`` m).

    Position-only: ``T`` holds measured points at ``target`` (m, tip frame; None: the tip itself).
    """
    pred = model.fk(q)
    if position_only:
        return T[:, :3, 3] - se3.point_at(pred, target)
    dp = T[:, :3, 3] - pred[:, :3, 3]
    w = se3.rotvec(T[:, :3, :3] @ np.swapaxes(pred[:, :3, :3], 1, 2))
    return np.concatenate([dp, orientation_length * w], axis=1)


def _joint_rows(
    model: ElasticChain,
    q: np.ndarray,
    position_only: bool,
    target: np.ndarray | None,
    orientation_length: float,
) -> np.ndarray:
    """``(N, width, n)``: how :func:`pose_residuals` changes per radian added to each joint, negated (the
    residual is measured minus modelled)."""
    tips, jac = model.fk_and_jacobian(q)
    lin, ang = jac[:, :3], jac[:, 3:]
    if position_only:
        arm = se3.point_at(tips, target) - tips[:, :3, 3]  # tip to target, per pair
        rows = lin + np.cross(ang, arm[:, :, None], axisa=1, axisb=1, axisc=1)
    else:
        rows = np.concatenate([lin, orientation_length * ang], axis=1)
    return -rows


def _joint_error_jacobian(
    model: ElasticChain,
    q: np.ndarray,
    basis: np.ndarray,
    joints: np.ndarray,
    position_only: bool,
    target: np.ndarray | None,
    orientation_length: float,
) -> np.ndarray:
    """``(N × width, m)``: derivatives of :func:`pose_residuals` by cyclic joint-error coefficients (rad).

    ``model`` without cyclic errors, at the joints ``q`` they shift to; ``basis (N, m)``: each coefficient's
    ``sin(f q)`` or ``cos(f q)`` and ``joints (m,)`` its joint. The coefficients enter through the joint
    angles, so each column is the joint's Jacobian column times its basis function: one Jacobian instead
    of a model evaluation per coefficient.
    """
    rows = _joint_rows(model, q, position_only, target, orientation_length)
    return (rows[:, :, joints] * basis[:, None, :]).reshape(-1, len(joints))


def fit_joint_map(
    model: ElasticChain,
    q: np.ndarray,
    T: np.ndarray,
    position_only: bool,
    target: np.ndarray | None = None,
    step: float = 0.01,
    smoothness: float = MAP_SMOOTHNESS,
    orientation_length: float = ORIENTATION_LENGTH,
) -> JointMap:
    """The joint error map that best explains what ``model`` leaves of the pairs, linearised at ``model``
    (its errors are microradians) and solved as one sparse regularised least-squares problem.

    Each joint's knots span the angles it was seen at, one step beyond. A pair touches two knots per
    joint, so the problem stays sparse however fine the map.
    """
    n = model.dof
    lower = q.min(axis=0) - step
    width = int(np.floor((q.max(axis=0) - lower) / step).max()) + 2  # knots per joint: the widest range's
    joint_map = JointMap(lower, step, np.zeros((n, width)))
    res = pose_residuals(model, q, T, position_only, target, orientation_length)
    rows = _joint_rows(model, q, position_only, target, orientation_length)  # (N, w, n)
    values = solve_joint_map(map_design(joint_map, q, rows), res.ravel(), len(q), n, width, smoothness, MAP_RIDGE)
    return JointMap(lower, step, values)


def map_design(joint_map: JointMap, q: np.ndarray, rows: np.ndarray) -> sparse.csr_matrix:
    """``(N × width, n × knots)``: how the residuals of pairs at ``q`` change with the map's knot values,
    from their joint rows ``(N, width, n)`` (:func:`_joint_rows`). Two knots per joint and pair: sparse."""
    pairs, w, n = rows.shape
    knots = joint_map.values.shape[1]
    row_index = np.arange(pairs * w).reshape(pairs, w)
    ii, jj, vv = [], [], []
    for k in range(n):
        knot, w0, w1 = joint_map.weights(q[:, k], k)
        for index, weight in ((knot, w0), (knot + 1, w1)):
            ii.append(row_index.ravel())
            jj.append(np.repeat(k * knots + index, w))
            vv.append((rows[:, :, k] * weight[:, None]).ravel())
    return sparse.csr_matrix(
        (-np.concatenate(vv), (np.concatenate(ii), np.concatenate(jj))), shape=(pairs * w, n * knots)
    )


def solve_joint_map(
    design: sparse.csr_matrix,
    res: np.ndarray,
    pairs: int,
    n: int,
    knots: int,
    smoothness: float = MAP_SMOOTHNESS,
    ridge: float = MAP_RIDGE,
) -> np.ndarray:
    """``(n, knots)``: the map's values that best explain the residuals ``res`` (flat) through ``design``
    (:func:`map_design`), with the smoothness prior and the pull to zero, both weighted by the ``pairs``
    count."""
    curvature = sparse.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(knots - 2, knots))
    smooth = sparse.block_diag([curvature] * n)
    # The normal equations are sparse (a pair couples two knots of each joint) and the priors keep them well
    # conditioned. A pair couples every joint's knots with every other's, though: a factorisation fills in
    # nearly completely, and a dense Cholesky is several times faster than a sparse LU at a few thousand
    # unknowns, with the same answer to rounding. Beyond DENSE_MAP_UNKNOWNS the sparse solve keeps the memory
    # bounded.
    normal = (design.T @ design + pairs * smoothness**2 * (smooth.T @ smooth)).tocsc()
    normal = normal + pairs * ridge**2 * sparse.identity(n * knots, format="csc")
    rhs = design.T @ res
    if n * knots > DENSE_MAP_UNKNOWNS:
        return spsolve(normal, rhs).reshape(n, knots)
    return cho_solve(cho_factor(normal.toarray()), rhs).reshape(n, knots)


@dataclass
class ParametricResult:
    model: ElasticChain
    params: list[Parameter]
    values: np.ndarray  # SI, zero where unidentifiable
    rigid_values: np.ndarray  # the best fit of the geometry alone (GEOMETRY_KINDS): what a URDF can carry
    identifiable: np.ndarray  # bool per parameter
    reasons: dict[str, str]  # unidentifiable parameter name -> why
    rms_before: dict[str, float]
    rms_after: dict[str, float]
    position_only: bool
    nominal: Chain | None = None  # the chain the parameters are relative to
    joint_map: JointMap | None = None
    # Corrections of the tracker placements and target mounts (``identify``'s labels 0, 1, …), ``(k, 4, 4)``:
    # the measurements fit the model as ``placement⁻¹ · T · mount⁻¹``; see referencing.refine_stations.
    placements: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    mounts: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    capacity: dict[str, Any] | None = None  # how the capacity was chosen (calibration.capacity), if it was
    options: dict[str, Any] | None = None  # the capacity options it was identified with (kinds, harmonics, …)
    uncertainty: Uncertainty | None = None  # σ per parameter (``params`` order), condition, correlations
    robust_scale: np.ndarray | None = None  # m: the robust loss's scale the fit ended with, per residual column
    # the pairs (indices into those identified from) whose position the stage leaves beyond ``outlier_limit`` (m)
    outliers: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    outlier_limit: float = float("nan")

    def geometry_model(self) -> ElasticChain:
        """The geometry-only calibration (joint offsets and joint origins, no compliance, bending or
        cyclic errors): what robot_calibration or pybotics give, and what a URDF export carries."""
        if self.nominal is None:
            raise CalibrationError("this result does not know its nominal chain")
        m = self.model
        return build_model(
            self.nominal, self.params, self.rigid_values, m.payload_mass, m.payload_com, gravity=m.gravity
        )

    def manifest(self) -> dict[str, Any]:
        m = self.model
        return {
            "payload": {"mass": m.payload_mass, "com": m.payload_com.tolist(), "gravity": m.gravity.tolist()},
            "position_only": self.position_only,
            "rms_before": self.rms_before,
            "rms_after": self.rms_after,
            "robust_scale_mm": None if self.robust_scale is None else (1e3 * self.robust_scale[::3]).tolist(),
            "outliers": {"pairs": len(self.outliers), "beyond_mm": 1e3 * self.outlier_limit},
            "parameters": [
                {
                    "name": p.name,
                    "kind": p.kind,
                    "index": p.index,
                    "component": p.component,
                    "unit": UNITS[p.kind],
                    "value": float(v),
                    "rigid_value": float(r),
                    "identifiable": bool(ok),
                    **({"sigma": float(sd)} if np.isfinite(sd) else {}),
                    **({"reason": self.reasons[p.name]} if p.name in self.reasons else {}),
                }
                for p, v, r, ok, sd in zip(
                    self.params, self.values, self.rigid_values, self.identifiable, self._sigma(), strict=True
                )
            ],
            **({"uncertainty": self.uncertainty.manifest()} if self.uncertainty is not None else {}),
            **({"joint_map": self.joint_map.manifest()} if self.joint_map is not None else {}),
        }

    def _sigma(self) -> np.ndarray:
        return self.uncertainty.sigma if self.uncertainty is not None else np.full(len(self.params), np.nan)


def _rms(res: np.ndarray) -> dict[str, float]:
    out = {"position_mm": float(1e3 * np.sqrt(np.mean(np.sum(res[:, :3] ** 2, axis=1))))}
    if res.shape[1] == 6:
        out["orientation_deg"] = float(np.degrees(np.sqrt(np.mean(np.sum(res[:, 3:] ** 2, axis=1)))))
    return out


@dataclass
class Linearisation:
    """The stage's least-squares problem linearised at the nominal model, over the drawn pairs: what
    capacity selection (:mod:`calibration.capacity`) cross-validates, with a solve per candidate and fold.

    The residual of pair ``i`` after parameters ``z`` (scaled units) is ``residual[i] + jacobian[i] @ z``;
    its error is second order in parameters of a few milliradians (about a micrometre)."""

    pick: np.ndarray  # (N,) indices of the drawn pairs in the caller's order
    q: np.ndarray  # (N, n) their joints
    params: list[Parameter]  # every column: the chain's, the stations', then the harmonics
    residual: np.ndarray  # (N, width): measured minus nominal, position m then orientation rad × orientation_length
    jacobian: np.ndarray  # (N, width, P) per scaled unit
    identifiable: np.ndarray  # (P,) bool
    scale: np.ndarray  # (P,) SI per scaled unit
    joint_rows: np.ndarray  # (N, width, n): the residuals' change per radian of each joint (the joint map's)
    orientation_length: float = ORIENTATION_LENGTH  # m per rad: the orientation rows' weight

    def reweighted(self, orientation_length: float) -> Linearisation:
        """The same problem with the orientation rows weighed at ``orientation_length`` m per rad: the rows
        are linear in the weight, so this is exact (the problem as :func:`linearise` would give it)."""
        if self.residual.shape[1] != 6:
            return self
        factor = np.r_[np.ones(3), np.full(3, orientation_length / self.orientation_length)]
        return dataclasses.replace(
            self,
            residual=self.residual * factor,
            jacobian=self.jacobian * factor[:, None],
            joint_rows=self.joint_rows * factor[:, None],
            orientation_length=float(orientation_length),
        )


def linearise(chain: Chain, q: np.ndarray, T: np.ndarray, **options: Any) -> Linearisation:
    """The stage's problem for :func:`identify`'s arguments, linearised at the nominal model, unsolved."""
    return Stage.of(chain, q, T, **options).linearise()


def identify(
    chain: Chain,
    q: np.ndarray,
    T: np.ndarray,
    payload_mass: float = 0.0,
    payload_com: np.ndarray | None = None,
    **options: Any,
) -> ParametricResult:
    """Identify the elasto-geometric parameters from joints ``q (N, n)`` and measured base-frame poses ``T``
    (the options: :class:`StageOptions`, and :class:`Stage`'s per-pair ``target``, ``placement``, ``mount`` and
    ``directions``)."""
    return Stage.of(chain, q, T, payload_mass=payload_mass, payload_com=payload_com, **options).identify()


@dataclass(frozen=True)
class StageOptions:
    """How the stage is identified.

    ``payload_mass`` (kg) and ``payload_com`` (m, tip frame): the payload the arm carried. ``gravity``: m/s² in
    the base frame (None: −9.81 along z, a floor mount; a wall or ceiling mount needs its own).
    ``position_only``: the measurements are target points. At most ``max_pairs`` pairs (drawn reproducibly
    from ``seed``, evenly from each tracker placement) enter the fit: a few thousand pin the parameters down far
    below the tracker noise, and the cost grows with the count; ``max_nfev``: Gauss-Newton's evaluations.

    ``kinds``: the kinds of parameter to fit (default all of :data:`KINDS`; :data:`GEOMETRY_KINDS` is a
    geometry-only calibration); the others stay zero. ``harmonics``: how many harmonics of the cyclic joint
    errors (0: none), each coefficient held towards zero by ``harmonic_prior`` (in pairs). ``map_step``: the
    joint error map's knot spacing (0: no map), fitted last from all the pairs (at most
    :data:`MAP_MAX_PAIRS`), with ``map_smoothness``. ``orientation_length`` (m per rad) weighs the orientation
    residuals against the position ones; ``robust_scale`` (m): residuals well above it are down-weighted (None:
    chosen from the data, :meth:`Stage.solve`)."""

    payload_mass: float = 0.0
    payload_com: np.ndarray | None = None
    gravity: np.ndarray | None = None
    position_only: bool = False
    max_pairs: int = 5000
    seed: int = 0
    max_nfev: int = 30
    kinds: Sequence[str] | None = None
    harmonics: int = HARMONICS
    harmonic_prior: float = HARMONIC_PRIOR
    orientation_length: float = ORIENTATION_LENGTH
    robust_scale: float | None = None
    map_step: float = MAP_STEP
    map_smoothness: float = MAP_SMOOTHNESS


@dataclass(frozen=True)
class _Start:
    """The problem at the nominal model: its pose residual (flat), the Jacobian (pose rows, then the priors'),
    the identifiable columns and why the others are not."""

    r0: np.ndarray
    jacobian: np.ndarray
    active: np.ndarray
    reasons: dict[str, str]


class Stage:
    """The stage's least-squares problem over the drawn pairs: its parameters (the chain's, the stations'
    corrections, then the cyclic terms) in scaled units, and the residual and Jacobian at any values of them.

    Per pair: ``target`` (m, ``(3,)`` or ``(N, 3)``), position-only, the target's offset in the tip frame, which
    makes the flange's rotation observable; ``placement`` and ``mount`` (``(N,)`` ints), which tracker placement
    and which target mount it was measured with, -1 for the reference ones that get no correction (the first
    station's; see the module text), whose corrections come back as :attr:`ParametricResult.placements` and
    ``mounts``; ``directions (N, n)``, the joints' approach directions (:mod:`kinematics.approach`): with the
    ``backlash`` kind, each joint seen arriving both ways gets a backlash term (its angle shifted by ``b`` times
    its direction), which the served model applies with the directions it is given."""

    @classmethod
    def of(
        cls,
        chain: Chain,
        q: np.ndarray,
        T: np.ndarray,
        target: np.ndarray | None = None,
        placement: np.ndarray | None = None,
        mount: np.ndarray | None = None,
        directions: np.ndarray | None = None,
        **options: Any,
    ) -> Stage:
        """The problem of :func:`identify`'s arguments."""
        return cls(chain, q, T, StageOptions(**options), target, placement, mount, directions)

    def __init__(
        self,
        chain: Chain,
        q: np.ndarray,
        T: np.ndarray,
        options: StageOptions,
        target: np.ndarray | None = None,
        placement: np.ndarray | None = None,
        mount: np.ndarray | None = None,
        directions: np.ndarray | None = None,
    ) -> None:
        if len(q) < 20:
            raise CalibrationError(f"only {len(q)} pairs: the parametric stage needs at least 20")
        o = options
        self.chosen = KINDS if o.kinds is None else tuple(o.kinds)
        unknown = sorted(set(self.chosen) - set(KINDS))
        if unknown:
            raise CalibrationError(f"unknown parameter kinds {unknown}; choose from {list(KINDS)}")
        self.chain, self.q, self.T, self.o = chain, q, T, o
        self.com = np.zeros(3) if o.payload_com is None else np.asarray(o.payload_com, dtype=float)
        self.every_target = None if target is None else np.asarray(target, dtype=float)  # (3,), or one per pair
        self.every_direction = None if directions is None else np.asarray(directions, dtype=float)
        self.placement = np.full(len(q), -1) if placement is None else np.asarray(placement, dtype=int)
        self.mount = np.full(len(q), -1) if mount is None else np.asarray(mount, dtype=int)
        self.pick = _draw(self.placement, o.max_pairs, np.random.default_rng(o.seed))
        self.q_fit = q[self.pick]
        self.counts = (int(self.placement.max()) + 1, int(self.mount.max()) + 1)
        self.params = self._parameters()
        self.scale = np.array([SCALE.get(p.kind, STATION_SCALE) for p in self.params])
        self.movable = np.array([p.kind in STATION_KINDS for p in self.params])
        self.chain_params = [p for p, m in zip(self.params, self.movable, strict=True) if not m]
        self.cyclic = np.array([p.kind in ("harmonic", "backlash") for p in self.params])  # shifts of the joints
        harmonic = np.array([p.kind == "harmonic" for p in self.params])
        self.joints = np.array([p.index for p in self.params])
        self.prior = np.where(harmonic, np.sqrt(o.harmonic_prior), 0.0) * self.scale  # m per scaled unit, × 1 m
        self.held_back = self.prior > 0
        self.basis = self._cyclic_basis()
        self.column = np.cumsum(self.cyclic) - 1  # column of a cyclic parameter in ``basis``
        self.width = 3 if o.position_only else 6

    def _parameters(self) -> list[Parameter]:
        """The chain's, the stations' corrections, the cyclic errors', then the backlash terms of the joints
        seen arriving both ways."""
        chain = self.chain
        harmonics = self.o.harmonics if "harmonic" in self.chosen else 0
        geometric = parameter_list(chain, 0)
        params = geometric + _station_parameters(*self.counts) + parameter_list(chain, harmonics)[len(geometric) :]
        if self.every_direction is not None and "backlash" in self.chosen:
            d_fit = self.every_direction[self.pick]
            both = np.flatnonzero(np.any(d_fit > 0, axis=0) & np.any(d_fit < 0, axis=0))
            params += [Parameter(f"backlash {chain.joint_names[j]}", "backlash", int(j), 0) for j in both]
        return params

    def _cyclic_basis(self) -> np.ndarray:
        """Each cyclic coefficient's basis function at the fitted joints, ``(N, m)``: computed once, not per
        evaluation; a backlash term shifts its joint by its value times the direction."""
        cyclic = self.cyclic
        components = np.array([p.component for p in self.params])[cyclic]
        phase = self.q_fit[:, self.joints[cyclic]] * (components // 2 + 1)
        basis = np.where(components % 2 == 0, np.sin(phase), np.cos(phase))
        shifting = np.array([p.kind == "backlash" for p in self.params])[cyclic]
        if shifting.any():
            basis[:, shifting] = self.every_direction[self.pick][:, self.joints[cyclic][shifting]]
        return basis

    def values_at(self, z: np.ndarray, active: np.ndarray, fixed: np.ndarray) -> np.ndarray:
        """SI values: ``fixed``, with the ``active`` ones at ``z`` (scaled units)."""
        values = fixed.copy()
        values[active] = z * self.scale[active]
        return values

    def chain_model(self, values: np.ndarray, joint_map: JointMap | None = None) -> ElasticChain:
        o = self.o
        chain_values = values[~self.movable]
        return build_model(self.chain, self.chain_params, chain_values, o.payload_mass, self.com, joint_map, o.gravity)

    def measurements(self, values: np.ndarray, rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """The measured poses of pairs ``rows`` (the drawn ones by default) and their target offsets, moved by the
        station corrections."""
        rows = self.pick if rows is None else rows
        every = self.every_target
        offsets = every if every is None or np.ndim(every) == 1 else every[rows]
        if not self.movable.any():
            return self.T[rows], offsets
        moves = (station_moves(self.params, values, k, n) for k, n in zip(STATION_KINDS, self.counts, strict=True))
        return _moved_measurements(
            self.T[rows], offsets, self.o.position_only, self.placement[rows], self.mount[rows], *moves
        )

    def shifted_joints(self, values: np.ndarray, active: np.ndarray) -> np.ndarray:
        """The fitted joints shifted by the cyclic errors (the model itself is then built without them)."""
        on = active & self.cyclic
        if not on.any():
            return self.q_fit
        shift = (self.basis[:, self.column[on]] * values[on]) @ (self.joints[on][:, None] == np.arange(self.chain.dof))
        return self.q_fit + shift

    def model_at(
        self, z: np.ndarray, active: np.ndarray, fixed: np.ndarray
    ) -> tuple[ElasticChain, np.ndarray, np.ndarray]:
        """The model without its cyclic errors, the joints they shift the fitted ones to, and the values."""
        values = self.values_at(z, active, fixed)
        return self.chain_model(np.where(self.cyclic, 0.0, values)), self.shifted_joints(values, active), values

    def pose_part(self, model: ElasticChain, shifted: np.ndarray, values: np.ndarray) -> np.ndarray:
        measured, offsets = self.measurements(values)
        o = self.o
        return pose_residuals(model, shifted, measured, o.position_only, offsets, o.orientation_length).ravel()

    def residual(self, z: np.ndarray, active: np.ndarray, fixed: np.ndarray) -> np.ndarray:
        """The pose rows, then the priors' rows of the active held-back parameters."""
        pulled = self.prior[active & self.held_back] * z[self.held_back[active]]
        return np.concatenate([self.pose_part(*self.model_at(z, active, fixed)), pulled])

    def jacobian(self, z: np.ndarray, active: np.ndarray, fixed: np.ndarray) -> np.ndarray:
        """Forward differences for the geometric, elastic and station parameters, closed form for the cyclic."""
        model, shifted, values = self.model_at(z, active, fixed)
        r0 = self.pose_part(model, shifted, values)
        cols = np.flatnonzero(active)
        jac = np.zeros((len(r0) + int(np.sum(active & self.held_back)), len(cols)))
        back = np.flatnonzero(self.held_back[cols])
        jac[len(r0) + np.arange(len(back)), back] = self.prior[cols[back]]
        step = 1e-3
        for i, c in enumerate(cols):
            if self.cyclic[c]:
                continue
            zi = z.copy()
            zi[i] += step
            moved_values = self.values_at(zi, active, fixed)
            moved = model if self.movable[c] else self.chain_model(np.where(self.cyclic, 0.0, moved_values))
            jac[: len(r0), i] = (self.pose_part(moved, shifted, moved_values) - r0) / step
        on = self.cyclic[cols]
        if on.any():
            o = self.o
            block = _joint_error_jacobian(
                model,
                shifted,
                self.basis[:, self.column[cols[on]]],
                self.joints[cols[on]],
                o.position_only,
                self.measurements(values)[1],
                o.orientation_length,
            )
            first = int(np.argmax(on))  # the cyclic parameters come last
            jac[: len(r0), first:] = block * self.scale[cols[on]]
        return jac

    def solve(
        self, subset: np.ndarray, start: np.ndarray, fixed: np.ndarray, first_jac: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """The ``subset`` of parameters fitted from ``start`` (scaled units), the others at ``fixed``, and the
        robust loss's scale it ended with (m; position, then orientation).

        Unless the options give that scale, the data choose it (:func:`robust_scales`): the first fit takes
        it from the residuals at ``start``, so a nominal model's error of centimetres still weighs fully; the
        second, from the first one's end, takes it from what that fit leaves, so only pairs far off what the
        fitted parameters explain (not what the start misses) are down-weighted. The priors' rows stay
        quadratic, as capacity selection's linear fits hold them."""
        held = int(np.sum(subset & self.held_back))

        def fit(z: np.ndarray, scale: np.ndarray, jac: np.ndarray | None) -> np.ndarray:
            rows = np.r_[np.tile(scale, len(self.pick)), np.full(held, np.inf)]
            return robust_gauss_newton(
                lambda z: self.residual(z, subset, fixed),
                lambda z: self.jacobian(z, subset, fixed),
                z,
                rows,
                self.o.max_nfev,
                jac,
            )

        if self.o.robust_scale is not None:
            given = np.full(self.width, self.o.robust_scale)
            return fit(start, given, first_jac), given
        z = fit(start, self._scales(start, subset, fixed), first_jac)
        scale = self._scales(z, subset, fixed)
        return fit(z, scale, None), scale

    def _scales(self, z: np.ndarray, subset: np.ndarray, fixed: np.ndarray) -> np.ndarray:
        return robust_scales(self.pose_part(*self.model_at(z, subset, fixed)).reshape(-1, self.width))

    def start(self) -> _Start:
        """The problem at the nominal model, and which parameters the pairs identify."""
        everything = np.ones(len(self.params), dtype=bool)
        nothing = np.zeros(len(self.params))
        r0 = self.pose_part(*self.model_at(nothing, everything, nothing))
        full_jac = self.jacobian(nothing, everything, nothing)
        wanted = np.array([p.kind in self.chosen for p in self.params]) | self.movable
        fitted = [p for p, w in zip(self.params, wanted, strict=True) if w]
        active, reasons = _identifiable(full_jac[: len(r0), wanted], fitted, self.o.position_only)
        reasons.update({p.name: "not fitted (kinds)" for p, w in zip(self.params, wanted, strict=True) if not w})
        return _Start(r0, full_jac, _expand(active, wanted), reasons)

    def linearise(self) -> Linearisation:
        """The problem linearised at the nominal model, unsolved (:class:`Linearisation`)."""
        start, o = self.start(), self.o
        nothing = np.zeros(len(self.params))
        joint_rows = _joint_rows(
            self.chain_model(nothing), self.q_fit, o.position_only, self.measurements(nothing)[1], o.orientation_length
        )
        return Linearisation(
            pick=self.pick,
            q=self.q_fit,
            params=self.params,
            residual=start.r0.reshape(-1, self.width),
            jacobian=start.jacobian[: len(start.r0)].reshape(len(self.pick), self.width, -1),
            identifiable=start.active,
            scale=self.scale,
            joint_rows=joint_rows,
            orientation_length=float(o.orientation_length),
        )

    def identify(self) -> ParametricResult:
        """The fitted stage: the identifiable parameters, the joint error map on top, and the geometry alone."""
        start = self.start()
        r0, active = start.r0, start.active
        nothing = np.zeros(len(self.params))
        # the Jacobian at zero, already computed, starts the fit: its pose rows, then the active priors' rows
        start_rows = np.r_[np.arange(len(r0)), len(r0) + np.flatnonzero(active[self.held_back])]
        start_jac = start.jacobian[np.ix_(start_rows, np.flatnonzero(active))]
        z, scale = self.solve(active, np.zeros(int(active.sum())), nothing, first_jac=start_jac)
        values = self.values_at(z, active, nothing)
        cols = np.flatnonzero(active)
        covariance = _covariance(
            self.jacobian(z, active, nothing), self.residual(z, active, nothing), len(r0), self.width
        )
        scales = self.scale[cols]
        uncertainty = Uncertainty.of(covariance * np.outer(scales, scales), cols, self.params, ~self.movable)
        model = self.chain_model(values)
        joint_map = self._joint_map(model, values)
        if joint_map is not None:
            model = self.chain_model(values, joint_map)
        keep, o = ~self.movable, self.o
        measured, offsets = self.measurements(values)
        after = pose_residuals(
            model, self._reached(model, self.pick), measured, o.position_only, offsets, o.orientation_length
        )
        sigma = robust_sigma(after[:, :3])
        return ParametricResult(
            model=model,
            params=self.chain_params,
            values=values[keep],
            rigid_values=self._rigid_values(start, values)[keep],
            identifiable=active[keep],
            reasons={n: why for n, why in start.reasons.items() if not n.startswith(("placement ", "mount "))},
            rms_before=_rms(r0.reshape(-1, self.width)),
            rms_after=_rms(after),
            position_only=o.position_only,
            nominal=self.chain,
            joint_map=joint_map,
            placements=station_moves(self.params, values, "placement", self.counts[0])[:-1],
            mounts=station_moves(self.params, values, "mount", self.counts[1])[:-1],
            uncertainty=uncertainty,
            robust_scale=scale,
            outliers=self.pick[outliers(after[:, :3], sigma)],
            outlier_limit=OUTLIER_SIGMAS * sigma,
        )

    def _reached(self, model: ElasticChain, rows: np.ndarray) -> np.ndarray:
        """The pairs' joints shifted by the backlash terms (the joint error map is fitted on top of them)."""
        return model.approached(self.q[rows], None if self.every_direction is None else self.every_direction[rows])

    def _joint_map(self, model: ElasticChain, values: np.ndarray) -> JointMap | None:
        """The joint error map fitted to what the stage leaves, from all the pairs (at most MAP_MAX_PAIRS)."""
        o = self.o
        if not (o.map_step > 0 and "harmonic" in self.chosen):
            return None
        draw = np.sort(np.random.default_rng(o.seed).permutation(len(self.q))[:MAP_MAX_PAIRS])
        measured, offsets = self.measurements(values, draw)
        return fit_joint_map(
            model,
            self._reached(model, draw),
            measured,
            o.position_only,
            offsets,
            o.map_step,
            o.map_smoothness,
            orientation_length=o.orientation_length,
        )

    def _rigid_values(self, start: _Start, values: np.ndarray) -> np.ndarray:
        """The same fit with the geometry alone, for a URDF export: the geometry then absorbs what it can, with
        the station corrections held (the referencings carry them for both)."""
        geometric = start.active & np.array([p.kind in GEOMETRY_KINDS for p in self.params])
        held = np.where(self.movable, values, 0.0)
        rigid = held.copy()
        scale = self.scale[geometric]
        first_jac = start.jacobian[: len(start.r0)][:, geometric]
        rigid[geometric] = self.solve(geometric, values[geometric] / scale, held, first_jac)[0] * scale
        return rigid


def _covariance(jac: np.ndarray, res: np.ndarray, pose_rows: int, width: int) -> np.ndarray:
    """The covariance of the fitted (scaled) parameters between fits on new poses: the sandwich
    ``A⁻¹ (Σᵢ gᵢ gᵢᵀ) A⁻¹`` with ``A = JᵀWJ + RᵀR`` and ``gᵢ = JᵢᵀW rᵢ`` the pull of pose ``i``'s residual
    (``J`` the pose rows, ``R`` the priors' rows: a prior narrows the spread of what it holds). What the stage
    leaves unmodelled is larger at some poses than at others; the sandwich takes each pose's own residual, so
    those poses weigh as much as they scatter. ``W`` weighs the position and orientation rows by the inverse
    of their mean squared residual (their scatter differs); the priors' rows are in the position rows' units,
    as the cost weighs them."""
    pose = res[:pose_rows].reshape(-1, width)
    dof_share = max(1.0 - jac.shape[1] / pose_rows, 1e-3)  # the parameters take their share of the scatter
    variance = np.array([np.mean(pose[:, b : b + 3] ** 2) for b in range(0, width, 3)])
    weight = 1.0 / np.tile(np.repeat(variance, 3), len(pose))
    data = jac[:pose_rows]
    priors = jac[pose_rows:] / np.sqrt(variance[0])
    inverse = np.linalg.inv(data.T @ (weight[:, None] * data) + priors.T @ priors)
    pulls = np.einsum("nwp,nw->np", (weight[:, None] * data).reshape(len(pose), width, -1), pose)
    return inverse @ (pulls.T @ pulls / dof_share) @ inverse


@dataclass(frozen=True)
class Uncertainty:
    """How well the data pin the fitted parameters down: each one's σ (SI, NaN where not fitted), the
    condition number of their correlation matrix (the stations' corrections included), and the most correlated
    pairs of the chain's parameters.

    σ takes the residuals left after the fit, tracker noise and what the stage does not model, as independent
    from pose to pose: it is the spread expected between calibrations on new poses. Measuring the same poses
    again varies only the noise, and the fits then spread less than σ says."""

    sigma: np.ndarray
    condition_number: float
    correlated: tuple[tuple[str, str, float], ...]

    @classmethod
    def of(cls, covariance: np.ndarray, cols: np.ndarray, params: list[Parameter], keep: np.ndarray) -> Uncertainty:
        """From the SI covariance of the fitted columns ``cols`` of ``params``; ``keep``: the chain's parameters
        (the stations' corrections are fitted too, but reported with the referencing)."""
        sd = np.sqrt(np.diag(covariance))
        sigma = np.full(len(params), np.nan)
        sigma[cols] = sd
        correlation = covariance / np.outer(sd, sd)
        eig = np.linalg.eigvalsh(correlation)
        chain = np.flatnonzero(keep[cols])
        a, b = (chain[k] for k in np.triu_indices(len(chain), 1))
        top = np.argsort(-np.abs(correlation[a, b]), kind="stable")[:CORRELATED_PAIRS]
        pairs = tuple((params[cols[a[t]]].name, params[cols[b[t]]].name, float(correlation[a[t], b[t]])) for t in top)
        return cls(sigma[keep], float(np.sqrt(eig.max() / max(eig.min(), 1e-300))), pairs)

    def manifest(self) -> dict[str, Any]:
        return {
            "condition_number": self.condition_number,
            "correlated": [{"a": a, "b": b, "correlation": r} for a, b, r in self.correlated],
        }


def robust_sigma(res: np.ndarray) -> float:
    """The robust standard deviation of residuals ``res`` (any shape; each component one residual, centred
    on zero): 1.4826 times their median absolute value, which model error and a few outliers barely move."""
    return 1.4826 * float(np.median(np.abs(res)))


def robust_scale(res: np.ndarray) -> float:
    """The soft-L1 scale for what a fit leaves, ``res`` (m): :data:`ROBUST_SIGMAS` robust standard
    deviations, so the loss follows the data's own scatter instead of a fixed length."""
    return max(ROBUST_SIGMAS * robust_sigma(res), ROBUST_MIN_M)


def robust_scales(res: np.ndarray) -> np.ndarray:
    """Per column of pose residuals ``res (N, 3 or 6)``: the position columns' :func:`robust_scale`, then
    the orientation columns' (their scatter differs from the positions' by the orientation length)."""
    return np.repeat([robust_scale(res[:, k : k + 3]) for k in range(0, res.shape[1], 3)], 3)


def outliers(position: np.ndarray, sigma: float) -> np.ndarray:
    """Which pairs' position residuals ``(N, 3)`` (m) lie beyond :data:`OUTLIER_SIGMAS` times ``sigma``."""
    return np.linalg.norm(position, axis=1) > OUTLIER_SIGMAS * max(sigma, ROBUST_MIN_M)


def _soft_l1_cost(res: np.ndarray, scale: float | np.ndarray) -> float:
    """scipy's soft-L1 cost, ``Σ s² (2 (√(1 + (r/s)²) − 1))``: quadratic below ``s``, linear above; written as
    ``Σ 2 r² / (√(1 + (r/s)²) + 1)``, which keeps its digits for ``r ≪ s`` and is ``Σ r²`` at ``s = ∞``."""
    return float(np.sum(2.0 * res**2 / (np.sqrt(1.0 + (res / scale) ** 2) + 1.0)))


def robust_gauss_newton(
    residual: Callable[[np.ndarray], np.ndarray],
    jacobian: Callable[[np.ndarray], np.ndarray],
    x0: np.ndarray,
    scale: float | np.ndarray,
    max_steps: int = 30,
    first_jacobian: np.ndarray | None = None,
    refresh: int = 4,
    tolerance: float = 1e-6,
) -> np.ndarray:
    """Minimise scipy's soft-L1 cost of ``residual(x)`` by Levenberg-Marquardt steps on reweighted normal
    equations (IRLS: each residual weighted by ``1 / √(1 + (r/s)²)``), the minimiser ``least_squares(...,
    loss="soft_l1")`` finds. ``scale`` (m): the loss's, one for every residual or one each.

    The calibration's parameters are small and their effects nearly linear, so a Jacobian (the costly part:
    a model evaluation per geometric parameter) is recomputed only every ``refresh`` accepted steps; each
    step still costs one residual evaluation and is accepted only if the true cost falls. Stops after
    ``max_steps`` steps or when a step gains less than ``tolerance`` of the cost.
    """
    x = np.array(x0, dtype=float)
    res = residual(x)
    cost = _soft_l1_cost(res, scale)
    jac = jacobian(x) if first_jacobian is None else first_jacobian
    fresh = 0  # accepted steps since the Jacobian was computed
    damping = 1e-6
    for _ in range(max_steps):
        if fresh >= refresh:
            jac, fresh = jacobian(x), 0
        weight = 1.0 / np.sqrt(1.0 + (res / scale) ** 2)
        normal = jac.T @ (weight[:, None] * jac)
        gradient = jac.T @ (weight * res)
        diagonal = np.maximum(np.diag(normal), 1e-12 * max(float(np.max(np.diag(normal), initial=0.0)), 1e-300))
        while True:
            step = -cho_solve(cho_factor(normal + damping * np.diag(diagonal)), gradient)
            trial = residual(x + step)
            trial_cost = _soft_l1_cost(trial, scale)
            if trial_cost < cost or damping > 1e6:
                break
            damping *= 10.0
        if trial_cost >= cost:
            break
        gain = cost - trial_cost
        x, res, cost = x + step, trial, trial_cost
        damping = max(damping / 10.0, 1e-9)
        fresh += 1
        if gain < tolerance * cost:
            break
    return x


def _expand(mask: np.ndarray, where: np.ndarray) -> np.ndarray:
    out = np.zeros(len(where), dtype=bool)
    out[where] = mask
    return out


def _identifiable(jac: np.ndarray, params: list[Parameter], position_only: bool) -> tuple[np.ndarray, dict]:
    """Which parameters to fit, and why the others are not identifiable.

    Columns are taken in the order of ``params`` (Gram-Schmidt, i.e. QR in that order): a column that
    adds less than ``RANK_TOLERANCE`` of its norm to the span of those already kept depends on them, so
    of two equivalent parameters the earlier, more meaningful one (a zero offset, say) is kept. The
    triangular factor gives each dependent column as a combination of the kept ones.
    """
    norms = np.linalg.norm(jac, axis=0)
    what = "positions" if position_only else "poses"
    reasons: dict[str, str] = {}
    # Gram-Schmidt needs only the columns' inner products, which the triangular factor of any QR keeps:
    # run it on that (n × n) instead of the (rows × n) Jacobian. Householder QR is fast and stable.
    if jac.shape[0] > jac.shape[1]:
        jac = qr(jac / np.where(norms > 0, norms, 1.0), mode="r", check_finite=False)[0][: jac.shape[1]] * norms
    basis = np.zeros((jac.shape[0], jac.shape[1]))
    rmat = np.zeros((jac.shape[1], jac.shape[1]))  # kept normalised columns = basis[:, :k] @ rmat[:k, :k]
    kept: list[int] = []
    for j, p in enumerate(params):
        if norms[j] <= RANK_TOLERANCE * norms.max():
            reasons[p.name] = f"does not change the measured {what}"
            continue
        k = len(kept)
        col = jac[:, j] / norms[j]
        proj = np.zeros(k)
        for _ in range(2):  # re-orthogonalise once: classical Gram-Schmidt loses orthogonality otherwise
            step = basis[:, :k].T @ col
            col = col - basis[:, :k] @ step
            proj += step
        size = np.linalg.norm(col)
        if size > RANK_TOLERANCE:
            basis[:, k] = col / size
            rmat[:k, k] = proj
            rmat[k, k] = size
            kept.append(j)
            continue
        coef = solve_triangular(rmat[:k, :k], proj) * norms[j] / norms[kept]  # in the scaled units of each
        top = np.argsort(-np.abs(coef))[:3]
        terms = ", ".join(f"{coef[i]:+.3g} × {params[kept[i]].name}" for i in top if abs(coef[i]) > 1e-3)
        reasons[p.name] = f"same effect as {terms}"
    active = np.zeros(len(params), dtype=bool)
    active[kept] = True
    return active, reasons
