"""``update``: a new model from an old one and a few new poses, in seconds; the old model stays as it is."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from hybrid_kinematics_ros.calibration.fit import load_stations
from hybrid_kinematics_ros.calibration.update import check_out, update, write_updated
from hybrid_kinematics_ros.model.hybrid import HybridModel


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("update", help="a new model from an old one and a few new poses (stations and stage refitted)")
    p.add_argument("--model", required=True, type=Path, help="the parent model directory (never modified)")
    p.add_argument("--bag", required=True, nargs="+", help="the new poses: pairs bag(s) or raw recordings")
    p.add_argument("--out", required=True, type=Path, help="the new model directory (must not exist)")
    p.add_argument("--json", type=Path, help="write what the update did as JSON here")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    start = time.perf_counter()
    check_out(args.out)
    model = HybridModel.load(args.model)
    updated = update(model, load_stations(args.bag, model.chain))
    write_updated(model, updated, args.out)
    HybridModel.load(args.out)  # the child serves
    print("\n".join(updated.lines()))
    print(f"wrote {args.out} in {time.perf_counter() - start:.1f} s")
    if args.json:
        args.json.write_text(json.dumps(updated.record, indent=2))
    return 0
