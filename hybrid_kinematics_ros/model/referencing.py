"""Where the tracker stands relative to the robot base and where the target sits on the flange, as the
served model reads it from ``model.json``; :mod:`hybrid_kinematics_ros.calibration.referencing` fits it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.kinematics import se3
from hybrid_kinematics_ros.kinematics.chain import Chain
from hybrid_kinematics_ros.model.errors import ModelError


@dataclass(frozen=True)
class Referencing:
    frame_id: str  # the tracker's frame, as in the pairs
    base_to_tracker: np.ndarray  # (4, 4): the tracker frame in the robot's base frame
    flange_to_target: np.ndarray  # (4, 4): the target in the tip (flange) frame
    position_only: bool
    rms_position_mm: float = float("nan")
    rms_orientation_deg: float = float("nan")
    method: str = "least squares"
    outliers: int = 0  # pairs far off what the fit leaves (calibration.parametric.outliers), left out of the rms
    undetermined: tuple[str, ...] = ()  # what the poses left undetermined and held at the prior, and how to fix it

    def to_base(self, pairs: Pairs, base_link: str) -> Pairs:
        """The pairs in the base frame: tip poses for a 6-DoF target, the target points for a position-only one.

        A reflector's offset from the tip is along the tip's axes, which a position-only measurement does
        not give; it cannot be subtracted without a model of the tip's orientation. So the point stays the
        target and the models predict the target instead. Either way the pairs carry ``flange_to_target``
        as their :attr:`Pairs.target`, where errors are judged.
        """
        if pairs.frame_id != self.frame_id:
            raise ModelError(f"the pairs are in frame '{pairs.frame_id}', but the referencing is for '{self.frame_id}'")
        if pairs.position_only:
            T = self.base_to_tracker @ pairs.T
            T[:, :3, :3] = np.eye(3)  # still no orientation
        else:
            T = self.base_to_tracker @ pairs.T @ se3.inverse(self.flange_to_target)
        target = np.broadcast_to(self.flange_to_target, (len(pairs), 4, 4)).copy()
        return replace(pairs.with_poses(T, base_link), target=target)

    def manifest(self) -> dict[str, Any]:
        return {
            "frame_id": self.frame_id,
            "method": self.method,
            "base_to_tracker": self.base_to_tracker.tolist(),
            "flange_to_target": self.flange_to_target.tolist(),
            "position_only": self.position_only,
            "rms_position_mm": self.rms_position_mm,
            "rms_orientation_deg": self.rms_orientation_deg,
            "outliers": self.outliers,
            "undetermined": list(self.undetermined),
        }

    @classmethod
    def from_manifest(cls, section: dict[str, Any]) -> Referencing:
        try:
            return cls(
                str(section["frame_id"]),
                np.asarray(section["base_to_tracker"], dtype=float).reshape(4, 4),
                np.asarray(section["flange_to_target"], dtype=float).reshape(4, 4),
                bool(section["position_only"]),
                float(section.get("rms_position_mm", float("nan"))),
                float(section.get("rms_orientation_deg", float("nan"))),
                str(section.get("method", "least squares")),
                int(section.get("outliers", 0)),
                tuple(str(note) for note in section.get("undetermined", ())),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelError(f"model.json: the referencing section is malformed ({exc!r})") from exc


def to_base_frame(stations: Sequence[Pairs], chain: Chain, referencings: Mapping[str, Referencing]) -> Pairs:
    """All stations' pairs in the base frame, each moved with its own frame's referencing."""
    parts = []
    for pairs in stations:
        if pairs.frame_id == chain.base_link:
            parts.append(pairs)
        elif pairs.frame_id in referencings:
            parts.append(referencings[pairs.frame_id].to_base(pairs, chain.base_link))
        else:
            known = ", ".join(f"'{f}'" for f in referencings) or "none"
            raise ModelError(
                f"the pairs are in frame '{pairs.frame_id}', not the base link '{chain.base_link}', and the model "
                f"is referenced to {known}; train with a bag of that tracker station among --bag to reference it"
            )
    return Pairs.concatenate(parts)
