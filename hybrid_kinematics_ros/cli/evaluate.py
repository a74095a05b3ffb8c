"""``evaluate``: error statistics of the analytic and hybrid models on a pairs bag, as JSON and plots."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from hybrid_kinematics_ros.calibration.evaluate import evaluate, plot_distributions, pose_errors_of
from hybrid_kinematics_ros.calibration.fit import load_pairs
from hybrid_kinematics_ros.cli.common import add_coverage_arg
from hybrid_kinematics_ros.model.hybrid import HybridModel


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("evaluate", help="analytic against hybrid errors (mm, deg) on a pairs bag")
    p.add_argument("--model", required=True, type=Path, help="model directory")
    p.add_argument("--bag", nargs="+", required=True, help="pairs bag(s) to test on")
    p.add_argument("--json", type=Path, help="write the statistics here")
    p.add_argument("--plots", type=Path, help="write the error-distribution PNGs into this folder")
    add_coverage_arg(p)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    model = HybridModel.load(args.model)
    if args.coverage_radius is not None:  # evaluate the model as served with it: no nets beyond the radius
        model = model.with_coverage_radius(args.coverage_radius).with_range_policy("parametric")
    pairs = load_pairs(args.bag, model.chain, referencings=model.referencings)
    errors = pose_errors_of(model, pairs)  # for the statistics and the plots alike
    report = {"model": str(args.model), "bags": [str(b) for b in args.bag], **evaluate(model, pairs, errors)}
    if pairs.dropped:
        report["dropped"] = dict(pairs.dropped)
    if args.plots:
        report["plots"] = [str(p) for p in plot_distributions(model, pairs, args.plots, errors)]
    text = json.dumps(report, indent=2)
    if args.json:
        args.json.write_text(text + "\n")
    print(text)
    return 0
