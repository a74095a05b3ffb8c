"""Smooth joint trajectories through waypoints, for the simulated cell.

Between waypoints every joint follows the same smoothstep profile (zero velocity at both ends), timed so
the fastest joint moves at ``speed`` rad/s on average; the robot then dwells for ``dwell_s`` (still
windows for static-mode recording). Waypoints: ``random`` ones in a reduced joint range here; the ISO 9283
test cube's come from IK (:func:`hybrid_kinematics_ros.ik.cube.cube_waypoints`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hybrid_kinematics_ros.kinematics.chain import Chain
from hybrid_kinematics_ros.simulation.errors import SimulationError
from hybrid_kinematics_ros.simulation.sampling import joint_range


@dataclass(frozen=True)
class Trajectory:
    waypoints: np.ndarray  # (W, n)
    starts: np.ndarray  # (W,) start time of the move towards waypoint i (s); move 0 is a dwell at waypoint 0
    durations: np.ndarray  # (W,) move durations (s)
    dwell_s: float

    @property
    def period(self) -> float:
        return float(self.starts[-1] + self.durations[-1] + self.dwell_s)

    def __call__(self, t: np.ndarray) -> np.ndarray:
        """Joints ``(B, n)`` at times ``t (B,)`` s; the trajectory loops."""
        t = np.asarray(t, dtype=float) % self.period
        i = np.clip(np.searchsorted(self.starts, t, side="right") - 1, 0, len(self.starts) - 1)
        prev = self.waypoints[i - 1]
        s = np.clip((t - self.starts[i]) / self.durations[i], 0.0, 1.0)
        s = s * s * (3.0 - 2.0 * s)
        return prev + s[:, None] * (self.waypoints[i] - prev)


def through(waypoints: np.ndarray, speed: float, dwell_s: float) -> Trajectory:
    if speed <= 0:
        raise SimulationError(f"trajectory speed must be positive, got {speed}")
    w = np.asarray(waypoints, dtype=float)
    step = np.abs(w - np.roll(w, 1, axis=0)).max(axis=1)  # move i goes from waypoint i-1 to i (looping)
    durations = np.maximum(1.5 * step / speed, 0.05)  # smoothstep peaks at 1.5x its mean speed
    starts = np.concatenate([[0.0], np.cumsum(durations + dwell_s)[:-1]])
    return Trajectory(w, starts, durations, dwell_s)


def random_waypoints(chain: Chain, count: int, rng: np.random.Generator, fraction: float = 0.6) -> np.ndarray:
    lo, hi = joint_range(chain, fraction)
    return rng.uniform(lo, hi, (count, chain.dof))


@dataclass(frozen=True)
class JointStep:
    """A joint that slips by ``rad`` at ``after_s`` (a re-mastering gone wrong, a slipped gear): the robot
    reaches ``q + rad`` on that joint while its encoders still read ``q``."""

    joint: int
    rad: float
    after_s: float

    def reached(self, q: np.ndarray, t: np.ndarray) -> np.ndarray:
        """The joints the robot reaches at times ``t (B,)`` s when commanded ``q (B, n)``."""
        out = np.array(q, dtype=float, copy=True)
        out[np.asarray(t) >= self.after_s, self.joint] += self.rad
        return out
