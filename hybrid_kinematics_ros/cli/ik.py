"""``ik``: poses CSV ``x,y,z,qx,qy,qz,qw`` (metres, base frame) to joint solutions through the hybrid model."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from tqdm import tqdm

from hybrid_kinematics_ros.cli.common import POSE_COLUMNS, bound_columns, bound_names, read_csv, write_csv
from hybrid_kinematics_ros.ik.solver import IKOptions, IKSolver
from hybrid_kinematics_ros.io.errors import DataError
from hybrid_kinematics_ros.kinematics.se3 import matrix_from_pose
from hybrid_kinematics_ros.model.hybrid import HybridModel


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("ik", help="inverse kinematics of a poses CSV through the hybrid model")
    p.add_argument("--model", required=True, type=Path, help="model directory")
    p.add_argument("--poses", required=True, type=Path, help="CSV with columns x,y,z,qx,qy,qz,qw (m, base frame)")
    p.add_argument("--out", required=True, type=Path, help="solutions CSV: one row per solution")
    p.add_argument("--seeds", type=Path, help="CSV of seed joints (header of joint names): one row, or one per pose")
    p.add_argument("--solutions", type=int, default=1, help="up to K distinct solutions per pose")
    p.add_argument("--analytic", action="store_true", help="solve on the uncorrected URDF model")
    p.add_argument("--timeout-ms", type=float, default=50.0, help="time budget per solution")
    p.add_argument(
        "--bounds",
        action="store_true",
        help="add each solution's error bounds (position_bound_mm, orientation_bound_deg)",
    )
    p.add_argument(
        "--rank-by-bound",
        action="store_true",
        help="with --solutions K: the solution the model knows best first (smallest position bound), not the "
        "nearest to the seed; implies --bounds",
    )
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    model = HybridModel.load(args.model)
    _, rows = read_csv(args.poses, POSE_COLUMNS)
    try:
        targets = matrix_from_pose(rows[:, :3], rows[:, 3:])
    except ValueError as exc:
        raise DataError(f"{args.poses}: {exc}") from exc
    seeds = None
    if args.seeds:
        _, seeds = read_csv(args.seeds, model.joint_names)
        if len(seeds) not in (1, len(targets)):
            raise DataError(f"{args.seeds}: {len(seeds)} seed rows; give one, or one per pose ({len(targets)})")
    if args.solutions < 1:
        raise DataError(f"--solutions must be at least 1, got {args.solutions}")
    bounded = args.bounds or args.rank_by_bound
    names = bound_names(model, args) if bounded else []
    solver = IKSolver(model, IKOptions(timeout_s=args.timeout_ms / 1e3)).warm_up()
    out_rows = []
    failed = 0
    for i, target in enumerate(tqdm(targets, desc="ik", unit="pose")):
        seed = None if seeds is None else seeds[0 if len(seeds) == 1 else i]
        if args.solutions == 1:
            results = [solver.solve(target, seed, analytic=args.analytic)]
        else:
            results = solver.solve_many(target, seed, args.solutions, analytic=args.analytic)
        results = [r for r in results if r.success]
        if not results:
            failed += 1
            nan = float("nan")
            out_rows.append([i, 0, *[nan] * (model.chain.dof + 2), "false", *[nan] * len(names)])
            continue
        q = np.array([r.q for r in results])
        bounds = bound_columns(model, q) if bounded else np.zeros((len(results), 0))
        order = np.argsort(bounds[:, 0], kind="stable") if args.rank_by_bound else range(len(results))
        for k, j in enumerate(order):
            r = results[j]
            out_rows.append([i, k, *r.q, r.position_error_mm, r.orientation_error_deg, "true", *bounds[j]])
    header = ["pose_index", "solution", *model.joint_names, "position_error_mm", "orientation_error_deg", "success"]
    header += names
    write_csv(args.out, header, out_rows)
    print(f"wrote {len(out_rows)} rows for {len(targets)} poses to {args.out}; {failed} without a solution")
    return 1 if failed else 0
