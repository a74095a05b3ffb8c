"""``verify``: a check recording against a model: still calibrated or drifted, PASS or FAIL, and why."""

from __future__ import annotations

import argparse
import html
import json
from pathlib import Path

from hybrid_kinematics_ros.calibration.fit import load_stations
from hybrid_kinematics_ros.calibration.verify import Tolerance, verify
from hybrid_kinematics_ros.io.errors import DataError
from hybrid_kinematics_ros.model.hybrid import HybridModel


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "verify", help="check a model with a new recording, from any tracker station (exit 0 holds, 1 drifted or FAIL)"
    )
    p.add_argument("--model", required=True, type=Path, help="model directory")
    p.add_argument("--bag", required=True, nargs="+", help="the check's pairs bag(s) or raw recordings")
    p.add_argument("--tolerance-mm", type=float, help="PASS when 95 %% of the poses are within it")
    p.add_argument("--tolerance-deg", type=float, help="and within this orientation error (with --tolerance-mm)")
    p.add_argument(
        "--refit-target",
        action="store_true",
        help="the target was re-mounted: at a new station, place it from the check too (a moved tool is then not seen)",
    )
    p.add_argument("--json", type=Path, help="write the outcome as JSON here")
    p.add_argument("--out", type=Path, help="write an HTML page of the outcome into this folder")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    if args.tolerance_deg is not None and args.tolerance_mm is None:
        raise DataError("--tolerance-deg needs --tolerance-mm")
    model = HybridModel.load(args.model)
    tolerance = Tolerance(args.tolerance_mm, args.tolerance_deg)
    result = verify(model, load_stations(args.bag, model.chain), tolerance, refit_target=args.refit_target)
    lines = result.lines()
    print("\n".join(lines))
    if args.json:
        args.json.write_text(json.dumps(result.manifest(), indent=2))
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        items = "".join(f"<li>{html.escape(line)}</li>" for line in lines)
        stations = "".join(f"<li>{html.escape(f)}: {html.escape(h)}</li>" for f, h in result.stations.items())
        (args.out / "index.html").write_text(
            f"<!doctype html><html><head><meta charset='utf-8'><title>verify {html.escape(str(args.model))}</title>"
            f"</head><body><h1>Verification of {html.escape(str(args.model))}</h1><ul>{items}</ul>"
            f"<h2>Tracker stations</h2><ul>{stations}</ul></body></html>"
        )
    return 0 if result.holds else 1
