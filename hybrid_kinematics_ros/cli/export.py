"""``export``: the calibrated geometry as a URDF, a UR kinematics file or a DH table, and what it leaves behind."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from hybrid_kinematics_ros.calibration.export import FORMATS, Exported, export, held_out_errors
from hybrid_kinematics_ros.calibration.fit import load_stations
from hybrid_kinematics_ros.io.errors import DataError
from hybrid_kinematics_ros.model.hybrid import HybridModel

SERVE_THE_REST = (
    "the rest is served by the kinematics node (ros2 run hybrid_kinematics_ros kinematics_node --ros-args "
    "-p model_dir:=MODEL), or by `hybrid-kinematics compensate` for a trajectory"
)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="write the calibrated geometry as a URDF, a UR kinematics file or a DH table")
    add_export_args(p)
    p.add_argument("--format", required=True, choices=FORMATS, help="the file to write")
    p.add_argument(
        "--convention",
        choices=("standard", "modified"),
        default="standard",
        help="DH convention, with --format dh (default standard)",
    )
    p.set_defaults(run=run)


def add_export_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", required=True, type=Path, help="model directory with a parametric stage")
    p.add_argument("--out", required=True, type=Path, help="file to write")
    p.add_argument(
        "--bag", nargs="+", help="held-out pairs bag(s): the exported geometry's errors beside the full model's"
    )


def run(args: argparse.Namespace) -> int:
    model = HybridModel.load(args.model)
    return write(args, model, export(model, args.format, args.convention), args.format)


def write(args: argparse.Namespace, model: HybridModel, exported: Exported, form: str) -> int:
    """Write the file, print what it leaves behind and, with ``--bag``, how accurate it is beside the model."""
    if args.out.exists():
        raise DataError(f"{args.out} exists already, not overwriting")
    args.out.write_text(exported.text)
    report: dict[str, Any] = {form: str(args.out), "left_behind": list(exported.left)}
    if args.bag:
        report |= held_out_errors(model, exported, load_stations(args.bag, model.chain))
        exported_mm = report["exported"]["position_mm_mean"]
        print(
            f"{form}: {exported_mm:.4f} mm held out, against {report['hybrid']['position_mm_mean']:.4f} mm for the "
            f"full model ({report['nominal']['position_mm_mean']:.4f} mm uncalibrated); " + SERVE_THE_REST,
            file=sys.stderr,
        )
    else:
        print(f"{form}: pass --bag with held-out pairs to see its accuracy; " + SERVE_THE_REST, file=sys.stderr)
    print(json.dumps(report, indent=2))
    return 0
