"""The virtual cell: a ground-truth robot observed by a laser tracker."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.kinematics.robot_config import RobotConfig
from hybrid_kinematics_ros.simulation.sampling import sample_joints
from hybrid_kinematics_ros.simulation.tracker import Tracker
from hybrid_kinematics_ros.simulation.truth import TrueRobot


@dataclass(frozen=True)
class VirtualCell:
    config: RobotConfig
    robot: TrueRobot
    tracker: Tracker

    @classmethod
    def from_config(cls, config: RobotConfig, noise: bool = True, seed: int | None = None) -> VirtualCell:
        return cls(config, TrueRobot.from_config(config, seed=seed), Tracker.from_config(config.tracker, noise=noise))

    @property
    def frame_id(self) -> str:
        return self.tracker.frame_id or self.config.base_link

    def measure(self, q: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Tracker measurements ``(B, 4, 4)`` of the robot at commanded joints ``q``."""
        return self.tracker.measure(self.robot.fk(q), rng)

    def pairs(self, q: np.ndarray, seed: int) -> Pairs:
        """The cell's measurements at commanded joints ``q (N, n)`` as pairs, 10 ms apart."""
        T = self.measure(q, np.random.default_rng(seed))
        return Pairs(q, T, 10**9 + 10**7 * np.arange(len(q)), self.config.chain.joint_names, self.frame_id)

    def samples(
        self, count: int, seed: int, fraction: float = 1.0, block: int = 50_000
    ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """Blocks of ``(q, T_measured)``, reproducible for a given seed and block size."""
        rng = np.random.default_rng(seed)
        q = sample_joints(self.config.chain, count, rng, fraction)
        noise_rng = np.random.default_rng([seed, 1])
        for s in range(0, count, block):
            yield q[s : s + block], self.measure(q[s : s + block], noise_rng)
