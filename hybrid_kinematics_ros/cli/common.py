"""Helpers shared by the subcommands: choosing the robot, reading and writing CSV files."""

from __future__ import annotations

import argparse
import csv
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from hybrid_kinematics_ros.io.errors import DataError
from hybrid_kinematics_ros.kinematics.chain import Chain, chain_from_urdf
from hybrid_kinematics_ros.kinematics.robot_config import RobotConfig, load_robot_config
from hybrid_kinematics_ros.model import range_policy
from hybrid_kinematics_ros.model.bounds import COLUMNS, in_report_units

if TYPE_CHECKING:  # the model (and torch) only for the commands that load one: the others start sooner
    from hybrid_kinematics_ros.model.hybrid import HybridModel

POSE_COLUMNS = ("x", "y", "z", "qx", "qy", "qz", "qw")
UR_ROBOT = "ur10"  # the robot config --ur-kinematics alone stands on: the embedded UR10's inertials and limits


def add_robot_args(p: argparse.ArgumentParser, required: bool = True) -> None:
    """``--robot``, ``--urdf`` (with ``--base-link`` and ``--tip-link``) and ``--ur-kinematics``. Where
    ``required``, the help says that one of them is needed and :func:`chain_from_args` refuses none: argparse's
    groups cannot require one of three of which ``--ur-kinematics`` may go with ``--robot``."""
    group = p.add_mutually_exclusive_group()
    needed = "; this command needs --robot, --urdf or --ur-kinematics" if required else ""
    group.add_argument("--robot", help=f"robot config YAML, or an embedded robot: ur10, rx160, kr16{needed}")
    group.add_argument("--urdf", help="URDF file (with --base-link and --tip-link)")
    p.add_argument("--base-link", help="base link of the chain (with --urdf)")
    p.add_argument("--tip-link", help="tip link of the chain (with --urdf)")
    p.add_argument(
        "--ur-kinematics",
        metavar="FILE",
        help="a UR's kinematics file (ur_calibration's extract of the controller's calibration, or a model's "
        "default in config/ur_kinematics/): the chain is the URDF ur_description builds from it, base_link to "
        "tool0; the inertials, limits, working range, payload, gravity and tool come from --robot (a UR's "
        "config), else from the embedded ur10",
    )


def add_payload_args(p: argparse.ArgumentParser) -> None:
    """The payload and gravity the joints' torques come from, for a robot given by ``--urdf``."""
    p.add_argument("--payload-mass", type=float, help="kg, with --urdf (a --robot config has its own)")
    p.add_argument("--payload-com", type=float, nargs=3, metavar=("X", "Y", "Z"), help="m, in the tip frame")
    p.add_argument(
        "--gravity",
        type=float,
        nargs=3,
        metavar=("X", "Y", "Z"),
        help="m/s² in the base frame, with --urdf (default 0 0 -9.81, a floor mount; a --robot config has its own)",
    )


def add_coverage_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--coverage-radius",
        type=float,
        metavar="RAD",
        help="the calibrated range is where a training configuration lies within this distance (joint space, "
        "rad), instead of the trained joint ranges; `evaluate` suggests one",
    )


def add_range_args(p: argparse.ArgumentParser) -> None:
    """``--out-of-range`` and ``--coverage-radius``: what the model does outside its calibrated range."""
    p.add_argument(
        "--out-of-range",
        choices=tuple(range_policy.RANGE_POLICIES),
        default="warn",
        help=f"outside the calibrated range: {range_policy.described()}",
    )
    add_coverage_arg(p)


def with_range_args(model: HybridModel, args: argparse.Namespace) -> HybridModel:
    """``model`` serving outside its calibrated range as ``--out-of-range`` and ``--coverage-radius`` say."""
    return model.with_range_policy(args.out_of_range).with_coverage_radius(args.coverage_radius)


def robot_given(args: argparse.Namespace) -> bool:
    """Whether the command line names a robot (``--robot``, ``--urdf`` or ``--ur-kinematics``)."""
    return bool(args.robot or args.urdf or getattr(args, "ur_kinematics", None))


def robot_config_from_args(args: argparse.Namespace) -> RobotConfig | None:
    """The robot config of ``--robot`` (the embedded ur10's for ``--ur-kinematics`` alone), its chain built from
    ``--ur-kinematics`` when given; None for ``--urdf``."""
    ur_kinematics = getattr(args, "ur_kinematics", None)
    if ur_kinematics and args.urdf:
        raise DataError(
            "--ur-kinematics builds the URDF itself: give it alone or with --robot (a UR's config), not with --urdf"
        )
    if not (args.robot or ur_kinematics):
        return None
    return load_robot_config(args.robot or UR_ROBOT, ur_kinematics=ur_kinematics)


def chain_from_args(args: argparse.Namespace) -> Chain:
    config = robot_config_from_args(args)
    if config is not None:
        return config.chain
    if not args.urdf:
        raise DataError("give the robot: --robot, --urdf (with --base-link and --tip-link) or --ur-kinematics")
    if not args.base_link or not args.tip_link:
        raise DataError("--urdf needs --base-link and --tip-link")
    return chain_from_urdf(Path(args.urdf), args.base_link, args.tip_link)


def gravity_from_args(args: argparse.Namespace) -> np.ndarray | None:
    """Gravity in the base frame (m/s²): the robot config's (a wall or ceiling mount says so there), else
    ``--gravity``, else None (a floor mount)."""
    config = robot_config_from_args(args)
    if config is not None:
        return config.gravity
    return None if getattr(args, "gravity", None) is None else np.asarray(args.gravity, dtype=float)


def payload_from_args(args: argparse.Namespace) -> tuple[float, np.ndarray]:
    """Payload mass (kg) and centre of mass (m, tip frame): the robot config's, else ``--payload-*``."""
    config = robot_config_from_args(args)
    if config is not None:
        return config.payload_mass, config.payload_com
    com = np.zeros(3) if args.payload_com is None else np.asarray(args.payload_com, dtype=float)
    return float(args.payload_mass or 0.0), com


def bound_names(model: HybridModel, args: argparse.Namespace) -> list[str]:
    """The CSV columns of the answers' error bounds (``--bounds``); a user error when the answers carry none
    (``--analytic``, or a model without bounds)."""
    if args.analytic or model.bounds is None:
        why = "--analytic answers carry none" if args.analytic else f"model {args.model or '(none)'} carries none"
        raise DataError(f"--bounds: {why}; give a model trained with this version, without --analytic")
    return list(COLUMNS[: 1 if model.bounds.orientation is None else 2])


def bound_columns(model: HybridModel, q: np.ndarray) -> np.ndarray:
    """``(B, k)``: the error bounds of the model's answers at ``q (B, n)``, in the columns of
    :func:`bound_names` (mm, degrees)."""
    return np.column_stack(list(in_report_units(model.error_bounds(q)).values()))


def read_csv(path: Path, columns: tuple[str, ...] | None = None) -> tuple[list[str], np.ndarray]:
    """Header and float rows of a CSV; ``columns`` picks and orders them. Errors name the file, row and column."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path} does not exist")
    with path.open(newline="") as f:
        rows = list(csv.reader(f))
    if not rows:
        raise DataError(f"{path} is empty; expected a header line")
    header = [h.strip() for h in rows[0]]
    if columns is not None:
        missing = [c for c in columns if c not in header]
        if missing:
            raise DataError(f"{path}: missing column(s) {', '.join(missing)} (header: {','.join(header)})")
        index = [header.index(c) for c in columns]
    else:
        index = list(range(len(header)))
    values = np.empty((len(rows) - 1, len(index)))
    for r, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise DataError(f"{path}: line {r} has {len(row)} fields, the header has {len(header)}")
        for c, i in enumerate(index):
            try:
                values[r - 2, c] = float(row[i])
            except ValueError:
                raise DataError(f"{path}: line {r}, column '{header[i]}': '{row[i]}' is not a number") from None
    if not np.all(np.isfinite(values)):
        r = int(np.argwhere(~np.isfinite(values))[0][0]) + 2
        raise DataError(f"{path}: line {r} has a NaN or infinite value")
    return [header[i] for i in index], values


def write_csv(path: Path, header: list[str], rows: np.ndarray | list) -> None:
    with Path(path).open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(header)
        for row in rows:
            writer.writerow([repr(float(v)) if isinstance(v, float | np.floating) else v for v in row])
