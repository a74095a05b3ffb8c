"""A bound on the error of each answer: how far the robot may really be from what the model says.

For each configuration the bound is ``quantile · √(1 + (d / length)²)``, in m (position) or rad
(orientation), where ``d`` is the distance to the nearest training configuration in joint space, each
joint's move weighed by its lever arm (the typical distance from its axis to the tip, m per rad) and taken
the short way round (:func:`embed`): a metre of ``d`` moves the tip about a metre, and a wrist that turns
or a joint one turn away counts for what it changes, not for its radians.
Near the data it is the error that ``level`` of the validation pairs stay under; it grows where the model
extrapolates, at the rate the calibration measured (:mod:`calibration.bounds` holds out whole regions of
joint space from the stage and watches its error grow with the distance). ``quantile`` is split conformal:
about ``level`` of errors on data like the validation blocks lie under their bounds by construction.

The bound is a property of the model directory (``model.json``'s ``bounds`` section); a model without one
(trained before, or without stored training configurations) gives none.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from hybrid_kinematics_ros.model.errors import ModelError


def growth(distance: np.ndarray, length: float) -> np.ndarray:
    """``√(1 + (d / length)²)``: how much a bound has grown at ``distance`` from the data."""
    return np.sqrt(1.0 + (np.asarray(distance, dtype=float) / length) ** 2)


@dataclass(frozen=True)
class ErrorBound:
    """One kind's bound: ``quantile · growth(d, length)``."""

    quantile: float  # m or rad: the bound on the data (d = 0)
    length: float  # m: the distance (:func:`embed`) at which the bound has grown by √2

    def __call__(self, distance: np.ndarray) -> np.ndarray:
        return self.quantile * growth(distance, self.length)


@dataclass(frozen=True)
class Bounds:
    level: float  # the share of errors meant to lie under their bounds
    lever_arms: np.ndarray  # (n,) m per rad (per m for a prismatic joint: 1): the distance's weights
    position: ErrorBound  # m
    orientation: ErrorBound | None  # rad; None for a position-only model
    figures: dict[str, Any]  # how they were calibrated (model.json, the report)

    @classmethod
    def from_manifest(cls, section: dict[str, Any]) -> Bounds:
        try:
            pos = section["position"]
            ori = section.get("orientation")
            return cls(
                level=float(section["level"]),
                lever_arms=np.asarray(section["lever_arms_m"], dtype=float),
                position=ErrorBound(float(pos["quantile_m"]), float(pos["length_m"])),
                orientation=None if ori is None else ErrorBound(float(ori["quantile_rad"]), float(ori["length_m"])),
                figures=dict(section.get("figures", {})),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelError(f"model.json: the 'bounds' section is malformed ({exc}); retrain the model") from exc

    def manifest(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "level": self.level,
            "lever_arms_m": self.lever_arms.tolist(),
            "position": {"quantile_m": self.position.quantile, "length_m": self.position.length},
        }
        if self.orientation is not None:
            out["orientation"] = {"quantile_rad": self.orientation.quantile, "length_m": self.orientation.length}
        return out | {"figures": self.figures}

    def of(self, distance: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Position bounds (m) and orientation bounds (rad, or None) at distances ``(B,)`` (:func:`embed`)."""
        return self.position(distance), None if self.orientation is None else self.orientation(distance)


COLUMNS = ("position_bound_mm", "orientation_bound_deg")  # the bounds' names in the units users read


def in_report_units(bounds: tuple[np.ndarray, np.ndarray | None]) -> dict[str, np.ndarray]:
    """:meth:`HybridModel.error_bounds`'s answer (m, rad) by column name of :data:`COLUMNS`, in mm and
    degrees (no orientation column for a position-only model)."""
    position, orientation = bounds
    out = {COLUMNS[0]: 1e3 * position}
    if orientation is not None:
        out[COLUMNS[1]] = np.degrees(orientation)
    return out


def embed(q: np.ndarray, lever_arms: np.ndarray, revolute: np.ndarray) -> np.ndarray:
    """``(B, 2n)``: configurations as points whose Euclidean distance is the bound's: a revolute joint on a
    circle of its lever arm's radius (a move of Δq counts ``2 r sin(Δq / 2)``, about ``r Δq``, and a whole
    turn nothing), a prismatic joint on a line."""
    q = np.atleast_2d(np.asarray(q, dtype=float))
    rev = np.asarray(revolute, dtype=bool)
    first = np.where(rev, lever_arms * np.cos(q), q)
    second = np.where(rev, lever_arms * np.sin(q), 0.0)
    return np.concatenate([first, second], axis=1)


class Distance:
    """The distance (:func:`embed`) from configurations to the nearest of ``coverage``, by a k-d tree."""

    def __init__(self, coverage: np.ndarray, lever_arms: np.ndarray, revolute: np.ndarray) -> None:
        self.lever_arms = np.asarray(lever_arms, dtype=float)
        self.revolute = np.asarray(revolute, dtype=bool)
        self.tree = cKDTree(embed(coverage, self.lever_arms, self.revolute))

    def __call__(self, q: np.ndarray) -> np.ndarray:
        return self.tree.query(embed(q, self.lever_arms, self.revolute))[0]
