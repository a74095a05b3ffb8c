"""Calibrating the bound on each answer's error (:mod:`model.bounds`) on the data being calibrated.

Two things are measured, each from the training run's own pairs (the test pairs never enter):

1. **How fast the error grows beyond the trained range, joint by joint.** The validation blocks sit among
   the training pairs, so their errors cannot show it. Instead each end of each joint's range is held out in
   turn, in slabs of :data:`SLABS` of its values, and the stage is fitted on the rest: the linearised
   problem of capacity selection (:class:`calibration.parametric.Linearisation`), one solve per slab. Each
   held-out pair lies some way beyond the rest's range of that joint (:func:`model.bounds.excess`); the
   joint's rate is the slope of the held-out errors' ``level`` quantile over that excess, above the fit's
   own error (:func:`growth_rate`).
2. **How hard each configuration is** (:class:`model.bounds.Scale`): the logarithm of the identified
   stage's errors on the training pairs, regressed on the joints' sines and cosines (:func:`fit_scale`).
   The stage's, not the hybrid's: the nets fit their training pairs closer than they predict, the stage
   barely does. The bound then follows the error more closely (BENCHMARKS.md, "bounds").
3. **The bound inside the range.** The hybrid model's errors on the validation blocks, less the growth at
   their excess (nearly all lie inside: none), divided by their scale, and the split conformal quantile of
   that (the ⌈(n + 1)·level⌉-th smallest), so about ``level`` of errors on data like the validation blocks
   lie under their bounds whatever the scale.

The nets' early stopping reads the validation blocks too; that choice of one epoch leaks little into the
quantile, and the bench (``bench/bench_bounds.py``) checks the coverage on held-out test blocks. The nets'
own extrapolation is not measured (that would retrain them per slab): their bound grows at the stage's rates.
On a virtual UR10 trained with its shoulder in one radian, and on the real UR10 trained on series C and
tested on B, the hybrid stays better than the stage beyond the trained range (BENCHMARKS.md).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.calibration.parametric import Linearisation
from hybrid_kinematics_ros.model.bounds import Bounds, ErrorBound, Scale, excess, features

LEVEL = 0.95  # the share of errors meant to lie under their bounds
# Each end of each joint's range held out in slabs of these shares of its values: the widest extrapolates
# almost half the range, so the rate is measured over the distances a model is asked to extrapolate.
SLABS = (0.15, 0.3, 0.45)
BINS = 10  # the held-out pairs beyond a joint's range, in bins of equal count, for the quantile's slope
MIN_BIN = 5  # pairs: a bin with fewer gives no quantile
MIN_PAIRS = 40  # too few pairs to hold a slab out of the stage's fit
SCALE_RIDGE = 1e-3  # per pair, on the scale's weights (features of order 1): for joints that never move


def conformal_quantile(scores: np.ndarray, level: float) -> float:
    """The split conformal quantile of ``scores``: the ⌈(n + 1)·level⌉-th smallest (the largest when
    ``n`` is too small for ``level``)."""
    s = np.sort(np.asarray(scores, dtype=float))
    if len(s) == 0:
        raise CalibrationError("no validation pairs to calibrate the error bounds on")
    return float(s[min(math.ceil((len(s) + 1) * level), len(s)) - 1])


def held_out_slabs(q: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """``(joint, mask)`` over the configurations ``q (N, n)``: each joint's lowest and highest share of its
    values, for each share in :data:`SLABS` (a joint that never moves gives none)."""
    if len(q) < MIN_PAIRS:
        raise CalibrationError(f"only {len(q)} pairs: too few to measure how the error grows beyond their range")
    slabs = []
    for j in range(q.shape[1]):
        for share in SLABS:
            low, high = np.quantile(q[:, j], [share, 1.0 - share])
            if high > low:
                slabs += [(j, q[:, j] < low), (j, q[:, j] > high)]
    return [(j, m) for j, m in slabs if m.any() and not m.all()]


def extrapolation_errors(
    lin: Linearisation, ridge: np.ndarray, revolute: np.ndarray
) -> tuple[tuple[np.ndarray, np.ndarray | None], list[tuple[int, np.ndarray, np.ndarray, np.ndarray | None]]]:
    """The stage's errors where it extrapolates. Returns the errors of its fit on all pairs (position m,
    orientation rad or None for position-only pairs), and for each held-out
    slab (:func:`held_out_slabs`): its joint, each held-out pair's excess beyond the rest's range of that
    joint, and their position (m) and orientation (rad, None for position-only pairs) errors after a fit on
    the rest. ``ridge (P,)``: the stage's prior on each column of ``lin``, in normal-equation units
    (:func:`capacity.harmonic_ridge`)."""
    cols = np.flatnonzero(lin.identifiable)
    jac, res, q = lin.jacobian[:, :, cols], lin.residual, lin.q
    flat = jac.reshape(-1, len(cols))
    whole, gradient = flat.T @ flat + np.diag(ridge[cols]), flat.T @ res.reshape(-1)

    def solve(normal: np.ndarray, rhs: np.ndarray) -> np.ndarray:  # a relative jitter keeps it regular
        return np.linalg.solve(normal + 1e-9 * max(float(np.mean(np.diag(normal))), 1e-300) * np.eye(len(rhs)), rhs)

    fitted = res + jac @ -solve(whole, gradient)

    def norms(after: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        rot = np.linalg.norm(after[:, 3:], axis=1) / lin.orientation_length if after.shape[1] == 6 else None
        return np.linalg.norm(after[:, :3], axis=1), rot

    on_data = norms(fitted)
    slabs = []
    for joint, held in held_out_slabs(q):
        a = jac[held].reshape(-1, len(cols))  # the rest's normal equations: all pairs' less the held-out ones'
        z = -solve(whole - a.T @ a, gradient - a.T @ res[held].reshape(-1))
        rest = q[~held, joint]
        x = excess(q[held, joint : joint + 1], rest.min()[None], rest.max()[None], revolute[joint : joint + 1])[:, 0]
        slabs.append((joint, x, *norms(res[held] + jac[held] @ z)))
    return on_data, slabs


def growth_rate(x: np.ndarray, error: np.ndarray, floor: float, level: float) -> float:
    """How fast the ``level`` quantile of ``error`` grows with the excess ``x`` beyond the range (per rad):
    the held-out pairs beyond it in :data:`BINS` bins of equal count, each bin's quantile above ``floor``
    (the fit's own, on its data), and the least-squares slope through the origin; 0 without pairs beyond."""
    beyond = x > 0
    if beyond.sum() < MIN_BIN:
        return 0.0
    x, error = x[beyond], error[beyond]
    edges = np.quantile(x, np.linspace(0.0, 1.0, BINS + 1))
    at, above = [], []
    for lo, hi in itertools.pairwise(edges):
        inside = (x >= lo) & (x <= hi)
        if inside.sum() >= MIN_BIN:
            at.append(np.median(x[inside]))
            above.append(np.quantile(error[inside], level) - floor)
    at, above = np.array(at), np.array(above)
    return max(0.0, float(at @ above / (at @ at))) if len(at) else 0.0


def fit_scale(q: np.ndarray, error: np.ndarray, revolute: np.ndarray) -> Scale:
    """:class:`Scale` from the stage's errors ``(N,)`` on the training configurations ``q (N, n)``: the
    least-squares fit of ``log(error)`` on :func:`model.bounds.features`, 1 at the median configuration,
    clipped to the range it takes on these pairs. An error of zero counts as a hundredth of the median (a
    logarithm needs a floor, and one relative to the errors is the same for every unit and robot)."""
    typical = float(np.median(error))
    if not typical > 0.0:  # a noise-free fit: every configuration alike
        return Scale(np.zeros(1 + 2 * q.shape[1]), 1.0, 1.0)
    a = features(q, revolute)
    y = np.log(np.maximum(error, 0.01 * typical))
    w = np.linalg.solve(a.T @ a + SCALE_RIDGE * len(a) * np.eye(a.shape[1]), a.T @ y)
    w[0] -= float(np.median(a @ w))  # 1 at the median configuration
    fitted = np.exp(a @ w)
    return Scale(w, float(fitted.min()), float(fitted.max()))


@dataclass(frozen=True)
class Validation:
    """The validation pairs as the bounds see them: configurations ``q (N, n)``, their ``excess (N, n)``
    beyond the trained range, and the hybrid model's and the stage alone's errors there (each: position m,
    orientation rad or None for position-only data)."""

    q: np.ndarray
    excess: np.ndarray
    hybrid: tuple[np.ndarray, np.ndarray | None]
    stage: tuple[np.ndarray, np.ndarray | None]


def calibrate(
    lin: Linearisation,
    ridge: np.ndarray,
    revolute: np.ndarray,
    training: tuple[np.ndarray, np.ndarray, np.ndarray | None],
    validation: Validation,
    level: float = LEVEL,
) -> Bounds:
    """The bounds, from the linearised stage problem over the training pairs (``lin`` with its ``ridge``,
    for the rates), the stage's errors on them (``training``: configurations, position m, orientation rad or
    None; for the scale) and the errors on the ``validation`` pairs: the hybrid model's for the bound's size,
    the stage alone's for its own quantile (the ``bound`` range policy compares the two)."""
    validation_q, validation_excess = validation.q, validation.excess
    position_error, orientation_error = validation.hybrid
    stage_error = validation.stage
    on_data, slabs = extrapolation_errors(lin, ridge, revolute)
    n = len(revolute)
    kinds = {"position": (0, position_error, stage_error[0])}
    if orientation_error is not None and on_data[1] is not None and training[2] is not None:
        kinds["orientation"] = (1, orientation_error, stage_error[1])
    made: dict[str, ErrorBound] = {}
    figures: dict[str, float | int | list[float]] = {
        "validation_pairs": len(validation_excess),
        "validation_beyond_range": int((validation_excess > 0).any(axis=1).sum()),
        "held_out_slabs": len(slabs),
        "held_out_pairs": int(sum(len(s[1]) for s in slabs)),
    }
    for kind, (column, validation, stage_validation) in kinds.items():
        floor = conformal_quantile(on_data[column], level)
        rates = np.zeros(n)
        for j in range(n):
            mine = [(x, err[column]) for joint, x, *err in slabs if joint == j]
            if mine:
                x = np.concatenate([m[0] for m in mine])
                rates[j] = growth_rate(x, np.concatenate([m[1] for m in mine]), floor, level)
        scale = fit_scale(training[0], training[1 + column], revolute)
        at = scale(validation_q, revolute)
        figures[f"{kind}_scale_p5_p95"] = [float(v) for v in np.percentile(scale(training[0], revolute), [5, 95])]
        # a validation pair beyond the range counts for what its error exceeds the growth there
        grown = np.linalg.norm(validation_excess * rates, axis=1)
        left = np.maximum(validation - grown, 0.0)
        stage_left = np.maximum(stage_validation - grown, 0.0)
        made[kind] = ErrorBound(
            conformal_quantile(left / at, level), rates, scale, conformal_quantile(stage_left / at, level)
        )
        figures[f"{kind}_quantile_without_scale"] = conformal_quantile(left, level)  # the quantile without a scale
    return Bounds(level, made["position"], made.get("orientation"), figures)
