"""A bound on the error of each answer: how far the robot may really be from what the model says.

For each configuration ``q`` the bound is ``quantile · scale(q) + ‖rates ⊙ x‖``, in m (position) or rad
(orientation), where ``x`` is how far each joint lies beyond the range the model was trained on (rad, the
short way round for a revolute joint; m for a prismatic one; 0 inside, :func:`excess`) and ``rates`` how fast
the error grows per unit of each joint's excess. Inside the trained range it is the error that ``level`` of
the validation pairs stay under, scaled by how hard the configuration is: split conformal on the validation
errors divided by their scale (normalised conformal prediction), so about ``level`` of errors on data like
the validation blocks lie under their bounds by construction, whatever the scale. The **scale** is
:class:`Scale`: how large the stage's errors are on the training pairs around ``q``, relative to their
median (1 at a typical configuration), a smooth function of the joints. Beyond the range the bound grows at
the rates the calibration measured
(:mod:`calibration.bounds` holds each end of each joint's range out of the stage's fit and watches its
error grow as it extrapolates): a shoulder that extrapolates costs more than a flange that turns further.

Why the trained range and not the distance to the nearest training configuration: in six dimensions the
training data leave gaps everywhere, and a model interpolates across them as well as it does on the data;
beyond the end of a joint's range it extrapolates, and there its error grows (a virtual UR10 trained with
its shoulder in one radian errs an order of magnitude more half a radian beyond it than inside, where gaps at
the same nearest-neighbour distance show no growth).

The bound is a property of the model directory (``model.json``'s ``bounds`` section); a model without one
(an older model directory) gives none.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from hybrid_kinematics_ros.model.errors import ModelError

DISTANCE = "joint_range_excess"  # what the section's rates are per (a section without it is of an older kind)


def excess(q: np.ndarray, lower: np.ndarray, upper: np.ndarray, revolute: np.ndarray) -> np.ndarray:
    """``(B, n)``: how far each joint of ``q (B, n)`` lies beyond ``[lower, upper]``: 0 inside; a revolute
    joint whose range spans less than a turn the short way round to the nearer end (a turn or more: 0); a
    prismatic joint the distance to the nearer end."""
    q = np.atleast_2d(np.asarray(q, dtype=float))
    width = upper - lower
    straight = np.maximum(0.0, np.maximum(lower - q, q - upper))
    turn = np.mod(q - lower, 2.0 * np.pi)  # from the lower end upwards, within one turn
    around = np.where(turn <= width, 0.0, np.minimum(turn - width, 2.0 * np.pi - turn))
    return np.where(revolute, np.where(width >= 2.0 * np.pi, 0.0, around), straight)


def features(q: np.ndarray, revolute: np.ndarray) -> np.ndarray:
    """``(B, 1 + 2n)``: what :class:`Scale` is linear in: a constant, and each joint's sine and cosine (a
    prismatic joint: its value and its square), so the scale is periodic where the joints are."""
    q = np.atleast_2d(np.asarray(q, dtype=float))
    first = np.where(revolute, np.sin(q), q)
    second = np.where(revolute, np.cos(q), q * q)
    return np.column_stack([np.ones(len(q)), first, second])


def features_one(q: list[float], revolute: list[bool]) -> list[float]:
    """:func:`features` of one configuration, in Python floats: on a service's hot path numpy's overhead on
    ``(1, n)`` arrays is most of a bound's cost."""
    first = [math.sin(v) if r else v for v, r in zip(q, revolute, strict=True)]
    second = [math.cos(v) if r else v * v for v, r in zip(q, revolute, strict=True)]
    return [1.0, *first, *second]


@dataclass(frozen=True)
class Scale:
    """How hard a configuration is: ``exp(features(q) · weights)``, clipped to ``[lower, upper]`` (the range it
    takes on the training pairs: the fit is not trusted to extrapolate), 1 at a typical configuration."""

    weights: np.ndarray  # (1 + 2n,)
    lower: float
    upper: float

    def __call__(self, q: np.ndarray, revolute: np.ndarray) -> np.ndarray:
        return self.at(features(q, revolute))

    def at(self, f: np.ndarray) -> np.ndarray:
        """The scale at configurations whose :func:`features` are ``f (B, 1 + 2n)``."""
        return np.clip(np.exp(f @ self.weights), self.lower, self.upper)

    def at_one(self, f: list[float]) -> float:
        """:meth:`at` of one configuration's :func:`features_one`."""
        value = math.exp(sum(a * w for a, w in zip(f, self.weights.tolist(), strict=True)))
        return min(max(value, self.lower), self.upper)

    def manifest(self) -> dict[str, Any]:
        return {"features": "sin_cos", "weights": self.weights.tolist(), "clip": [self.lower, self.upper]}

    @classmethod
    def from_manifest(cls, section: dict[str, Any] | None) -> Scale | None:
        if section is None:
            return None
        lower, upper = section["clip"]
        return cls(np.asarray(section["weights"], dtype=float), float(lower), float(upper))


@dataclass(frozen=True)
class ErrorBound:
    """One kind's bound: ``quantile · scale(q) + ‖rates ⊙ excess‖``; the parametric stage's alone (without
    the nets) has its own quantile, ``stage_quantile``, and the same scale and rates."""

    quantile: float  # m or rad: the bound inside the trained range at a typical configuration (scale 1)
    rates: np.ndarray  # (n,) m or rad of error per rad (per m, prismatic) of each joint's excess
    scale: Scale | None = None  # None: the same everywhere (an older section without one)
    stage_quantile: float | None = None  # the stage alone's ``quantile``; None: an older section without it

    def __call__(self, q: np.ndarray, x: np.ndarray, revolute: np.ndarray) -> np.ndarray:
        return self.at(features(q, revolute), x)

    def at(self, f: np.ndarray, x: np.ndarray, stage: bool = False) -> np.ndarray:
        """The bound at configurations whose :func:`features` are ``f (B, 1 + 2n)`` and excess ``x (B, n)``;
        the stage alone's with ``stage``."""
        quantile = self.stage_quantile if stage else self.quantile
        if quantile is None:
            raise ModelError("the model's bounds carry no bound of its parametric stage alone; retrain the model")
        inside = quantile if self.scale is None else quantile * self.scale.at(f)
        x = np.atleast_2d(x)
        # inside the trained range (a service's usual call) the growth is zero: skip its norm
        return inside + (np.linalg.norm(x * self.rates, axis=1) if x.any() else np.zeros(len(x)))

    def inside_one(self, f: list[float]) -> float:
        """:meth:`at` of one configuration inside the trained range (no excess: no growth), from its
        :func:`features_one`."""
        return self.quantile if self.scale is None else self.quantile * self.scale.at_one(f)

    def manifest(self, unit: str) -> dict[str, Any]:
        out = {f"quantile_{unit}": self.quantile, f"growth_{unit}_per_rad": self.rates.tolist()}
        if self.stage_quantile is not None:
            out[f"stage_quantile_{unit}"] = self.stage_quantile
        return out if self.scale is None else out | {"scale": self.scale.manifest()}

    @classmethod
    def from_manifest(cls, section: dict[str, Any], unit: str) -> ErrorBound:
        stage = section.get(f"stage_quantile_{unit}")
        return cls(
            float(section[f"quantile_{unit}"]),
            np.asarray(section[f"growth_{unit}_per_rad"], dtype=float),
            Scale.from_manifest(section.get("scale")),
            None if stage is None else float(stage),
        )


@dataclass(frozen=True)
class Bounds:
    level: float  # the share of errors meant to lie under their bounds
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
                position=ErrorBound.from_manifest(pos, "m"),
                orientation=None if ori is None else ErrorBound.from_manifest(ori, "rad"),
                figures=dict(section.get("figures", {})),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelError(f"model.json: the 'bounds' section is malformed ({exc}); retrain the model") from exc

    def manifest(self) -> dict[str, Any]:
        out: dict[str, Any] = {"level": self.level, "distance": DISTANCE, "position": self.position.manifest("m")}
        if self.orientation is not None:
            out["orientation"] = self.orientation.manifest("rad")
        return out | {"figures": self.figures}

    @property
    def has_stage(self) -> bool:
        """True when the section carries the stage alone's bounds too (the ``bound`` range policy needs them)."""
        kinds = [k for k in (self.position, self.orientation) if k is not None]
        return all(k.stage_quantile is not None for k in kinds)

    def of(
        self, q: np.ndarray, x: np.ndarray, revolute: np.ndarray, stage: bool = False
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Position bounds (m) and orientation bounds (rad, or None) at configurations ``q (B, n)`` whose
        joints lie ``x (B, n)`` beyond the trained range (:func:`excess`); the stage alone's with ``stage``."""
        f = features(q, revolute)  # once for both kinds: half the bound's cost on the node's hot path
        orientation = None if self.orientation is None else self.orientation.at(f, x, stage)
        return self.position.at(f, x, stage), orientation

    def inside_one(self, q: list[float], revolute: list[bool]) -> tuple[float, float | None]:
        """:meth:`of` of one configuration inside the trained range, in Python floats (a service's usual
        call, several times faster than through :meth:`of`)."""
        f = features_one(q, revolute)
        orientation = None if self.orientation is None else self.orientation.inside_one(f)
        return self.position.inside_one(f), orientation


COLUMNS = ("position_bound_mm", "orientation_bound_deg")  # the bounds' names in the units users read


def in_report_units(bounds: tuple[np.ndarray, np.ndarray | None]) -> dict[str, np.ndarray]:
    """:meth:`HybridModel.error_bounds`'s answer (m, rad) by column name of :data:`COLUMNS`, in mm and
    degrees (no orientation column for a position-only model)."""
    position, orientation = bounds
    out = {COLUMNS[0]: 1e3 * position}
    if orientation is not None:
        out[COLUMNS[1]] = np.degrees(orientation)
    return out
