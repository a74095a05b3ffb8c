"""``report``: an HTML accuracy report (PNG plots, tables) of a model on a test bag, opening with a summary
and a PASS/FAIL verdict against the tolerance the user gives."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from hybrid_kinematics_ros.calibration.fit import load_stations
from hybrid_kinematics_ros.calibration.report import write_report
from hybrid_kinematics_ros.calibration.summary import DataSource, Tolerance
from hybrid_kinematics_ros.io.errors import DataError
from hybrid_kinematics_ros.model.hybrid import HybridModel
from hybrid_kinematics_ros.model.referencing import to_base_frame


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("report", help="write an HTML accuracy report of a model on a test bag")
    p.add_argument("--model", required=True, type=Path, help="model directory")
    p.add_argument("--bag", nargs="+", required=True, help="test pairs bag(s)")
    p.add_argument("--out", type=Path, default=Path("report"), help="folder for index.html and the PNGs")
    p.add_argument("--curve", type=Path, help="data-amount curve JSON (bench/bench_parametric.py writes one)")
    p.add_argument(
        "--tolerance-mm",
        type=_positive,
        help="position tolerance (mm): the summary's verdict is PASS when 95 %% of the test poses lie within it",
    )
    p.add_argument(
        "--tolerance-deg",
        type=_positive,
        help="orientation tolerance (deg), checked with --tolerance-mm on the same poses",
    )
    p.set_defaults(run=run)


def _positive(text: str) -> float:
    value = float(text)
    if not value > 0:  # also refuses nan
        raise argparse.ArgumentTypeError(f"a tolerance must be above zero, not {text}")
    return value


def run(args: argparse.Namespace) -> int:
    if args.tolerance_deg is not None and args.tolerance_mm is None:
        raise DataError("--tolerance-deg needs --tolerance-mm: the verdict is on position, and orientation beside it")
    model = HybridModel.load(args.model)
    stations = load_stations(args.bag, model.chain)
    pairs = to_base_frame(stations, model.chain, model.referencings)
    curve = None
    if args.curve:
        try:
            curve = json.loads(args.curve.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise DataError(f"{args.curve}: not a readable curve JSON ({exc})") from None
    source = DataSource([str(b) for b in args.bag], [p.frame_id for p in stations])
    tolerance = Tolerance(args.tolerance_mm, args.tolerance_deg)
    page, summary = write_report(model, pairs, args.out, source, curve, tolerance)
    if summary["verdict"] is not None:
        print(summary["verdict"]["line"])
    print(f"wrote {page}")
    return 0
