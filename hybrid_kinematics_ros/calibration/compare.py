"""Two calibrations of one robot side by side: which parameters moved beyond their uncertainty, how far the two
models' tip poses differ over the range both were trained on, and how each does on a shared check.

A parameter moved when the change exceeds ``CHANGE_SIGMAS`` times the σ of the difference (the two σ in
quadrature, :class:`~hybrid_kinematics_ros.calibration.parametric.Uncertainty`). The tip difference is the full
served models' (stage and nets) over the joint range both were trained on, in the robot's base frame, so the
tracker stations they were referenced to do not enter it. Where the two trained ranges of a joint do not overlap,
it is the parametric stages' over both ranges: neither model's nets are calibrated in the other's.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.calibration.verify import Verification, verify
from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.kinematics import se3
from hybrid_kinematics_ros.model.hybrid import HybridModel

CHANGE_SIGMAS = 3.0  # a change beyond this many σ of the difference is flagged
TIP_SAMPLES = 5000  # configurations drawn over the shared trained range


@dataclass(frozen=True)
class Comparison:
    """``parameters``: one entry per parameter both stages identified (SI values, their σ, the change in σ,
    flagged); ``tip``: the position (mm) and orientation (deg) differences at ``q``; ``checks``: each model's
    verification on the shared check, if one was given."""

    parameters: list[dict[str, Any]]
    q: np.ndarray
    position_mm: np.ndarray
    orientation_deg: np.ndarray
    checks: dict[str, Verification]
    apart: tuple[str, ...] = ()  # joints whose trained ranges do not overlap: the tips are the stages' alone

    @property
    def flagged(self) -> list[dict[str, Any]]:
        return [p for p in self.parameters if p["flagged"]]

    def tip_stats(self) -> dict[str, float]:
        out: dict[str, Any] = {"configurations": len(self.q), "stages_only_apart_in": list(self.apart)}
        for name, values in (("position_mm", self.position_mm), ("orientation_deg", self.orientation_deg)):
            out |= {f"{name}_max": float(values.max()), f"{name}_p95": float(np.percentile(values, 95))}
        return out

    def lines(self) -> list[str]:
        tip = self.tip_stats()
        out = [
            f"{len(self.flagged)} of {len(self.parameters)} parameters moved by more than {CHANGE_SIGMAS:g} σ",
            *(f"  {p['name']}: {p['a']:+.4g} -> {p['b']:+.4g} {p['unit']} ({p['sigmas']:.1f} σ)" for p in self.flagged),
            f"tip difference over {tip['configurations']} configurations {self.where()}: position max "
            f"{tip['position_mm_max']:.4f} mm, p95 {tip['position_mm_p95']:.4f} mm; orientation max "
            f"{tip['orientation_deg_max']:.4f} deg, p95 {tip['orientation_deg_p95']:.4f} deg",
        ]
        for label, check in self.checks.items():
            out.append(f"{label} on the check: {'; '.join(check.lines()[:2])}")
        return out

    def where(self) -> str:
        """Where the tips were compared."""
        if not self.apart:
            return "of the range both were trained on"
        return (
            f"of both trained ranges (they do not overlap in {', '.join(self.apart)}), the parametric stages alone: "
            "neither model's nets know the other's range"
        )

    def manifest(self) -> dict[str, Any]:
        return {
            "change_sigmas": CHANGE_SIGMAS,
            "parameters": self.parameters,
            "tip": self.tip_stats(),
            "checks": {label: check.manifest() for label, check in self.checks.items()},
        }


def compare(
    a: HybridModel, b: HybridModel, check: Sequence[Pairs] = (), count: int = TIP_SAMPLES, seed: int = 0
) -> Comparison:
    """Compare model ``a`` with model ``b`` (the same robot's joints); ``check``: pairs to verify both on."""
    if a.chain.joint_names != b.chain.joint_names:
        raise CalibrationError(
            f"the models move different joints ({', '.join(a.chain.joint_names)} against "
            f"{', '.join(b.chain.joint_names)}): compare two calibrations of one robot"
        )
    q, apart = _shared_range(a, b, count, seed)
    nets = not apart  # the nets are not compared where neither was trained
    position_mm, orientation_deg = se3.pose_errors(b.fk(q, nets=nets), a.fk(q, nets=nets))
    checks = {"A": verify(a, check), "B": verify(b, check)} if check else {}
    return Comparison(_parameters(a.manifest, b.manifest), q, position_mm, orientation_deg, checks, apart)


def _shared_range(a: HybridModel, b: HybridModel, count: int, seed: int) -> tuple[np.ndarray, tuple[str, ...]]:
    """``count`` configurations drawn uniformly where both models were trained; where their ranges of a joint
    do not overlap, over both ranges together, and those joints."""
    ranges = [m.manifest.get("trained_range") or {"lower": m.chain.lower, "upper": m.chain.upper} for m in (a, b)]
    lows, highs = (np.array([r[k] for r in ranges], dtype=float) for k in ("lower", "upper"))
    lower, upper = lows.max(axis=0), highs.min(axis=0)
    apart = lower >= upper
    lower[apart], upper[apart] = lows.min(axis=0)[apart], highs.max(axis=0)[apart]
    q = np.random.default_rng(seed).uniform(lower, upper, (count, len(lower)))
    return q, tuple(a.chain.joint_names[j] for j in np.flatnonzero(apart))


def _parameters(a: dict[str, Any], b: dict[str, Any]) -> list[dict[str, Any]]:
    """The parameters both stages identified, with the change in σ of the difference (NaN without σ)."""
    if "parametric" not in a or "parametric" not in b:
        return []
    theirs = {p["name"]: p for p in b["parametric"]["parameters"]}
    out = []
    for mine in a["parametric"]["parameters"]:
        other = theirs.get(mine["name"])
        if other is None or not (mine["identifiable"] and other["identifiable"]) or mine["kind"] == "harmonic":
            continue
        sigma = float(np.hypot(mine.get("sigma", np.nan), other.get("sigma", np.nan)))
        change = other["value"] - mine["value"]
        sigmas = abs(change) / sigma if sigma > 0 else float("nan")
        out.append(
            {
                "name": mine["name"],
                "unit": mine["unit"],
                "a": mine["value"],
                "b": other["value"],
                "sigma_a": mine.get("sigma"),
                "sigma_b": other.get("sigma"),
                "sigmas": sigmas,
                "flagged": bool(sigmas > CHANGE_SIGMAS),
            }
        )
    return sorted(out, key=lambda p: -np.nan_to_num(p["sigmas"]))
