"""The direction each joint last moved in before a pose: an input for backlash and friction.

A geared joint stops on one side or the other of its lost motion (backlash, and the torsion friction holds),
depending on the direction it came from; the encoder on the motor side does not see it. On the real UR10
data set (series A) the residual of the parametric stage depends on that direction: nets given it as an
input predict held-out poses better, in position and orientation, than nets on the joints alone (BENCHMARKS.md).
ISO 9283 measures the same effect as multi-directional pose accuracy.

The direction is +1 or -1 per joint: the way the joint last went by more than ``still`` (rad) from its
last turning point, with hysteresis, so the label does not depend on how often the motion was sampled.
A slow final approach of 0.5 mrad is a move whether it arrives as one row of a tracker export or as
thousands of 500 Hz joint states a few microradians apart (judged step by step, it would be no move at all).
0 where no move is known yet (the first pose, or a joint that has not moved), which the nets take as
halfway between the two sides. It comes from the order of the poses: the rows of a tracker export, the
pairs of a bag in stamp order, the joint states a node receives.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

STILL_RAD = 1e-4  # a smaller change of a joint between two poses is not a move (encoder noise, a joint at rest)
PREFIX = "approach_"  # condition channels approach_<joint name>, one per joint


def channel_names(joint_names: Sequence[str]) -> tuple[str, ...]:
    """The condition channels that carry each joint's approach direction."""
    return tuple(PREFIX + name for name in joint_names)


def is_channel(name: str) -> bool:
    return name.startswith(PREFIX)


def approach_directions(q: np.ndarray, still: float = STILL_RAD, start: np.ndarray | None = None) -> np.ndarray:
    """``(N, n)`` in {-1, 0, +1}: for each pose of the sequence ``q (N, n)`` and each joint, the way it last
    went by more than ``still`` from its last turning point (see the module text); ``start (n,)`` the
    directions before the first pose (default 0: unknown)."""
    q = np.asarray(q, dtype=float)
    out = np.empty_like(q)
    if not len(q):
        return out
    tracker = ApproachTracker(q.shape[1], still, start)
    for i, row in enumerate(q):
        out[i] = tracker.update(row)
    return out


def arrival_directions(start: np.ndarray, end: np.ndarray, current: np.ndarray, still: float = STILL_RAD) -> np.ndarray:
    """The directions the joints arrive at ``end`` in when they move there from ``start`` (each ``(n,)`` or
    ``(N, n)``): the sign of the move, or ``current`` for a joint that moves less than ``still`` (it stays
    on the side it is on). What IK answers with: the robot goes from the seed (where it is) to the solution."""
    move = np.asarray(end, dtype=float) - np.asarray(start, dtype=float)
    return np.where(np.abs(move) > still, np.sign(move), np.asarray(current, dtype=float))


class ApproachTracker:
    """The directions from a stream of joint positions, one at a time (a node's joint states, or the rows
    of a sequence): a Schmitt trigger on each joint's travel since its last turning point."""

    def __init__(self, dof: int, still: float = STILL_RAD, start: np.ndarray | None = None) -> None:
        self.still = still
        self.directions = np.zeros(dof) if start is None else np.array(start, dtype=float)
        self.extreme: np.ndarray | None = None  # furthest point of the current direction (the start, at first)

    def update(self, q: np.ndarray) -> np.ndarray:
        q = np.asarray(q, dtype=float)
        if self.extreme is None:
            self.extreme = q.copy()
            return self.directions
        d, e = self.directions, self.extreme
        up = (q > e + self.still) & (d <= 0)  # turned (or first moved) upwards by more than still
        down = (q < e - self.still) & (d >= 0)
        further = ((d > 0) & (q > e)) | ((d < 0) & (q < e))  # still going the same way: a new extreme
        self.directions = np.where(up, 1.0, np.where(down, -1.0, d))
        self.extreme = np.where(up | down | further, q, e)
        return self.directions
