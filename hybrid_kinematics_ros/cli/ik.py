"""``ik``: poses CSV ``x,y,z,qx,qy,qz,qw`` (metres, base frame) to joint solutions through the hybrid model."""

from __future__ import annotations

import argparse
from pathlib import Path

from tqdm import tqdm

from hybrid_kinematics_ros.cli.common import POSE_COLUMNS, read_csv, write_csv
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
    solver = IKSolver(model, IKOptions(timeout_s=args.timeout_ms / 1e3))
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
            out_rows.append([i, 0, *([float("nan")] * model.chain.dof), float("nan"), float("nan"), "false"])
        for k, r in enumerate(results):
            out_rows.append([i, k, *r.q, r.position_error_mm, r.orientation_error_deg, "true"])
    header = ["pose_index", "solution", *model.joint_names, "position_error_mm", "orientation_error_deg", "success"]
    write_csv(args.out, header, out_rows)
    print(f"wrote {len(out_rows)} rows for {len(targets)} poses to {args.out}; {failed} without a solution")
    return 1 if failed else 0
