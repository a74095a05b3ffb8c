"""``report``: an HTML accuracy report (PNG plots, tables) of a model on a test bag."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from hybrid_kinematics_ros.calibration.fit import load_pairs
from hybrid_kinematics_ros.calibration.report import write_report
from hybrid_kinematics_ros.io.errors import DataError
from hybrid_kinematics_ros.model.hybrid import HybridModel


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("report", help="write an HTML accuracy report of a model on a test bag")
    p.add_argument("--model", required=True, type=Path, help="model directory")
    p.add_argument("--bag", nargs="+", required=True, help="test pairs bag(s)")
    p.add_argument("--out", type=Path, default=Path("report"), help="folder for index.html and the PNGs")
    p.add_argument("--curve", type=Path, help="data-amount curve JSON (bench/bench_parametric.py writes one)")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    model = HybridModel.load(args.model)
    pairs = load_pairs(args.bag, model.chain, referencings=model.referencings)
    curve = None
    if args.curve:
        try:
            curve = json.loads(args.curve.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise DataError(f"{args.curve}: not a readable curve JSON ({exc})") from None
    page = write_report(model, pairs, args.out, [str(b) for b in args.bag], curve)
    print(f"wrote {page}")
    return 0
