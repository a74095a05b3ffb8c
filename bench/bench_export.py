"""What each exported file keeps: the real UR10 (series A) trained with ``train``'s recipe on four fifths of its
poses, each export format judged on the held-out fifth (contiguous blocks) in the tracker frame, at the probe,
beside the full model and the uncalibrated URDF.

Usage: python -m bench.bench_export [--steps S]
"""

from __future__ import annotations

import argparse

from bench.bench_real import fit_recipe, load_series
from bench.report import table, write_section
from hybrid_kinematics_ros.calibration import train
from hybrid_kinematics_ros.calibration.export import FORMATS, export, held_out_errors
from hybrid_kinematics_ros.calibration.fit import split
from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.model.hybrid import HybridModel


def trained_on_a(steps: int) -> tuple[HybridModel, Pairs, Pairs]:
    """The real UR10's model of series A with ``train``'s recipe on four fifths (contiguous blocks): the model,
    its training pairs and the held-out fifth."""
    cfg = load_robot_config("ur10")
    train_pairs, _, held_out = split(load_series("A", cfg.chain.joint_names), 0, (0.0, 0.2))
    model, *_ = fit_recipe(cfg, [train_pairs], train.PRESETS["fast"], (), 10.0, steps)
    return model, train_pairs, held_out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--steps", type=int, default=6000, help="optimiser steps per net")
    args = parser.parse_args()
    model, train_pairs, test = trained_on_a(args.steps)
    rows = []
    for form in FORMATS:
        exported = export(model, form)
        errors = held_out_errors(model, exported, [test])
        if not rows:
            for name, label in (("nominal", "URDF model, uncalibrated"), ("hybrid", "full model (served)")):
                rows.append([label, "", *_figures(errors[name])])
        rows.append([f"exported {form}", "; ".join(exported.left), *_figures(errors["exported"])])
    head = ["model", "left behind", "pos. mean (mm)", "pos. p95 (mm)", "ori. mean (deg)"]
    body = f"Real UR10, series A: {len(train_pairs)} poses to train, {len(test)} held out.\n\n" + table(head, rows)
    write_section("export", "What each exported file keeps (bench_export)", body)


def _figures(stats: dict) -> list[str]:
    keys = ("position_mm_mean", "position_mm_p95", "orientation_deg_mean")
    return [f"{stats[key]:.4f}" for key in keys]


if __name__ == "__main__":
    main()
