"""Robot config YAML: which URDF, which links, the working joint range, tool and payload.

Simulation settings (the ``truth`` and ``tracker`` sections) are kept as plain dicts here and read by
``simulation``, so that the kinematics core does not depend on the virtual cell.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from hybrid_kinematics_ros.kinematics.chain import Chain, chain_from_urdf
from hybrid_kinematics_ros.kinematics.elastic import GRAVITY
from hybrid_kinematics_ros.kinematics.errors import KinematicsError
from hybrid_kinematics_ros.kinematics.paths import config_dir, resolve_path
from hybrid_kinematics_ros.kinematics.ur_kinematics import chain_from_ur_kinematics, parent_frame

CONFIG_DIR = config_dir()  # the package share directory's config/ (see paths.py)


def transform_from_xyz_rpy(spec: dict[str, Any] | None, where: str) -> np.ndarray:
    """4x4 from ``{xyz: [..], rpy: [..]}`` (URDF convention: fixed-axis roll, pitch, yaw)."""
    t = np.eye(4)
    if not spec:
        return t
    try:
        t[:3, 3] = np.asarray(spec.get("xyz", [0, 0, 0]), dtype=float).reshape(3)
        rpy = np.asarray(spec.get("rpy", [0, 0, 0]), dtype=float).reshape(3)
        t[:3, :3] = Rotation.from_euler("xyz", rpy).as_matrix()
    except (ValueError, TypeError, AttributeError) as exc:
        raise KinematicsError(f"{where}: expected {{xyz: [x, y, z], rpy: [r, p, y]}}, got {spec!r}") from exc
    return t


@dataclass(frozen=True)
class RobotConfig:
    name: str
    path: Path
    urdf_path: Path
    base_link: str
    tip_link: str
    chain: Chain
    payload_mass: float = 0.0
    payload_com: np.ndarray = field(default_factory=lambda: np.zeros(3))
    gravity: np.ndarray = field(default_factory=lambda: GRAVITY.copy())  # m/s², base frame
    truth: dict[str, Any] = field(default_factory=dict)
    tracker: dict[str, Any] = field(default_factory=dict)


def resolve_robot(spec: str | Path) -> Path:
    """A config path (``package://`` too), or the name of an embedded robot (``ur10``, ``rx160``, ``kr16``)."""
    path = resolve_path(spec)
    if path.is_file():
        return path
    embedded = config_dir() / f"{spec}.yaml"
    if embedded.is_file():
        return embedded
    raise KinematicsError(f"robot config {spec} does not exist (embedded robots: ur10, rx160, kr16)")


def load_robot_config(spec: str | Path, ur_kinematics: str | Path | None = None) -> RobotConfig:
    """A robot config (a path, ``package://`` too, or an embedded robot's name) with its chain.

    With ``ur_kinematics`` (a UR kinematics file, see :mod:`~hybrid_kinematics_ros.kinematics.ur_kinematics`)
    the chain is the one ur_description builds from that file, with the config's URDF as the template of its
    inertials and limits; the config's tool, working range and payload apply to it as to its own URDF, and its
    gravity is turned into the built URDF's ``base_link`` (REP-103 aligned, a half turn about z from the base of
    the embedded UR10's URDF).
    """
    path = resolve_robot(spec)
    try:
        raw = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise KinematicsError(f"{path}: not valid YAML: {exc}") from exc
    if not isinstance(raw, dict):
        raise KinematicsError(f"{path}: expected a mapping at the top level")
    for key in ("urdf", "base_link", "tip_link"):
        if key not in raw:
            raise KinematicsError(f"{path}: missing field '{key}'")
    urdf_path = resolve_path(raw["urdf"], relative_to=path.parent).resolve()
    if not urdf_path.is_file():
        raise KinematicsError(f"{path}: field 'urdf': {urdf_path} does not exist")
    chain = chain_from_urdf(urdf_path, raw["base_link"], raw["tip_link"])
    base_turn = np.eye(3)
    if ur_kinematics is not None:
        template = chain
        chain = chain_from_ur_kinematics(ur_kinematics, urdf_path, raw["base_link"], raw["tip_link"])
        # both first joints hang from the UR's own base frame: the turn between the two URDFs' base links
        base_turn = (parent_frame(chain, 0) @ np.linalg.inv(parent_frame(template, 0)))[:3, :3]
    chain = chain.with_tool(transform_from_xyz_rpy(raw.get("tool"), f"{path}: field 'tool'"))
    limits = raw.get("joint_limits")
    if limits:
        lower = np.asarray(limits.get("lower", chain.lower), dtype=float)
        upper = np.asarray(limits.get("upper", chain.upper), dtype=float)
        if lower.shape != (chain.dof,) or upper.shape != (chain.dof,) or np.any(lower > upper):
            raise KinematicsError(
                f"{path}: field 'joint_limits' needs lower and upper lists of {chain.dof} values with lower <= upper"
            )
        chain = chain.with_limits(np.maximum(lower, chain.lower), np.minimum(upper, chain.upper))
    payload = raw.get("payload") or {}
    gravity = np.asarray(raw.get("gravity", GRAVITY), dtype=float)
    if gravity.shape != (3,) or not np.all(np.isfinite(gravity)):
        raise KinematicsError(f"{path}: field 'gravity' needs three numbers (m/s², in the base frame)")
    gravity = base_turn @ gravity + 0.0  # no negative zeros from the turn
    return RobotConfig(
        name=str(raw.get("name", path.stem)),
        path=path,
        urdf_path=urdf_path,
        base_link=raw["base_link"],
        tip_link=raw["tip_link"],
        chain=chain,
        payload_mass=float(payload.get("mass", 0.0)),
        payload_com=np.asarray(payload.get("com", [0.0, 0.0, 0.0]), dtype=float),
        gravity=gravity,
        truth=dict(raw.get("truth") or {}),
        tracker=dict(raw.get("tracker") or {}),
    )
