"""The measurement floor of a data set: what even a perfect model's mean error would be on one measurement.

Two measurements of (nearly) the same joints, from one tracker station and separate visits, differ by the
measurement's own scatter (tracker noise, encoder noise, what the robot does not repeat) and by the model's
error change over their joint difference, which ``FLOOR_TOLERANCE_RAD`` keeps negligible. So the floor is the
mean of ``|Δ residual| / √2`` over such pairs, the residual taken against the URDF model with its own
referencing. The spread of repeated poses about their mean is smaller by about √2 for pairs, so it is not this
floor. Data that never repeats a
configuration has no floor to tell.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from hybrid_kinematics_ros.calibration.evaluate import measured_targets
from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.kinematics import fk, se3
from hybrid_kinematics_ros.kinematics.chain import Chain
from hybrid_kinematics_ros.model.referencing import Referencing, to_base_frame

FLOOR_TOLERANCE_RAD = 1e-3  # two poses this close in every joint count as a repeat
FLOOR_APART_S = 1.0  # ... when measured this far apart: samples of one stop repeat the tracker, not the robot


@dataclass(frozen=True)
class Floor:
    position_mm: float
    orientation_deg: float  # NaN for position-only data
    pairs: int  # pairs of repeated configurations it stands on

    def manifest(self) -> dict[str, Any]:
        return {
            "position_mm": self.position_mm,
            "orientation_deg": None if np.isnan(self.orientation_deg) else self.orientation_deg,
            "pairs": self.pairs,
        }

    def line(self, held_out_mm: float) -> str:
        """What ``train`` says of a held-out mean position error (mm) against this floor."""
        return (
            f"held-out error {held_out_mm:.4f} mm, {held_out_mm / self.position_mm:.2f}x the floor of this data "
            f"({self.position_mm:.4f} mm, from {self.pairs} pairs of repeated joints)"
        )


def tracker_line(floor: tuple[float, float], held_out_mm: float) -> str:
    """What ``train`` says of a held-out mean position error (mm) against the tracker's own floor (m, rad:
    :attr:`Pairs.floor`)."""
    mm = 1e3 * floor[0]
    if not mm > 0.0:
        return f"held-out error {held_out_mm:.4f} mm; the export shows no scatter of the tracker's own"
    return (
        f"held-out error {held_out_mm:.4f} mm, {held_out_mm / mm:.2f}x the tracker's own floor ({mm:.4f} mm, as the "
        "export tells it; what the robot does not repeat comes on top)"
    )


def measurement_floor(stations: Sequence[Pairs], chain: Chain, referencings: Mapping[str, Referencing]) -> Floor | None:
    """The floor of ``stations`` (one :class:`Pairs` per frame; repeats are paired within a station), each
    moved into the base frame with ``referencings``; None when no configuration repeats."""
    position, orientation = [], []
    for pairs in stations:
        close = cKDTree(pairs.q).query_pairs(FLOOR_TOLERANCE_RAD, p=np.inf, output_type="ndarray")
        if len(close):
            close = close[np.abs(pairs.stamps[close[:, 0]] - pairs.stamps[close[:, 1]]) > FLOOR_APART_S * 1e9]
        if not len(close):
            continue
        base = to_base_frame([pairs], chain, referencings)
        model = fk.fk(chain, base.q) @ base.targets
        measured = measured_targets(base)
        residual = measured[:, :3, 3] - model[:, :3, 3]
        position.append(np.linalg.norm(residual[close[:, 0]] - residual[close[:, 1]], axis=1))
        if not pairs.position_only:
            local = se3.inverse(model) @ measured  # the measured pose in the model's frame
            orientation.append(se3.pose_errors(local[close[:, 0]], local[close[:, 1]])[1])
    if not position:
        return None
    root2 = np.sqrt(2.0)
    rot = float(np.mean(np.concatenate(orientation))) / root2 if orientation else float("nan")
    return Floor(1e3 * float(np.mean(np.concatenate(position))) / root2, rot, int(sum(len(p) for p in position)))
