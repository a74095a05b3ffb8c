"""How far the real cells move from one seed to the next, and series B and D trained alone against the former
fixed recipe: the yardstick a change to the recipe is judged by on real data.

Each real cell of the portfolio (split as ``bench_portfolio`` splits it) is trained with the capacity chosen,
once per seed; only the recipe's seed changes (the nets' initialisation, the folds, the referencing's start).
B and D, each on its own held-out fifth in contiguous blocks, are trained with the capacity chosen and with the
former constants, side by side.

Usage: python -m bench.bench_seeds [--seeds N] [--steps S] [--skip SUBSTRING ...] [--only SUBSTRING]
(``--skip`` leaves out the real cells whose name holds it; ``--only`` prints its rows and leaves BENCHMARKS.md
alone.)
"""

from __future__ import annotations

import argparse

import numpy as np

from bench.bench_portfolio import FORMER, evaluate_cell, real_cells
from bench.bench_real import load_series
from bench.report import table, write_section
from hybrid_kinematics_ros.calibration.fit import split
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config

ALONE = ("B", "D")  # the series trained alone


def spread_rows(seeds: int, steps: int, skip: list[str], only: str | None) -> list[list[object]]:
    """Per real cell: the held-out hybrid mean position (mm) of each seed, their range and standard deviation."""
    rows = []
    for name, config, trains, tests, _ in real_cells():
        if (only and only not in name) or any(s in name for s in skip):
            continue
        means = [
            evaluate_cell(config, trains, tests, True, steps, None, seed=seed)[0]["hybrid"]["position_mm_mean"]
            for seed in range(seeds)
        ]
        rows.append(
            [
                name,
                sum(len(p) for p in trains),
                " / ".join(f"{m:.4f}" for m in means),
                f"{min(means):.4f} - {max(means):.4f}",
                f"{np.std(means, ddof=1):.4f}" if seeds > 1 else "—",
            ]
        )
        print(" | ".join(str(v) for v in rows[-1]), flush=True)
    return rows


def alone_rows(steps: int, only: str | None) -> list[list[object]]:
    """B and D alone: hybrid and stage held-out mean position (mm), the capacity chosen against the former."""
    config = load_robot_config("ur10")
    rows = []
    for name in ALONE:
        if only and only not in f"{name} alone":
            continue
        train, _, test = split(load_series(name, config.chain.joint_names), 0, (0.0, 0.2))
        figures = []
        for fixed in (None, FORMER):
            errors = evaluate_cell(config, [train], [test], True, steps, fixed)[0]
            figures.append(
                f"{errors['hybrid']['position_mm_mean']:.4f} / {errors['parametric stage']['position_mm_mean']:.4f}"
            )
        rows.append([f"{name} alone", len(train), len(test), *figures])
        print(" | ".join(str(v) for v in rows[-1]), flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, default=3, help="seeds per real cell (0, 1, ...)")
    parser.add_argument("--steps", type=int, default=3000, help="optimiser steps per net")
    parser.add_argument("--skip", action="append", default=[], help="leave out the real cells whose name holds this")
    parser.add_argument("--only", help="run only the cells whose name holds this")
    args = parser.parse_args()
    spread = spread_rows(args.seeds, args.steps, args.skip, args.only)
    alone = alone_rows(args.steps, args.only)
    if args.only:
        return
    body = (
        f"Real cells of the portfolio, split as there, `fast` nets of {args.steps:,} steps, the capacity chosen; "
        "only the recipe's seed changes between runs. Held-out hybrid mean position error (mm).\n\n"
        + table(["cell", "training poses", "seed 0 / 1 / ... (mm)", "range (mm)", "sd (mm)"], spread)
        + "\n\nSeries B and D trained alone, each tested on its own last fifth in contiguous blocks, approach "
        "inputs offered: the capacity chosen against the former fixed constants (every elastic term, 40 harmonics, "
        "prior 30, a 0.01 rad joint error map). Held-out mean position error (mm), hybrid / stage.\n\n"
        + table(["series", "training poses", "test poses", "chosen: hybrid / stage", "former: hybrid / stage"], alone)
    )
    write_section("seeds", "Real cells: seed-to-seed spread, and B and D alone", body)


if __name__ == "__main__":
    main()
