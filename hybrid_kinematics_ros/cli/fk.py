"""``fk``: joints CSV (header of joint names) to poses CSV ``x,y,z,qx,qy,qz,qw`` in metres, base frame; with
``--bounds``, each pose's error bounds beside it (``position_bound_mm``, ``orientation_bound_deg``)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from hybrid_kinematics_ros.cli.common import (
    POSE_COLUMNS,
    add_range_args,
    add_robot_args,
    bound_columns,
    bound_names,
    chain_from_args,
    read_csv,
    with_range_args,
    write_csv,
)
from hybrid_kinematics_ros.kinematics.se3 import pose_from_matrix
from hybrid_kinematics_ros.model.hybrid import HybridModel
from hybrid_kinematics_ros.model.range_policy import OUTSIDE


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("fk", help="forward kinematics of a joints CSV (hybrid or analytic)")
    p.add_argument("--model", type=Path, help="model directory (else the analytic model of --robot or --urdf)")
    add_robot_args(p, required=False)
    p.add_argument("--joints", required=True, type=Path, help="CSV whose header names the joints (radians)")
    p.add_argument("--out", required=True, type=Path, help="poses CSV to write")
    p.add_argument("--analytic", action="store_true", help="uncorrected URDF kinematics")
    p.add_argument(
        "--bounds",
        action="store_true",
        help="add each pose's error bounds (mm, deg), under which the model's level (95 %%) of real errors lie",
    )
    add_range_args(p)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    model = HybridModel.load(args.model) if args.model else HybridModel.analytic_only(chain_from_args(args))
    model = with_range_args(model, args)
    _, q = read_csv(args.joints, model.joint_names)
    if not args.analytic:
        model.check_range(q)
    names = bound_names(model, args) if args.bounds else []
    T = model.fk(q, analytic=args.analytic)
    position, quat = pose_from_matrix(T)
    bounds = bound_columns(model, q) if names else np.zeros((len(q), 0))
    write_csv(args.out, [*POSE_COLUMNS, *names], np.hstack([position, quat, bounds]))
    outside = int(np.sum(~model.in_calibrated_range(q))) if model.nets and not args.analytic else 0
    print(f"wrote {len(q)} poses to {args.out}")
    if outside:
        print(
            f"warning: {outside} configuration(s) outside the calibrated range: {OUTSIDE[args.out_of_range]}",
            file=sys.stderr,
        )
    return 0
