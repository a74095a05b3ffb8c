"""A virtual cell whose geared joints have backlash: each joint stops on one side or the other of its play,
depending on the direction it arrived from, and its encoder does not see it (the real UR10's largest
effect after the joint errors, see model.approach). The truth for the approach-direction inputs and for
IK that answers for the side the joints arrive from.

The play is physical (:func:`play`): the link follows the motor only once the motor has crossed the gap,
so where it stops depends on the whole path, sampled however densely, not on a labelling of it; the
approach directions the nets get are judged independently, from the commanded joints alone."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.kinematics.robot_config import RobotConfig
from hybrid_kinematics_ros.simulation.cell import VirtualCell

# rad: how far each joint stops from its commanded angle, to either side (the shoulder and elbow of a UR10
# carry the play; about 0.3-0.4 mm at the tool 1 m out)
HALF_BACKLASH = np.array([4e-4, 3e-4, 3e-4, 0.0, 0.0, 0.0])


def play(q: np.ndarray, half: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
    """``(N, n)``: where the links are along a path of motor-side joints ``q (N, n)`` with ``half (n,)`` rad
    of play each side (the backlash operator: a link stays put until the motor pushes it, then trails it by
    ``half``); ``start (n,)``: the links before the path (default: centred on its first point). A straight
    move between two samples gives what any denser sampling of it gives."""
    q = np.atleast_2d(np.asarray(q, dtype=float))
    link = q[0].copy() if start is None else np.asarray(start, dtype=float).copy()
    out = np.empty_like(q)
    for i, x in enumerate(q):
        link = np.clip(link, x - half, x + half)
        out[i] = link
    return out


@dataclass(frozen=True)
class BacklashCell:
    cell: VirtualCell
    half: np.ndarray = field(default_factory=HALF_BACKLASH.copy)  # (n,) rad

    @classmethod
    def from_config(cls, config: RobotConfig, half: np.ndarray = HALF_BACKLASH) -> BacklashCell:
        """The noise-free virtual cell of ``config``, with ``half (n,)`` rad of play each side."""
        return cls(VirtualCell.from_config(config, noise=False), np.asarray(half, dtype=float))

    def measure(self, q: np.ndarray, directions: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """``(B, 4, 4)``: where the robot really is, commanded to ``q (B, n)`` and arriving in ``directions``
        (+1, -1 per joint, by more than the play; 0: the middle of it): the links trail the motors by
        ``half`` (:func:`play`)."""
        q = np.atleast_2d(q)
        return self.cell.measure(q - self.half * np.broadcast_to(directions, q.shape), rng)

    def miss_mm(self, q: np.ndarray, directions: np.ndarray, targets: np.ndarray) -> np.ndarray:
        """``(B,)``: how far (mm) from ``targets (B, 4, 4)`` the robot really stops, commanded to ``q`` and
        arriving in ``directions``."""
        T = self.measure(q, directions, np.random.default_rng(0))
        return 1e3 * np.linalg.norm(T[:, :3, 3] - np.reshape(targets, (-1, 4, 4))[:, :3, 3], axis=1)

    def walk(self, count: int, seed: int, step: float = 0.3, fraction: float = 0.8) -> Pairs:
        """``count`` pairs along a random walk of the joints (as a measurement program visits poses, each
        joint moving up to ``step`` rad per pose within ``fraction`` of its limits), measured with the play,
        with their approach directions."""
        chain = self.cell.config.chain
        rng = np.random.default_rng(seed)
        lower, upper = fraction * chain.lower, fraction * chain.upper
        q = np.empty((count, chain.dof))
        q[0] = rng.uniform(lower, upper)
        for i in range(1, count):
            q[i] = np.clip(q[i - 1] + rng.uniform(-step, step, chain.dof), lower, upper)
        T = self.cell.measure(play(q, self.half), rng)
        return Pairs(q, T, 10**9 + 10**7 * np.arange(count), chain.joint_names, self.cell.frame_id).with_approach()
