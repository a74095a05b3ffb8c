"""``export-urdf``: the calibrated geometry as a URDF, and how much accuracy that URDF alone keeps."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from hybrid_kinematics_ros.calibration.evaluate import error_stats, target_errors
from hybrid_kinematics_ros.calibration.export import export_urdf
from hybrid_kinematics_ros.calibration.fit import load_pairs
from hybrid_kinematics_ros.io.errors import DataError
from hybrid_kinematics_ros.kinematics import fk
from hybrid_kinematics_ros.kinematics.chain import chain_from_urdf
from hybrid_kinematics_ros.model.hybrid import HybridModel


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export-urdf", help="write the parametric stage's geometry as a URDF (for MoveIt and co.)")
    p.add_argument("--model", required=True, type=Path, help="model directory with a parametric stage")
    p.add_argument("--out", required=True, type=Path, help="URDF file to write")
    p.add_argument("--bag", nargs="+", help="pairs bag(s): report the URDF's accuracy against the full model")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    model = HybridModel.load(args.model)
    if args.out.exists():
        raise DataError(f"{args.out} exists already, not overwriting")
    text = export_urdf(model)
    args.out.write_text(text)
    report: dict = {"urdf": str(args.out)}
    if args.bag:
        pairs = load_pairs(args.bag, model.chain, referencings=model.referencings)
        exported = chain_from_urdf(text, model.chain.base_link, model.chain.tip_link).with_tool(model.chain.tool)
        for name, T in (
            ("nominal_urdf", model.fk(pairs.q, analytic=True)),
            ("exported_urdf", fk.fk(exported, pairs.q)),
            ("parametric", model.fk(pairs.q, nets=False)),
            ("hybrid", model.fk(pairs.q)),
        ):
            report[name] = error_stats(*target_errors(pairs, T))
    print(json.dumps(report, indent=2))
    return 0
