"""Where the IK starts: the restart table, the spread of seeds for several solutions, what counts as another
branch, and the valley restarts at a near-singular near miss.

The seed decides which solution LM finds. When the caller's seed fails, restarts come from a table of
quasi-random configurations whose (URDF-model) poses lie nearest the target, then from random ones.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import qmc

from hybrid_kinematics_ros.ik.lm import Limits, project, turned
from hybrid_kinematics_ros.kinematics import fk
from hybrid_kinematics_ros.model.hybrid import HybridModel

# The restart table: Halton configurations in a k-d tree over their poses; a solve restarts from the
# TABLE_RESTARTS nearest, the branch search from twice as many. Hand-set.
TABLE_SIZE = 4096
TABLE_RESTARTS = 16
ROTATION_LENGTH = 0.3  # m: weight of the rotation matrix entries against the position in the table metric
SPREAD_SEEDS = 64  # deterministic seeds solve_many tries after the caller's: enough to reach every branch of a 6R arm
# A URDF-model answer this close to a hybrid target starts in the hybrid solution's basin: the nets correct
# millimetres and milliradians.
NEAR_M, NEAR_RAD = 5e-3, 1e-2
BRANCH_RAD = 1e-2  # classical answers closer than this on every joint are one branch
SAME_SOLUTION_RAD = 1e-3  # solve_many's duplicates, modulo 2π on revolute joints
# The valley restarts: a near miss (mm) at a near-singular hybrid Jacobian (smallest singular value), and the
# steps along its weak direction, where the local minima of the hybrid near-solutions lie (chosen by bench_ik,
# BENCHMARKS.md).
VALLEY_MM, VALLEY_SINGULAR = 0.1, 1e-2
VALLEY_STEPS_RAD = (-0.7, 0.7, -1.2, 1.2)


def _pose_features(T: np.ndarray) -> np.ndarray:
    """``(B, 12)``: position and scaled rotation entries; Euclidean distance ~ pose distance."""
    return np.concatenate([T[:, :3, 3], ROTATION_LENGTH * T[:, :3, :3].reshape(-1, 9)], axis=1)


class SeedTable:
    """The deterministic seeds of one chain (built once per solver) and the random ones after them."""

    def __init__(self, model: HybridModel, lower: np.ndarray, upper: np.ndarray) -> None:
        self.lower, self.upper = lower, upper
        self._rng = np.random.default_rng(0)
        sampler = qmc.Halton(d=model.chain.dof, seed=0)
        self.spread = qmc.scale(sampler.random(SPREAD_SEEDS), lower, upper)
        self.table = qmc.scale(sampler.random(TABLE_SIZE), lower, upper)
        self._tree = cKDTree(_pose_features(fk.fk(model.chain, self.table)))

    def nearest(self, target: np.ndarray, k: int) -> np.ndarray:
        """The ``k`` table configurations whose (URDF-model) poses lie nearest ``target``."""
        _, index = self._tree.query(_pose_features(target[None])[0], k=k)
        return self.table[np.atleast_1d(index)]

    def random(self) -> np.ndarray:
        """A uniform configuration within the limits, from the table's own generator (reproducible)."""
        return self._rng.uniform(self.lower, self.upper)


def is_new_branch(q: np.ndarray, tried: list[np.ndarray]) -> bool:
    """Another branch than every one in ``tried``. One shifted by 2π on a joint counts as another: the nets
    see raw joint values, so it is another hybrid problem."""
    return not any(np.abs(q - t).max() < BRANCH_RAD for t in tried)


def valley_seeds(
    model: HybridModel, q: np.ndarray | None, position_error_mm: float, limits: Limits
) -> list[np.ndarray]:
    """Restarts along the weak direction of the hybrid Jacobian from a near miss at a near-singular
    configuration. There the hybrid near-solutions form a valley (at a wrist singularity, joints 4 and 6
    trade off), and LM settles in a local minimum of it tenths of a radian from the solution."""
    if q is None or position_error_mm > VALLEY_MM:
        return []
    _, sv, vt = np.linalg.svd(model.fk_and_jacobian_single(q)[1], full_matrices=False)  # 7 joints: not the null space
    if sv[-1] > VALLEY_SINGULAR:
        return []
    return [project(q + step * vt[-1], *limits) for step in VALLEY_STEPS_RAD]


def nearest_equivalent(q: np.ndarray, seed: np.ndarray, limits: Limits) -> np.ndarray:
    """Shift revolute joints by multiples of 2π towards the seed, staying inside the limits."""
    lower, upper, revolute = limits
    out = q.copy()
    for j in np.flatnonzero(revolute):
        k = np.round((seed[j] - q[j]) / (2 * np.pi))
        for shift in (k, k - np.sign(k)) if k else (0,):
            cand = q[j] + 2 * np.pi * shift
            if lower[j] - 1e-12 <= cand <= upper[j] + 1e-12:
                out[j] = cand
                break
    return out


def same_solution(a: np.ndarray, b: np.ndarray, revolute: np.ndarray) -> bool:
    """Equal within SAME_SOLUTION_RAD on every joint, modulo 2π on revolute ones."""
    return bool(np.all(np.abs(turned(a - b, revolute)) < SAME_SOLUTION_RAD))
