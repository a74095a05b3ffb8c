"""Poses that keep one tool orientation: the portfolio's surface cells trained with the target offset held
where the poses do not determine it, beside the same recipe with the offset left free (no direction held),
each judged on held-out poses of the same path in the tracker frame, at the target, against the floor.

"URDF, rigid-only" is the nominal model with the tracker and target fitted to it alone, the candidate the
recipe never serves a worse model than; "URDF, as reported" is the URDF row a model's summary shows.

Usage: python -m bench.bench_one_orientation [--steps S]
"""

from __future__ import annotations

import argparse

import numpy as np

from bench.bench_real import fit_recipe, model_errors
from bench.report import table, write_section
from hybrid_kinematics_ros.calibration import referencing, train
from hybrid_kinematics_ros.simulation.portfolio import SURFACE_CELLS, TRACKER_FAR, build_cell
from hybrid_kinematics_ros.simulation.tracker import Tracker


def run_cell(spec, steps: int, hold: bool) -> list[object]:
    cell = build_cell(spec)
    margin = referencing.TURN_MARGIN
    referencing.TURN_MARGIN = margin if hold else 0.0
    try:
        model, manifest, tr, _ = fit_recipe(cell.config, [cell.train], train.PRESETS["fast"], (), 10.0, steps)
    finally:
        referencing.TURN_MARGIN = margin
    errors = model_errors(cell.config, model, manifest, tr, [cell.test])
    reported = manifest["metrics"]["test"]["analytic"]["position_mm_mean"]
    (ref,) = manifest["rigid_referencing"]
    offset = np.array(ref["flange_to_target"])[:3, 3]
    truth = Tracker.from_config(TRACKER_FAR).flange_to_target[:3, 3]
    hybrid = errors["hybrid"]["position_mm_mean"]
    return [
        spec.name,
        "held where undetermined" if hold else "free",
        f"{cell.floor['position_mm_mean']:.4f}",
        f"{errors['URDF model']['position_mm_mean']:.4f}",
        f"{reported:.4f}",
        f"{errors['parametric stage']['position_mm_mean']:.4f}",
        f"{hybrid:.4f}",
        f"{hybrid / cell.floor['position_mm_mean']:.2f}",
        f"{1e3 * np.linalg.norm(offset - truth):.2f}",
        "yes" if ref["undetermined"] else "no",
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--steps", type=int, default=2000, help="optimiser steps per net")
    args = parser.parse_args()
    rows = [run_cell(spec, args.steps, hold) for spec in SURFACE_CELLS for hold in (True, False)]
    head = [
        "cell",
        "target offset",
        "floor pos. (mm)",
        "URDF, rigid-only (mm)",
        "URDF, as reported (mm)",
        "stage pos. (mm)",
        "hybrid pos. (mm)",
        "hybrid / floor",
        "referenced offset from the true one (mm)",
        "undetermined named",
    ]
    body = table(head, rows)
    write_section("one_orientation", "Poses of one tool orientation (bench_one_orientation)", body)


if __name__ == "__main__":
    main()
