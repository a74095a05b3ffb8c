"""Verify a calibration with a tracker placed anywhere: is the model still calibrated, or has the robot drifted,
and does it meet the tolerance?

A check is a recording of some poses, often from a new tracker station after a crash, a gear change or months
of wear. A station the model does not know is referenced from the check itself, through the model (so what is
judged is the model), and cross-fitted: each fifth of the poses is judged with the tracker placed from the
other four, so every pose is judged and none placed its own station. The target stays where the model has it,
so a tool that moved is seen; when the target was re-mounted on purpose, ``refit_target`` places it from the
check too, and a tool that moved is then a target placed elsewhere. Each
judged pose is compared with the model's own 95 % bound at its configuration. Five poses in a hundred may lie
beyond it by design, and the bound's coverage is itself known only from the validation pairs that set it, so
"drifted" needs more poses beyond it than those pairs had, with significance (a one-sided Fisher exact
test): a few unlucky poses do not fail a good model. The tolerance verdict is the report's.

When the robot drifted, a least-squares fit of the residual to each group of the geometry's parameters (a
joint's zero offset, a joint origin, the tool, the tracker's placement) says which explains it best.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy import stats

from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.calibration.evaluate import target_errors
from hybrid_kinematics_ros.calibration.parametric import orientation_length
from hybrid_kinematics_ros.calibration.referencing import reference_stations
from hybrid_kinematics_ros.calibration.summary import verdict
from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.kinematics import fk, se3
from hybrid_kinematics_ros.kinematics.chain import Chain
from hybrid_kinematics_ros.model.bounds import Bounds
from hybrid_kinematics_ros.model.hybrid import HybridModel
from hybrid_kinematics_ros.model.referencing import Referencing

FOLDS = 5  # an unknown station is cross-fitted: placed from four fifths, the other fifth judged, in turn
MIN_REFERENCE_POSES = 10  # the least squares that place a station with its target need this many
DRIFT_P_VALUE = 0.01  # "drifted" when the share of poses over their bound is this unlikely for a good model
STEP = 1e-6  # m or rad: the finite difference of the diagnosis's columns


@dataclass(frozen=True)
class Tolerance:
    """What the check must meet, as ``report --tolerance-mm/--tolerance-deg`` (None: no PASS/FAIL)."""

    position_mm: float | None = None
    orientation_deg: float | None = None


@dataclass(frozen=True)
class Verification:
    """A check's outcome: the judged poses' errors (mm, deg), how each station was placed, the bound test,
    the tolerance verdict and, for a drift, what explains it."""

    position_mm: np.ndarray
    orientation_deg: np.ndarray
    stations: dict[str, str]
    over_bound: int | None  # judged poses beyond the model's position or orientation bound, the larger count
    # (None: the model carries no bounds)
    level: float
    p_value: float
    tolerance: dict[str, Any] | None
    diagnosis: list[dict[str, Any]] = field(default_factory=list)

    @property
    def drifted(self) -> bool:
        return self.over_bound is not None and self.p_value < DRIFT_P_VALUE

    @property
    def holds(self) -> bool:
        """Still calibrated and, when a tolerance was given, within it: the exit code's 0."""
        return not self.drifted and (self.tolerance is None or self.tolerance["passed"])

    def lines(self) -> list[str]:
        """What ``verify`` prints: the two verdicts and the diagnosis."""
        n = len(self.position_mm)
        out = [f"{n} poses judged, mean {np.mean(self.position_mm):.4f} mm"]
        if self.over_bound is None:
            out.append("no bound test: the model carries no error bounds (retrain it)")
        else:
            state = "DRIFTED" if self.drifted else "STILL CALIBRATED"
            out.append(
                f"{state}: {self.over_bound} of {n} poses beyond the model's {self.level:.0%} bound "
                "(position or orientation, the more), "
                f"{1 - self.level:.0%} allowed (p = {self.p_value:.2g})"
            )
        if self.tolerance is not None:
            out.append(self.tolerance["line"])
        out += [f"explains {d['explained']:.0%} of the residual: {d['what']}" for d in self.diagnosis]
        return out

    def manifest(self) -> dict[str, Any]:
        return {
            "poses": len(self.position_mm),
            "position_mm_mean": float(np.mean(self.position_mm)),
            "orientation_deg_mean": None
            if np.all(np.isnan(self.orientation_deg))
            else float(np.nanmean(self.orientation_deg)),
            "stations": self.stations,
            "bound_level": self.level,
            "over_bound": self.over_bound,
            "p_value": self.p_value,
            "drifted": self.drifted,
            "tolerance": self.tolerance,
            "passed": None if self.tolerance is None else self.tolerance["passed"],
            "holds": self.holds,
            "causes": self.diagnosis,  # most likely first
        }


def verify(
    model: HybridModel, stations: Sequence[Pairs], tolerance: Tolerance = Tolerance(), refit_target: bool = False
) -> Verification:
    """Judge ``model`` on the check pairs ``stations`` (one :class:`Pairs` per frame). ``refit_target``: at a
    station the model does not know, place the target from the check too (it was re-mounted)."""
    judged, how = [], {}
    for pairs in stations:
        base, how[pairs.frame_id] = _in_base_frame(model, pairs, refit_target)
        judged.append(base)
    pairs = Pairs.concatenate(judged)
    tip = _tips(model, pairs)
    pos_mm, rot_deg = target_errors(pairs, tip)
    over, level, p_value = _bound_test(model, pairs, pos_mm, rot_deg)
    checked = None
    if tolerance.position_mm is not None:
        checked = verdict(pos_mm, rot_deg, tolerance.position_mm, tolerance.orientation_deg)
    result = Verification(pos_mm, rot_deg, how, over, level, p_value, checked)
    if result.drifted:
        result = replace(result, diagnosis=diagnose(model.chain, pairs, tip))
    return result


def _in_base_frame(model: HybridModel, pairs: Pairs, refit_target: bool) -> tuple[Pairs, str]:
    """The check pairs of one station in the base frame, and how the station was found: the model's own
    referencing for a station it knows; else cross-fitted, each of ``FOLDS`` interleaved parts placed from the
    others (with the target, when ``refit_target``), so that no judged pose placed its own station."""
    base_link = model.chain.base_link
    if pairs.frame_id == base_link:
        return pairs, "the base frame"
    if pairs.frame_id in model.referencings:
        return model.referencings[pairs.frame_id].to_base(pairs, base_link), "the model's referencing"
    if len(pairs) < 2 * MIN_REFERENCE_POSES:
        raise CalibrationError(
            f"frame '{pairs.frame_id}': {len(pairs)} check poses; a station the model does not know needs at "
            f"least {2 * MIN_REFERENCE_POSES} (each part is judged with the station placed from the others)"
        )
    fold = np.arange(len(pairs)) % FOLDS
    tips = _tips(model, pairs)
    parts, targets = [], set()
    for k in range(FOLDS):
        rows = np.flatnonzero(fold != k)
        place = pairs.subset(rows)
        if refit_target:
            ref, target = place_station(model, place, tips[rows])
        else:
            ref, target = _placed_with_target(model, place, tips[rows]), "the target at the model's"
        parts.append(ref.to_base(pairs.subset(np.flatnonzero(fold == k)), base_link))
        targets.add(target)
    where = " or ".join(sorted(targets))
    return Pairs.concatenate(parts), f"placed from the other {FOLDS - 1} fifths for each fifth judged, {where}"


def place_station(model: HybridModel, pairs: Pairs, tips: np.ndarray | None = None) -> tuple[Referencing, str]:
    """A station the model does not know, placed through the model from ``pairs`` (``tips``: the model's poses
    at their joints, when the caller has them): with a 6-D probe the target too, unless the poses leave it
    undetermined; else at the model's target. Also says where the target is."""
    tips = _tips(model, pairs) if tips is None else tips
    if not pairs.position_only:  # the probe's orientation places the target too
        (ref,) = reference_stations(model.chain, [pairs], [tips])
        if not ref.undetermined:
            return ref, "the target with it"
    return _placed_with_target(model, pairs, tips), "the target at the model's"


def _tips(model: HybridModel, pairs: Pairs) -> np.ndarray:
    return model.fk(pairs.q, conditions=model.conditions_of(pairs.conditions, len(pairs)))


def _placed_with_target(model: HybridModel, place: Pairs, tips: np.ndarray) -> Referencing:
    """The tracker placed by the measured targets against the model's, the target where the model has it: by
    their points, and with a 6-D probe also by points one orientation length along each of their axes, so
    that position and orientation weigh as in the stage's fit."""
    target = np.eye(4) if model.referencing is None else model.referencing.flange_to_target
    predicted, measured = tips @ target, place.T
    if place.position_only:
        base, _ = se3.fit_rigid(measured[:, :3, 3], predicted[None, :, :3, 3])
    else:
        base, _ = se3.fit_rigid(_frame_points(measured, model), _frame_points(predicted, model)[None])
    return Referencing(place.frame_id, base[0], target, place.position_only, method="placed by the check")


def _frame_points(T: np.ndarray, model: HybridModel) -> np.ndarray:
    """``(4N, 3)``: each frame's origin and the points one orientation length along its axes."""
    length = orientation_length(model.manifest)
    origin = T[:, None, :3, 3]
    return np.concatenate([origin, origin + length * np.swapaxes(T[:, :3, :3], 1, 2)], axis=1).reshape(-1, 3)


def _bound_test(
    model: HybridModel, pairs: Pairs, pos_mm: np.ndarray, rot_deg: np.ndarray
) -> tuple[int | None, float, float]:
    """Poses beyond the model's position bound (or, when more, its orientation bound), the bounds' level, and
    the binomial p-value of at least that many, each kind tested on its own (Bonferroni over the two)."""
    bounds = model.error_bounds(pairs.q, model.conditions_of(pairs.conditions, len(pairs)))
    if bounds is None:
        return None, float("nan"), 1.0
    position, orientation = bounds
    beyond = [pos_mm > 1e3 * position]
    if orientation is not None and not pairs.position_only:
        beyond.append(rot_deg > np.degrees(orientation))
    level = model.bounds.level
    counts = [int(b.sum()) for b in beyond]
    return max(counts), level, drift_p_value(counts, len(pos_mm), model.bounds)


def drift_p_value(counts: Sequence[int], judged: int, bounds: Bounds) -> float:
    """How unlikely ``counts`` of ``judged`` poses beyond each of the model's bounds (position, and orientation
    where it is judged) are for a model still as good as when its bounds were set: each kind tested on its own
    (:func:`excess_p_value`), Bonferroni over them."""
    validation = bounds.figures.get("validation_pairs")
    p_values = [excess_p_value(c, judged, bounds.level, validation) for c in counts]
    return float(min(1.0, len(counts) * min(p_values)))


def excess_p_value(over: int, count: int, level: float, validation: int | None) -> float:
    """How unlikely ``over`` of ``count`` poses beyond a bound are for a model still as good as when its bound
    was set. The bound's coverage is known from its ``validation`` pairs alone, so the check is compared with
    them (Fisher's exact test, one-sided); without that count, with the nominal share (a binomial test)."""
    if not validation:
        return float(stats.binomtest(over, count, 1.0 - level, alternative="greater").pvalue)
    allowed = round((1.0 - level) * validation)
    table = [[over, count - over], [allowed, validation - allowed]]
    return float(stats.fisher_exact(table, alternative="greater").pvalue)


def diagnose(chain: Chain, pairs: Pairs, tip: np.ndarray, top: int = 3) -> list[dict[str, Any]]:
    """The parameter groups that best explain the position residual at the target, each fitted alone by
    least squares on the nominal geometry's Jacobian: share of the residual explained and the fitted values."""
    measured = pairs.T[:, :3, 3] if pairs.position_only else (pairs.T @ pairs.targets)[:, :3, 3]
    residual = (measured - (tip @ pairs.targets)[:, :3, 3]).ravel()
    out = []
    for name, joint, columns, unit in _groups(chain, pairs):
        fitted, *_ = np.linalg.lstsq(columns, residual, rcond=None)
        left = residual - columns @ fitted
        explained = 1.0 - float(left @ left) / float(residual @ residual)
        scale = np.degrees(1.0) if unit == "deg" else 1e3
        values = ", ".join(f"{scale * v:+.4f}" for v in fitted)
        what = f"{name} ({values} {unit})"
        out.append({"group": name, "joint": joint, "explained": explained, "values": fitted.tolist(), "what": what})
    return sorted(out, key=lambda d: -d["explained"])[:top]


def _groups(chain: Chain, pairs: Pairs) -> list[tuple[str, str | None, np.ndarray, str]]:
    """Each group's name, joint (None: not a joint's), columns ``(3N, k)`` (how the target points move per
    unit of its parameters, SI) and the unit it is shown in."""
    q = pairs.q
    base = _points(chain, q, pairs.targets)
    out = []
    for j, name in enumerate(chain.joint_names):
        moved = q.copy()
        moved[:, j] += STEP
        columns = ((_points(chain, moved, pairs.targets) - base) / STEP).reshape(-1, 1)
        out.append((f"zero offset of {name}", name, columns, "deg"))
    for k, name in enumerate(chain.joint_names):
        columns = []
        for axis in np.eye(3):
            pre = chain.pre.copy()
            pre[k, :3, 3] += STEP * (pre[k, :3, :3] @ axis)
            columns.append(((_points(replace(chain, pre=pre), q, pairs.targets) - base) / STEP).ravel())
        out.append((f"origin of {name} (x, y, z)", name, np.column_stack(columns), "mm"))
    rotations = fk.fk(chain, q)[:, :3, :3]
    out.append(("the tool (x, y, z in the tip frame)", None, np.concatenate(list(rotations), axis=0), "mm"))
    shift = np.tile(np.eye(3), (len(q), 1))
    out.append(("the tracker's placement (x, y, z)", None, shift, "mm"))
    return out


def _points(chain: Chain, q: np.ndarray, targets: np.ndarray) -> np.ndarray:
    return (fk.fk(chain, q) @ targets)[:, :3, 3].ravel()
