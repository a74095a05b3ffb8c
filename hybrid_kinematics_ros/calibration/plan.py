"""Plan a measurement: which configurations to measure, in which order, and the accuracy they will give.

Measuring is what a calibration costs, so the poses are chosen for what the model can learn from them:

- **Information for the parametric stage.** The stage's problem linearised at the nominal model
  (:func:`calibration.parametric.linearise`) gives each candidate's Jacobian; the candidates are taken one at
  a time, each the one that raises the log-determinant of the information matrix most (greedy D-optimal
  design), with the Jacobian rows divided by the noise they will carry. Parameters the candidates cannot
  identify are left out. The stage planned for is the one every capacity includes (geometry, compliance,
  bending; no harmonics, no joint map): fewer poses then mean that ``train``'s capacity selection keeps the
  richer terms out.
- **Coverage of the working range for the nets.** Each candidate's distance, in joint space scaled by the
  working range, to the nearest pose already chosen. Both terms are divided by their largest value among the
  candidates at each step and added, the coverage term weighted by ``coverage_weight``.

The predicted accuracy comes from the same linearisation: the parameters' covariance for the stage's own
estimator (orientation rows weighed as the capacity selection will weigh them: the ratio of the two kinds'
noise or a factor about it, whichever leaves the least) propagated to the tip at configurations drawn from the
working range, plus what the stage cannot learn (``floor_mm``, ``floor_deg``; 0: nothing) and the test
measurement's own noise. The noise that identification sees is the tracker's plus the floor, in position and
in orientation. The floor is that of the stage the linearisation models, which has no joint error map and no
backlash: a previous calibration's held-out error with neither (``train --map-step 0 --no-approach``), less
the tracker's noise. Those two terms need dense data, and the selection takes them only from a hundred poses
or more; with the whole data set's floor, which has them, the prediction would fall well below the measured
error at the pose counts a plan is for.

The cyclic joint errors (gear harmonics) weigh most where poses are few: on the real UR10 a stage without them is
several times further off than with them. Their coefficients are many (80 a joint for 40 harmonics) and held
towards zero by the stage's ridge, so few poses learn them only in part. Given what a previous calibration of the
robot (or of one of its type) found (:class:`CyclicPrior`: how many harmonics, the coefficients' size for each
joint and order), the prediction counts what the ridge estimator leaves of them, ``A⁻¹ (Jᵀ Σ J + R T R) A⁻¹`` with
``A = JᵀJ + R``, the ridge ``R`` and the coefficients' prior variance ``T`` (a Bayesian linear model), for the
capacity the selection will choose from that many poses: of the harmonic counts and ridges
:mod:`calibration.capacity` offers, the one that leaves the least (fewer harmonics leave the others' prior whole).
Without a prior, the harmonics are left out and the prediction is a lower bound where poses are few.

The order is a short tour: nearest neighbour, then 2-opt, with the largest joint move as the distance (with
every joint at the same speed, that is the time a move takes).

What is checked about the tracker: the distance from the tracker to the target, the target's acceptance cone
about its axis (the tip frame's z), a box for the target's position. Not checked: self-occlusion by the
robot's links, and the cell's other objects, for want of collision geometry.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from hybrid_kinematics_ros.calibration.capacity import HARMONIC_PRIORS, HARMONICS, WEIGHT_FACTORS
from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.calibration.parametric import linearise
from hybrid_kinematics_ros.kinematics import se3
from hybrid_kinematics_ros.kinematics.chain import Chain
from hybrid_kinematics_ros.kinematics.fk import fk

PREDICTION_CAVEAT = (
    "what the parameters' covariance gives if what the stage cannot learn behaves as noise, without the cyclic "
    "joint errors (no --prior-model): a lower bound below a few hundred poses (BENCHMARKS.md, Planning the "
    "measurement, shows how far below on the real UR10)"
)
PREDICTION_WITH_PRIOR = (
    "what the parameters' covariance gives if what the stage cannot learn behaves as noise, with the cyclic joint "
    "errors the prior model found, each joint's and order's size; the stage without a joint error map or "
    "backlash, which dense data add (BENCHMARKS.md, Planning the measurement, shows how far it fell from the "
    "measured error on the real UR10 and on a virtual one)"
)
# mean over RMS of the norm of an isotropic 3-D Gaussian error (chi distribution with 3 degrees of freedom)
MEAN_OVER_RMS = float(np.sqrt(8.0 / (3.0 * np.pi)))
MAX_INFORMATION_CANDIDATES = 4000  # candidates linearised at once: a few thousand cover a working range
LIMIT_SLACK = 1e-9  # rad (or m): a pool row this far beyond a joint limit counts as on it (rounding in a CSV)
EVALUATION_POSES = 500  # where the predicted accuracy is averaged
CURVE = (50, 100, 200, 300, 500, 750, 1000, 1500, 2000)


@dataclass(frozen=True)
class TrackerView:
    """What the tracker can see. ``position``: the tracker in the base frame (m; None: unknown, so neither
    the distance nor the cone is checked). ``cone_deg``: the target's acceptance half-angle about the tip
    frame's z axis (about 45° for a 6-DoF probe, 30° for a plain reflector). ``box``: ``(2, 3)`` the lower
    and upper corner of the region the target must lie in (m, base frame)."""

    position: np.ndarray | None = None
    cone_deg: float | None = None
    min_distance: float = 0.0
    max_distance: float = float("inf")
    box: np.ndarray | None = None

    def checks(self) -> dict[str, list[str]]:
        checked = []
        if self.box is not None:
            checked.append("target inside the box")
        if self.position is not None:
            checked.append(f"tracker distance {self.min_distance:g}-{self.max_distance:g} m")
            if self.cone_deg is not None:
                checked.append(f"target's acceptance cone ±{self.cone_deg:g}° about the tip's z axis")
        not_checked = ["self-occlusion by the robot's links (no collision geometry)", "other objects in the cell"]
        if self.position is None:
            not_checked.insert(0, "line of sight, distance and acceptance cone (no --tracker-xyz)")
        return {"checked": checked, "not_checked": not_checked}

    def kept(self, frames: np.ndarray, target: np.ndarray | None) -> dict[str, np.ndarray]:
        """Each check's mask over the target frames ``(N, 4, 4)``, in the order they are applied."""
        point = se3.point_at(frames, target)
        out: dict[str, np.ndarray] = {}
        if self.box is not None:
            out["box"] = np.all((point >= self.box[0]) & (point <= self.box[1]), axis=1)
        if self.position is not None:
            ray = self.position - point
            distance = np.linalg.norm(ray, axis=1)
            out["distance"] = (distance >= self.min_distance) & (distance <= self.max_distance)
            if self.cone_deg is not None:
                cosine = np.einsum("ni,ni->n", frames[:, :3, 2], ray) / np.maximum(distance, 1e-12)
                out["cone"] = cosine >= np.cos(np.radians(self.cone_deg))
        return out


@dataclass(frozen=True)
class CyclicPrior:
    """The cyclic joint errors of the robot, as a previous calibration found them: ``harmonics`` of each joint's
    angle, their coefficients' root mean square ``rms_rad``, and ``joint_order_rms_rad`` the root mean square of
    each joint's pair (sine, cosine) at each order ``(n, harmonics)``, the prior's standard deviation of those
    coefficients (None: ``rms_rad`` for every one).

    Per joint and order, because the robot's cyclic errors are not alike: a wrist's gears err more than a
    shoulder's and move the tip less, and the spectrum falls with the order. One pooled size puts a wrist's
    amplitude on the shoulder, where a joint error moves the tip most, and the high orders' smallness on the low
    ones."""

    harmonics: int
    rms_rad: float
    joint_order_rms_rad: tuple[tuple[float, ...], ...] | None = None

    @classmethod
    def from_manifest(cls, manifest: dict[str, Any], where: str = "model.json") -> CyclicPrior:
        """From a trained model's ``model.json``: its stage's harmonic coefficients (a pair that could not be
        identified takes its joint's size, else the overall one)."""
        try:
            params = manifest["parametric"]["parameters"]
            cyclic = [p for p in params if p["kind"] == "harmonic" and p["identifiable"]]
            values = np.array([p["value"] for p in cyclic], dtype=float)
            joints = np.array([int(p["index"]) for p in cyclic], dtype=int)
            orders = np.array([int(p["component"]) // 2 + 1 for p in cyclic], dtype=int)
            n = len({int(p["index"]) for p in params if p["kind"] == "zero"})  # the chain's joints
        except (KeyError, TypeError, ValueError) as exc:
            raise CalibrationError(f"{where}: no parametric stage to take the cyclic errors from ({exc!r})") from None
        if not cyclic:
            raise CalibrationError(f"{where}: its parametric stage has no cyclic joint errors (harmonics 0)")
        harmonics, overall = int(orders.max()), float(np.sqrt(np.mean(values**2)))
        table = np.full((max(n, int(joints.max()) + 1), harmonics), overall)
        for j in np.unique(joints):
            mine = joints == j
            table[j] = np.sqrt(np.mean(values[mine] ** 2))
            for k in np.unique(orders[mine]):
                table[j, k - 1] = np.sqrt(np.mean(values[mine & (orders == k)] ** 2))
        return cls(harmonics, overall, tuple(tuple(float(v) for v in row) for row in table))

    def rms_of(self, joint: np.ndarray, order: np.ndarray) -> np.ndarray:
        """The prior's standard deviation (rad) of the coefficients of ``joint`` at ``order`` (1 …)."""
        out = np.full(np.shape(joint), self.rms_rad)
        if self.joint_order_rms_rad is not None:  # a joint the previous calibration did not have: the overall size
            table = np.asarray(self.joint_order_rms_rad)
            known = (joint < len(table)) & (order <= table.shape[1])
            out[known] = table[joint[known], order[known] - 1]
        return out


@dataclass(frozen=True)
class PlanOptions:
    count: int
    target: np.ndarray | None = None  # (3,) m in the tip frame: a plain reflector there (position only)
    position_noise_m: float = 15e-6  # the tracker's, per axis
    orientation_noise_rad: float = np.radians(0.001)
    floor_mm: float = 0.0  # what the stage cannot learn, as a mean position error
    floor_deg: float = 0.0  # and as a mean orientation error (6-DoF measurements)
    coverage_weight: float = 3.0  # against the information term, both scaled to 1 among the candidates
    criterion: str = "i-optimal"  # or "d-optimal" (see _greedy)
    seconds_per_pose: float = 5.0  # settling and measuring
    joint_speed: float = 0.5  # rad/s, every joint
    curve: bool = False
    seed: int = 0
    payload_mass: float = 0.0  # kg, and its centre of mass in the tip frame (m): the joints' torques need them
    payload_com: np.ndarray | None = None
    gravity: np.ndarray | None = None  # m/s², base frame (None: a floor mount)
    cyclic: CyclicPrior | None = None  # the cyclic joint errors to predict with (None: left out)


@dataclass
class Plan:
    """``rows``: the chosen candidates' indices in tour order; ``predicted``: at the chosen count."""

    rows: np.ndarray
    q: np.ndarray
    seconds: float
    predicted: dict[str, float]
    parameters: int  # identifiable, of the stage planned for
    candidates: dict[str, int]
    checks: dict[str, list[str]]
    curve: list[dict[str, float]] = field(default_factory=list)
    cyclic: CyclicPrior | None = None  # what the prediction took the cyclic errors from

    @property
    def caveat(self) -> str:
        return PREDICTION_CAVEAT if self.cyclic is None else PREDICTION_WITH_PRIOR

    def summary(self) -> dict[str, Any]:
        return {
            "poses": len(self.rows),
            "measuring_time_h": round(self.seconds / 3600.0, 2),
            "predicted": {**self.predicted, "note": self.caveat},
            **({"cyclic_prior": asdict(self.cyclic)} if self.cyclic is not None else {}),
            "identifiable_parameters": self.parameters,
            "candidates": self.candidates,
            "tracker": self.checks,
            **({"curve": self.curve} if self.curve else {}),
        }


def draw_configurations(lower: np.ndarray, upper: np.ndarray, count: int, seed: int = 0) -> np.ndarray:
    """``count`` configurations uniform in the box ``lower``-``upper`` (rad or m)."""
    lower, upper = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)
    if not (np.all(np.isfinite(lower)) and np.all(np.isfinite(upper))):
        raise CalibrationError("the working range needs finite joint ranges: give --joint-range for unlimited joints")
    return np.random.default_rng(seed).uniform(lower, upper, (count, len(lower)))


def visible(chain: Chain, q: np.ndarray, view: TrackerView, target: np.ndarray | None) -> tuple[np.ndarray, dict]:
    """The mask of configurations within the joint limits that the tracker can measure, and how many each
    check kept in turn."""
    # a pool's rows beyond the joint limits (another robot's data set, a typo) would send the robot there
    kept = np.all((q >= chain.lower - LIMIT_SLACK) & (q <= chain.upper + LIMIT_SLACK), axis=1)
    counts = {"given": len(q), "within the joint limits": int(kept.sum())}
    for name, mask in view.kept(fk(chain, q), target).items():
        kept &= mask
        counts[f"after {name}"] = int(kept.sum())
    return kept, counts


@dataclass(frozen=True)
class _Problem:
    """The stage's problem at the candidates, in scaled units: ``jacobian (N, w, P)`` (m, or rad × ``weight`` for
    orientation rows) on the identifiable parameters and the cyclic coefficients, the noise each row will carry
    ``sigma (w,)``, and per column its harmonic order ``order (P,)`` (0: not cyclic), its SI value per scaled
    unit ``scale (P,)`` and the prior variance of a cyclic coefficient ``prior (P,)``. ``design (P,)``: the
    columns the design maximises the information on (the stage every capacity includes). ``weight``: the
    orientation rows' weight (m per rad) the problem is at, the ratio of the two kinds' noise (0: position
    only)."""

    jacobian: np.ndarray
    sigma: np.ndarray
    order: np.ndarray
    scale: np.ndarray
    prior: np.ndarray
    weight: float = 0.0

    @property
    def design(self) -> np.ndarray:
        return self.order == 0


def _information(chain: Chain, q: np.ndarray, options: PlanOptions) -> _Problem:
    """The stage's problem at candidates ``q``; its noise is the tracker's and, as if it were noise, what the
    stage cannot learn."""
    frames = fk(chain, q)
    position_only = options.target is not None
    measured = frames.copy()
    measured[:, :3, 3] = se3.point_at(frames, options.target)
    cyclic = options.cyclic
    lin = linearise(
        chain,
        q,
        measured,
        position_only=position_only,
        target=options.target,
        max_pairs=len(q),
        harmonics=0 if cyclic is None else cyclic.harmonics,
        map_step=0.0,
        payload_mass=options.payload_mass,
        payload_com=options.payload_com,
        gravity=options.gravity,
    )
    rows = np.argsort(lin.pick)  # the linearisation's rows back in the candidates' order
    order = np.array([p.component // 2 + 1 if p.kind == "harmonic" else 0 for p in lin.params])
    columns = lin.identifiable | (order > 0)  # the ridge holds every cyclic coefficient
    size = np.zeros(len(order))
    if cyclic is not None:
        size[order > 0] = cyclic.rms_of(np.array([p.index for p in lin.params])[order > 0], order[order > 0])
    prior = (size / lin.scale) ** 2
    per_axis = MEAN_OVER_RMS * np.sqrt(3.0)  # a mean error norm over the per-axis standard deviation
    sigma = np.full(lin.jacobian.shape[1], np.hypot(options.position_noise_m, 1e-3 * options.floor_mm / per_axis))
    weight = 0.0
    if not position_only:
        # the stage weighs orientation rows starting from the ratio of the two kinds' errors
        # (calibration.capacity, item 5): with these noises, every row's noise is then the same
        weight = float(sigma[0] / np.hypot(options.orientation_noise_rad, np.radians(options.floor_deg) / per_axis))
        lin = lin.reweighted(weight)
        sigma[3:] = sigma[0]
    return _Problem(
        lin.jacobian[rows][:, :, columns], sigma, order[columns], lin.scale[columns], prior[columns], weight
    )


def _normal(jac: np.ndarray, sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``Σ JᵀJ`` and ``Σ Jᵀ diag(σ²) J`` over the poses' Jacobians ``(k, w, P)`` (one product each)."""
    flat = jac.reshape(-1, jac.shape[2])
    weighted = (jac * sigma[None, :, None] ** 2).reshape(flat.shape)
    return flat.T @ flat, weighted.T @ flat


def _weighted_normals(problem: _Problem, rows: np.ndarray):
    """:func:`_normal` of the poses ``rows`` at each orientation weight the capacity selection tries (the data's
    ratio, then :data:`~calibration.capacity.WEIGHT_FACTORS` times it): ``(weight, a, b)``. Scaling the
    orientation rows by ``f`` scales their ``JᵀJ`` by ``f²`` and, their noise scaled alike, ``Jᵀ diag(σ²) J``
    by ``f⁴``."""
    jac = problem.jacobian[rows]
    if problem.weight == 0.0:
        return [(0.0, *_normal(jac, problem.sigma))]
    a_pos, b_pos = _normal(jac[:, :3], problem.sigma[:3])
    a_ori, b_ori = _normal(jac[:, 3:], problem.sigma[3:])
    return [(problem.weight * f, a_pos + f**2 * a_ori, b_pos + f**4 * b_ori) for f in (1.0, *WEIGHT_FACTORS)]


def _error_variance(
    a: np.ndarray,
    b: np.ndarray,
    metric: np.ndarray,
    kept: np.ndarray | None = None,
    ridge: np.ndarray | None = None,
    prior: np.ndarray | None = None,
) -> float:
    """The mean squared error ``tr(metric · C)`` that the stage's own estimator leaves, ``C`` the covariance of
    every parameter's error (scaled units), from the normal matrices ``a = Σ JᵀJ`` and ``b = Σ Jᵀ diag(σ²) J``
    (:func:`_normal`): least squares on the columns ``kept`` (default: all) with every row weighted alike
    (position in m, orientation in rad × the stage's weight), whatever noise each carries, and a ``ridge`` on the
    cyclic coefficients, whose values are drawn from their prior variance ``prior`` (scaled units).

    The kept columns' error is ``A⁻¹ (Jᵀε - R θ_K + a_KE θ_E)`` with ``A = a_KK + R``: the noise, the ridge's
    bias, and the share of the left-out columns' values ``θ_E`` that the kept ones absorb; a left-out column
    errs by its whole value. Absorbing is not free: at few poses the kept columns take up what they cannot
    tell from the left-out ones as if it were signal."""
    p = a.shape[0]
    kept = np.ones(p, dtype=bool) if kept is None else kept
    out = ~kept
    ridge = np.zeros(int(kept.sum())) if ridge is None else ridge
    prior = np.zeros(p) if prior is None else prior
    inside = np.ix_(kept, kept)
    a_inv = np.linalg.pinv(a[inside] + np.diag(ridge), rcond=1e-12, hermitian=True)
    absorbed = a[np.ix_(kept, out)] * prior[out]  # a_KE T_E
    inner = b[inside] + np.diag(ridge**2 * prior[kept]) + absorbed @ a[np.ix_(out, kept)]
    cross = -a_inv @ absorbed  # the kept columns' errors against the left-out ones'
    return float(
        np.sum((a_inv @ inner @ a_inv) * metric[inside])
        + 2.0 * np.sum(cross * metric[np.ix_(kept, out)])
        + np.sum(np.diag(metric)[out] * prior[out])
    )


def _stage_variance(problem: _Problem, rows: np.ndarray, metric: np.ndarray) -> tuple[float, dict[str, float]]:
    """The mean squared position error (m², over the evaluation poses, ``metric``: the mean of their position
    rows' ``JᵀJ``) that the parameters leave after the poses ``rows``, for the capacity the selection will
    choose, taken as the one of those it offers that leaves the least position error. The selection itself
    judges on held-out blocks, orientation included, and keeps the simpler candidate unless another is better
    beyond the noise: the prediction takes the optimist's choice. Offered:

    - the orientation rows' weight (with 6-DoF measurements): the ratio of the two kinds' noise, and the
      factors about it that the selection tries. The ratio is the best weight for least squares alone, not
      with a ridge on the cyclic coefficients, whose strength the weight changes. On the virtual UR10 of
      ``bench_plan`` the selection chooses a few times the ratio, and the prediction at that weight comes far
      nearer the stage's error than the prediction at the ratio (BENCHMARKS.md);
    - with a prior on the cyclic errors, the harmonics and their ridge, as :mod:`calibration.capacity` offers
      them. The harmonics a candidate leaves out are errors of their prior's size, which the kept columns
      absorb in part.

    Without a prior, the stage every capacity includes."""
    cyclic = problem.order > 0
    top = int(problem.order.max()) if cyclic.any() else 0
    best: tuple[float, dict[str, float]] = (np.inf, {})
    for weight, a, b in _weighted_normals(problem, rows):
        chosen = {"orientation_length": float(f"{weight:.3g}")} if weight else {}  # as the selection rounds it
        if not cyclic.any():
            variance = _error_variance(a, b, metric)
            best = min(best, (variance, chosen), key=lambda c: c[0])
            continue
        for harmonics in sorted({h for h in HARMONICS if h < top} | {top}):
            kept = ~cyclic | (problem.order <= harmonics)
            for ridge_pairs in HARMONIC_PRIORS if harmonics else (0.0,):
                ridge = np.where(cyclic[kept], ridge_pairs * problem.scale[kept] ** 2, 0.0)
                variance = _error_variance(a, b, metric, kept, ridge, problem.prior)
                if variance < best[0]:
                    best = (variance, {"harmonics": harmonics, "harmonic_prior": ridge_pairs, **chosen})
    return best


def _greedy(
    info: np.ndarray,
    spread: np.ndarray,
    count: int,
    coverage_weight: float,
    metric: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Greedy optimal design with a coverage term: the order of choice and the design's inverse information
    matrix ``A`` after the last pick (scaled units).

    ``metric`` None: D-optimal, each step's gain ``log det(I + G_c A G_cᵀ)``. Else I-optimal: the fall of the
    mean prediction variance ``tr(metric A)``, which adding candidate ``c`` lowers by ``tr(S_c⁻¹ G_c A metric A
    G_cᵀ)`` with ``S_c = I + G_c A G_cᵀ``. The forms ``G_c A G_cᵀ`` of every candidate follow rank-``w``
    (Woodbury) updates, so a step costs a product or two with the candidates' Jacobians."""
    n, w, p = info.shape
    full = np.einsum("nwp,nwq->pq", info, info)
    ridge = 1e-9 * np.trace(full) / p  # an almost flat start, so the first steps are defined
    cov = np.eye(p) / ridge
    quad = np.einsum("nwp,nvp->nwv", info, info) / ridge
    nearest = np.full(n, np.inf)
    taken = np.zeros(n, dtype=bool)
    order = np.empty(count, dtype=int)
    eye = np.eye(w)
    for k in range(count):
        if metric is None:
            gain = np.linalg.slogdet(eye + quad)[1]
        else:
            through = info @ (cov @ metric @ cov)  # (n, w, p)
            fall = through @ np.swapaxes(info, 1, 2)  # (n, w, w): G_c A M A G_cᵀ
            gain = np.einsum("nii->n", np.linalg.solve(eye + quad, fall))
        score = gain / max(np.max(gain[~taken]), 1e-300)
        if k and coverage_weight > 0:
            score = score + coverage_weight * nearest / max(np.max(nearest[~taken]), 1e-300)
        score[taken] = -np.inf
        s = int(np.argmax(score))
        order[k] = s
        taken[s] = True
        v = cov @ info[s].T  # (p, w)
        inner = np.linalg.inv(eye + info[s] @ v)
        cross = info @ v  # (n, w, w): G_c A G_sᵀ
        quad -= cross @ inner @ np.swapaxes(cross, 1, 2)
        cov -= v @ inner @ v.T
        cov = 0.5 * (cov + cov.T)
        nearest = np.minimum(nearest, np.linalg.norm(spread - spread[s], axis=1))
    return order, cov


def _predicted(problem: _Problem, rows: np.ndarray, metric: np.ndarray, options: PlanOptions) -> dict[str, Any]:
    """Mean position error (mm) the stage will show on test measurements like these, and its parts."""
    variance, capacity = _stage_variance(problem, rows, metric)
    parameters_rms = float(np.sqrt(variance))  # m
    floor_rms = 1e-3 * options.floor_mm / MEAN_OVER_RMS
    measured_rms = np.sqrt(parameters_rms**2 + floor_rms**2 + 3.0 * options.position_noise_m**2)
    return {
        "position_mean_mm": round(1e3 * MEAN_OVER_RMS * measured_rms, 4),
        "parameters_part_mm": round(1e3 * MEAN_OVER_RMS * parameters_rms, 4),
        "floor_mm": options.floor_mm,
        "tracker_noise_mm": round(1e3 * MEAN_OVER_RMS * np.sqrt(3.0) * options.position_noise_m, 4),
        **({"capacity": capacity} if capacity else {}),
    }


def tour(q: np.ndarray, start: int = 0) -> np.ndarray:
    """An open tour through every row of ``q`` from row ``start``: nearest neighbour, then 2-opt, with the
    largest joint move as the distance."""
    n = len(q)
    if n <= 2:
        return np.r_[start, np.delete(np.arange(n), start)] if n else np.arange(0)
    dist = np.max(np.abs(q[:, None, :] - q[None, :, :]), axis=2)
    order = [start]
    free = np.ones(n, dtype=bool)
    free[start] = False
    for _ in range(n - 1):
        row = np.where(free, dist[order[-1]], np.inf)
        order.append(int(np.argmin(row)))
        free[order[-1]] = False
    path = np.array(order)
    for _ in range(100):  # 2-opt passes: reverse path[i:j+1] when that shortens the tour
        improved = False
        for i in range(1, n - 1):
            j = np.arange(i + 1, n)
            before = dist[path[i - 1], path[i]] + np.where(j < n - 1, dist[path[j], path[np.minimum(j + 1, n - 1)]], 0)
            after = dist[path[i - 1], path[j]] + np.where(j < n - 1, dist[path[i], path[np.minimum(j + 1, n - 1)]], 0)
            best = int(np.argmin(after - before))
            if after[best] - before[best] < -1e-12:
                path[i : j[best] + 1] = path[i : j[best] + 1][::-1].copy()
                improved = True
        if not improved:
            break
    return path


def travel_seconds(q: np.ndarray, options: PlanOptions) -> np.ndarray:
    """Cumulative time at which each pose of the tour is measured (moves at ``joint_speed``, then a dwell)."""
    moves = np.r_[0.0, np.max(np.abs(np.diff(q, axis=0)), axis=1)] / options.joint_speed
    return np.cumsum(moves + options.seconds_per_pose)


def plan(
    chain: Chain,
    candidates: np.ndarray,
    options: PlanOptions,
    view: TrackerView | None = None,
    spread_lower: np.ndarray | None = None,
    spread_upper: np.ndarray | None = None,
) -> Plan:
    """Choose ``options.count`` of ``candidates (N, n)`` and order them; the rows refer to ``candidates``.

    ``spread_lower``/``spread_upper``: the working range that scales joint distances (default: the
    candidates' own)."""
    view = view or TrackerView()
    candidates = np.asarray(candidates, dtype=float)
    rng = np.random.default_rng(options.seed)
    pool, counts = _pool(chain, candidates, options, view, rng)
    q = candidates[pool]
    problem = _information(chain, q, options)
    jac, sigma = problem.jacobian, problem.sigma
    info, position_rows = jac[:, :, problem.design] / sigma[None, :, None], jac[:, :3]
    lower = q.min(axis=0) if spread_lower is None else np.asarray(spread_lower, dtype=float)
    upper = q.max(axis=0) if spread_upper is None else np.asarray(spread_upper, dtype=float)
    spread = (q - lower) / np.maximum(upper - lower, 1e-9)
    stops = tuple(c for c in CURVE if c <= len(pool)) if options.curve else ()
    last = max((options.count, *stops))
    evaluate = rng.choice(len(pool), min(EVALUATION_POSES, len(pool)), replace=False)
    at_eval = position_rows[evaluate]
    flat_eval = at_eval.reshape(-1, at_eval.shape[2])
    everywhere = flat_eval.T @ flat_eval / len(at_eval)  # the mean prediction variance is tr(C · everywhere)
    metric = None
    if options.criterion == "i-optimal":
        metric = everywhere[np.ix_(problem.design, problem.design)]
    elif options.criterion != "d-optimal":
        raise CalibrationError(f"criterion {options.criterion!r}: choose i-optimal or d-optimal")
    order, _ = _greedy(info, spread, last, options.coverage_weight, metric)
    chosen = order[: options.count]
    path, times = _toured(q, spread, chosen, options)
    curve = [
        {
            "poses": c,
            **_predicted(problem, order[:c], everywhere, options),
            # each count's own tour: denser poses are closer together, so a time per pose would overstate it
            "measuring_time_h": round(float(_toured(q, spread, order[:c], options)[1][-1]) / 3600, 2),
        }
        for c in stops
    ]
    return Plan(
        rows=pool[path],
        q=candidates[pool[path]],
        seconds=float(times[-1]),
        predicted=_predicted(problem, chosen, everywhere, options),
        parameters=int(info.shape[2]),
        candidates=counts,
        checks=view.checks(),
        curve=curve,
        cyclic=options.cyclic,
    )


def _pool(
    chain: Chain, candidates: np.ndarray, options: PlanOptions, view: TrackerView, rng: np.random.Generator
) -> tuple[np.ndarray, dict[str, int]]:
    """The rows of ``candidates`` the design considers (those the tracker can see, at most
    MAX_INFORMATION_CANDIDATES of them at random), and how many each check kept; or a :class:`CalibrationError`
    when fewer than ``options.count`` are usable."""
    kept, counts = visible(chain, candidates, view, options.target)
    usable = np.flatnonzero(kept)
    if options.count < 1:
        raise CalibrationError(f"--count {options.count}: plan at least one pose")
    if len(usable) < options.count:
        steps = ", ".join(f"{k} {v}" for k, v in counts.items())
        raise CalibrationError(
            f"--count {options.count}: only {len(usable)} usable candidate configurations ({steps}); "
            "widen the working range or the tracker's limits, or ask for fewer poses"
        )
    pool = usable
    if len(pool) > MAX_INFORMATION_CANDIDATES and options.count < MAX_INFORMATION_CANDIDATES:
        pool = np.sort(rng.choice(usable, MAX_INFORMATION_CANDIDATES, replace=False))
    counts["considered"] = len(pool)
    return pool, counts


def _toured(
    q: np.ndarray, spread: np.ndarray, chosen: np.ndarray, options: PlanOptions
) -> tuple[np.ndarray, np.ndarray]:
    """The rows ``chosen`` of ``q`` in tour order, from the one nearest the range's middle, and when each is
    measured (:func:`travel_seconds`)."""
    middle = int(np.argmin(np.linalg.norm(spread[chosen] - 0.5, axis=1)))
    path = chosen[tour(q[chosen], middle)]
    return path, travel_seconds(q[path], options)


def trajectory_message(joint_names: tuple[str, ...], q: np.ndarray, seconds: np.ndarray) -> dict[str, Any]:
    """A ``trajectory_msgs/JointTrajectory`` as a YAML-ready mapping: one point per pose to stop at, its
    ``time_from_start`` when the pose is measured (after the move and the dwell)."""
    points = []
    for row, t in zip(q, seconds, strict=True):
        sec, nanosec = divmod(round(float(t) * 1e9), 1_000_000_000)
        points.append(
            {
                "positions": [float(v) for v in row],
                "velocities": [0.0] * len(row),
                "time_from_start": {"sec": sec, "nanosec": nanosec},
            }
        )
    return {"header": {"frame_id": ""}, "joint_names": list(joint_names), "points": points}
