"""Calibrating the bound on each answer's error (:mod:`model.bounds`) on the data being calibrated.

Two things are measured, each from the training run's own pairs (the test pairs never enter):

1. **How the error grows away from the data.** The validation blocks sit among the training pairs, so their
   errors cannot show it. Instead parts of joint space are held out in turn (:func:`held_out_sets`: k-means
   regions, and each end of each joint's range) and the stage is fitted on the rest: the linearised problem
   of capacity selection (:class:`calibration.parametric.Linearisation`), one solve per part. Each held-out
   pair gives an error and its distance to the configurations fitted on; the growth length is the one whose
   curve fits these errors best (:func:`growth_length`).
2. **The bound on the data.** The hybrid model's errors on the validation blocks, each divided by its
   growth factor at its distance from the stored training configurations; the bound is their split
   conformal quantile (the ⌈(n + 1)·level⌉-th smallest), so about ``level`` of errors on data like the
   validation blocks lie under it.

The nets' early stopping reads the validation blocks too; that choice of one epoch leaks little into the
quantile, and the bench (``bench/bench_bounds.py``) checks the coverage on held-out test blocks.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.cluster.vq import kmeans2
from scipy.spatial import cKDTree

from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.calibration.parametric import ORIENTATION_LENGTH, Linearisation
from hybrid_kinematics_ros.kinematics import fk
from hybrid_kinematics_ros.kinematics.chain import Chain
from hybrid_kinematics_ros.model.bounds import Bounds, ErrorBound, embed, growth

LEVEL = 0.95  # the share of errors meant to lie under their bounds
REGIONS = 8  # regions of joint space held out in turn to watch the error grow
SLAB = 0.15  # the share of each joint's values held out at each end of its range
LENGTHS = np.geomspace(1e-3, 20.0, 60)  # m: growth lengths tried (20: no growth within a robot's reach)
LEVER_SAMPLES = 2000  # configurations the lever arms are measured on
TINY = 1e-9  # m or rad: an error this small is taken as this, so that its logarithm stays finite
MIN_LEVER_ARM = 0.01  # m: a joint whose axis passes through the tip still turns the tool


def conformal_quantile(scores: np.ndarray, level: float) -> float:
    """The split conformal quantile of ``scores``: the ⌈(n + 1)·level⌉-th smallest (the largest when
    ``n`` is too small for ``level``)."""
    s = np.sort(np.asarray(scores, dtype=float))
    if len(s) == 0:
        raise CalibrationError("no validation pairs to calibrate the error bounds on")
    return float(s[min(math.ceil((len(s) + 1) * level), len(s)) - 1])


def held_out_sets(q: np.ndarray, points: np.ndarray) -> list[np.ndarray]:
    """Boolean masks over the configurations ``q (N, n)``, each a part of joint space to hold out: the
    :data:`REGIONS` k-means regions of their ``points`` (:func:`model.bounds.embed`; gaps inside the data),
    and each joint's lowest and highest :data:`SLAB` of its values (beyond the range, where a calibration
    extrapolates)."""
    regions = min(REGIONS, len(q) // 20)
    if regions < 2:
        raise CalibrationError(f"only {len(q)} pairs: too few to measure how the error grows away from them")
    _, label = kmeans2(points, regions, seed=0, minit="++")
    sets = [label == r for r in range(regions)]
    for j in range(q.shape[1]):
        low, high = np.quantile(q[:, j], [SLAB, 1.0 - SLAB])
        if high > low:
            sets += [q[:, j] < low, q[:, j] > high]
    return [s for s in sets if s.any()]


def extrapolation_errors(
    lin: Linearisation, ridge: np.ndarray, lever_arms: np.ndarray, revolute: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Held-out errors of the stage with each part of joint space (:func:`held_out_sets`) left out of its
    fit in turn: the distances (m, :func:`model.bounds.embed` with ``lever_arms``) to the configurations
    fitted on, the position errors (m) and the orientation errors (rad, None for position-only pairs).
    ``ridge (P,)``: the stage's prior on each column of ``lin``, in normal-equation units
    (:func:`capacity.harmonic_ridge`)."""
    cols = np.flatnonzero(lin.identifiable)
    jac, res, q = lin.jacobian[:, :, cols], lin.residual, lin.q
    points = embed(q, lever_arms, revolute)
    flat = jac.reshape(-1, len(cols))
    whole, gradient = flat.T @ flat + np.diag(ridge[cols]), flat.T @ res.reshape(-1)
    dist, pos, rot = [], [], []
    for held in held_out_sets(q, points):
        a = jac[held].reshape(-1, len(cols))  # the rest's normal equations: all pairs' less the held-out ones'
        normal = whole - a.T @ a
        normal += 1e-9 * max(float(np.mean(np.diag(normal))), 1e-300) * np.eye(len(cols))
        z = -np.linalg.solve(normal, gradient - a.T @ res[held].reshape(-1))
        after = res[held] + jac[held] @ z
        dist.append(cKDTree(points[~held]).query(points[held])[0])
        pos.append(np.linalg.norm(after[:, :3], axis=1))
        if res.shape[1] == 6:
            rot.append(np.linalg.norm(after[:, 3:], axis=1) / ORIENTATION_LENGTH)
    return np.concatenate(dist), np.concatenate(pos), np.concatenate(rot) if rot else None


def growth_length(distance: np.ndarray, error: np.ndarray) -> float:
    """The growth length (m) whose curve ``m₀ · growth(d)`` fits the held-out ``error`` at ``distance`` best,
    by least squares on the logarithms (``m₀`` fitted for each length): the bound is a factor times the
    error on the data, so the trend is fitted as a factor too, and a few wild extrapolations do not set it.
    The trend is what the bound carries beyond the distances held out (a bound that merely covered them
    would stop growing where they stop: held-out parts lie a few tenths of a metre from the rest)."""
    log_error = np.log(np.maximum(error, TINY))
    best, best_sse = float(LENGTHS[-1]), np.inf
    for length in LENGTHS:
        log_growth = np.log(growth(distance, length))
        sse = float(np.sum((log_error - log_growth - np.mean(log_error - log_growth)) ** 2))
        if sse < best_sse * (1.0 - 1e-9):
            best, best_sse = float(length), sse
    return best


def calibrate(
    lin: Linearisation,
    ridge: np.ndarray,
    lever_arms: np.ndarray,
    revolute: np.ndarray,
    distance: np.ndarray,
    position_error: np.ndarray,
    orientation_error: np.ndarray | None,
    level: float = LEVEL,
) -> Bounds:
    """The bounds, from the linearised stage problem over the training pairs (``lin`` with its ``ridge``,
    for the growth) and the hybrid model's validation errors (m, rad; None: position only) at their
    ``distance`` (m) from the stored training configurations, both measured with ``lever_arms``."""
    d_far, pos_far, rot_far = extrapolation_errors(lin, ridge, lever_arms, revolute)
    kinds = {"position": (pos_far, position_error)}
    if orientation_error is not None and rot_far is not None:
        kinds["orientation"] = (rot_far, orientation_error)
    made: dict[str, ErrorBound] = {}
    figures: dict[str, float | int] = {
        "validation_pairs": len(distance),
        "held_out_pairs": len(d_far),
        "validation_distance_median_m": float(np.median(distance)),
        "held_out_distance_median_m": float(np.median(d_far)),
    }
    for kind, (far, val) in kinds.items():
        length = growth_length(d_far, far)
        made[kind] = ErrorBound(conformal_quantile(val / growth(distance, length), level), length)
    return Bounds(level, np.asarray(lever_arms, dtype=float), made["position"], made.get("orientation"), figures)


def lever_arms(chain: Chain, q: np.ndarray) -> np.ndarray:
    """``(n,)``: each revolute joint's median distance to the tip over configurations ``q`` (m per rad of
    its move; 1 for a prismatic joint): the weights of the bound's distance."""
    q = q[np.random.default_rng(0).permutation(len(q))[:LEVER_SAMPLES]]
    frames = fk.joint_frames(chain, q)  # every joint's frame, then the tip's
    tip = frames[:, -1:, :3, 3]
    arms = np.median(np.linalg.norm(tip - frames[:, :-1, :3, 3], axis=2), axis=0)
    return np.where(chain.revolute, np.maximum(arms, MIN_LEVER_ARM), 1.0)
