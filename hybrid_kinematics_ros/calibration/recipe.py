"""The recipe: everything a calibration is told or chooses besides its pairs, as one value.

``train`` builds it from its flags (or reads an earlier model's with ``--recipe``), :func:`~hybrid_kinematics_ros.
calibration.fit.fit` follows it, and ``model.json`` records it under ``recipe`` so that a model says how it was
made and the same recipe can be run again on new pairs.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from hybrid_kinematics_ros.calibration import train
from hybrid_kinematics_ros.calibration.errors import CalibrationError

CAPACITY_SETTINGS = (
    "elastic",
    "harmonics",
    "harmonic_prior",
    "map_step",
    "map_smoothness",
    "orientation_length",
    "approach",
)


@dataclass(frozen=True)
class Recipe:
    """How to calibrate: the nets' preset and budget, the stage and its capacity, the load and the conditions.

    ``capacity`` holds the stage's settings that are given (names in :data:`CAPACITY_SETTINGS`); with
    ``choose_capacity`` the others are chosen from the pairs by cross-validation, without it they take
    the stage's defaults. ``conditions`` are channels the nets always take; ``offered`` are channels each
    net takes only where its validation errors show their worth (None: every varied channel the pairs carry,
    unless ``conditions`` names some). ``shared_targets`` groups tracker frames that saw one target.
    ``drop_outliers``: the training pairs the stage leaves far off (its outliers) are left out, and the
    referencing, the stage and the nets fitted without them; otherwise they stay in, down-weighted.
    """

    preset: train.Preset = field(default_factory=lambda: train.PRESETS["fast"])
    max_minutes: float = 5.0  # wall-clock budget for the nets, trained side by side
    seed: int = 0
    arch: Mapping[str, str] = field(default_factory=dict)  # net kind -> architecture(s), else the preset's
    parametric: bool = True  # identify the elasto-geometric stage before the nets
    capacity: Mapping[str, Any] = field(default_factory=dict)
    choose_capacity: bool = True
    payload_mass: float = 0.0  # kg
    payload_com: tuple[float, float, float] = (0.0, 0.0, 0.0)  # m, in the tip frame
    gravity: tuple[float, float, float] | None = None  # m/s² in the base frame; None: a floor mount
    conditions: tuple[str, ...] = ()
    offered: tuple[str, ...] | None = None
    shared_targets: tuple[tuple[str, ...], ...] = ()
    drop_outliers: bool = True

    def __post_init__(self) -> None:
        unknown = sorted(set(self.capacity) - set(CAPACITY_SETTINGS))
        if unknown:
            raise CalibrationError(
                f"recipe: unknown capacity settings {unknown}; choose from {list(CAPACITY_SETTINGS)}"
            )
        given = {k: v for k, v in self.capacity.items() if v is not None}
        object.__setattr__(self, "capacity", given)
        object.__setattr__(self, "payload_com", tuple(float(c) for c in self.payload_com))
        if self.gravity is not None:
            object.__setattr__(self, "gravity", tuple(float(g) for g in self.gravity))
        object.__setattr__(self, "conditions", tuple(self.conditions))
        if self.offered is not None:
            object.__setattr__(self, "offered", tuple(self.offered))
        object.__setattr__(self, "shared_targets", tuple(tuple(group) for group in self.shared_targets))

    @property
    def payload(self) -> tuple[float, np.ndarray]:
        return self.payload_mass, np.array(self.payload_com)

    @property
    def gravity_vector(self) -> np.ndarray | None:
        return None if self.gravity is None else np.array(self.gravity)

    def manifest(self) -> dict[str, Any]:
        """The recipe as ``model.json`` stores it (JSON types only)."""
        out = asdict(self)
        out["arch"] = dict(self.arch)
        out["capacity"] = dict(self.capacity)
        return json.loads(json.dumps(out))

    @classmethod
    def from_manifest(cls, section: Mapping[str, Any], where: str = "recipe") -> Recipe:
        """A recipe from :meth:`manifest`'s dict; unknown or malformed fields name ``where``."""
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(section) - names)
        if unknown:
            raise CalibrationError(f"{where}: unknown recipe fields {unknown}")
        values = dict(section)
        try:
            if "preset" in values:
                values["preset"] = train.Preset(**values["preset"])
            return cls(**values)
        except TypeError as exc:
            raise CalibrationError(f"{where}: a malformed recipe ({exc})") from exc

    @classmethod
    def read(cls, path: Path) -> Recipe:
        """The recipe of a model directory or of its ``model.json`` (or a JSON file holding one recipe)."""
        file = path / "model.json" if path.is_dir() else path
        try:
            data = json.loads(file.read_text())
        except (OSError, ValueError) as exc:
            raise CalibrationError(f"{file}: cannot read a recipe ({exc})") from exc
        section = data.get("recipe", data) if isinstance(data, dict) else None
        if not isinstance(section, dict) or ("preset" not in section and "recipe" not in data):
            raise CalibrationError(f"{file}: no recipe in it (a model.json written by train has one)")
        return cls.from_manifest(section, str(file))
