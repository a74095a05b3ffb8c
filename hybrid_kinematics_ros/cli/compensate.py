"""``compensate``: a joint trajectory planned on the URDF (CSV) to the one the calibrated robot must be sent
so that it follows the planned path (the ``~/compensate_trajectory`` service, offline)."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from hybrid_kinematics_ros.cli.common import add_range_args, read_csv, with_range_args, write_csv
from hybrid_kinematics_ros.ik.compensate import MAX_JOINT_CORRECTION_RAD, compensate
from hybrid_kinematics_ros.ik.errors import IKError
from hybrid_kinematics_ros.ik.solver import IKOptions, IKSolver
from hybrid_kinematics_ros.io.errors import DataError
from hybrid_kinematics_ros.model.hybrid import HybridModel

TIME_COLUMN = "time_from_start"


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("compensate", help="correct a joint trajectory planned on the URDF (the robot follows the plan)")
    p.add_argument("--model", required=True, type=Path, help="model directory")
    p.add_argument(
        "--joints",
        required=True,
        type=Path,
        help=f"plan CSV: {TIME_COLUMN} (s) and one column per joint (rad); optional <joint>_velocity, "
        "<joint>_acceleration columns",
    )
    p.add_argument("--out", required=True, type=Path, help="corrected trajectory CSV to write (same columns)")
    p.add_argument("--tolerance-mm", type=float, default=1e-6, help="hybrid FK vs the plan's URDF pose (mm)")
    p.add_argument("--tolerance-deg", type=float, default=1e-6, help="orientation tolerance (deg)")
    p.add_argument("--max-correction", type=float, default=MAX_JOINT_CORRECTION_RAD, metavar="RAD")
    add_range_args(p)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    model = HybridModel.load(args.model)
    model = with_range_args(model, args)
    names = list(model.joint_names)
    header, _ = read_csv(args.joints)
    _, values = read_csv(args.joints, (TIME_COLUMN, *names))
    t, q = values[:, 0], values[:, 1:]
    rates = {}
    for kind in ("velocity", "acceleration"):
        columns = [f"{n}_{kind}" for n in names]
        present = [c for c in columns if c in header]
        if present and len(present) != len(columns):
            missing = ", ".join(c for c in columns if c not in header)
            raise DataError(f"{args.joints}: has some {kind} columns but not {missing}")
        rates[kind] = read_csv(args.joints, tuple(columns))[1] if present else None
    options = IKOptions(
        position_tolerance_mm=args.tolerance_mm,
        orientation_tolerance_deg=args.tolerance_deg,
        require_calibrated_range=args.out_of_range == "refuse",
    )
    result = compensate(
        IKSolver(model, options).warm_up(),
        q,
        t,
        rates["velocity"],
        rates["acceleration"],
        require_calibrated_range=args.out_of_range == "refuse",
        max_joint_correction_rad=args.max_correction,
    )
    if not result.success:
        raise IKError(f"{args.joints}: {result.message} (line {result.failed_index + 2}); nothing written")
    out_header = [TIME_COLUMN, *names]
    blocks = [t[:, None], result.positions]
    for kind, arr in (("velocity", result.velocities), ("acceleration", result.accelerations)):
        if arr is not None:
            out_header += [f"{n}_{kind}" for n in names]
            blocks.append(arr)
    out_header += ["position_error_mm", "orientation_error_deg", "in_calibrated_range"]
    errors = [result.position_error_mm, result.orientation_error_deg, result.in_calibrated_range.astype(float)]
    write_csv(args.out, out_header, np.hstack([*blocks, np.column_stack(errors)]))  # in range: 1.0, else 0.0
    outside = int(np.sum(~result.in_calibrated_range)) if model.nets else 0
    print(
        f"wrote {len(q)} corrected points to {args.out}: largest joint correction "
        f"{np.abs(result.positions - q).max():.6f} rad, hybrid FK within {result.position_error_mm.max():.2e} mm and "
        f"{result.orientation_error_deg.max():.2e} deg of the plan"
        + (f"; {outside} outside the calibrated range" if outside else "")
    )
    return 0
