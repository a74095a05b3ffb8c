"""The orientation residuals' weight in the parametric stage: a fixed 1 m per rad (the former default) against
the weight chosen from each cell's data (``calibration.capacity``, item 5), side by side on every cell.

Every virtual cell of ``simulation.portfolio`` (the stage alone, its capacity chosen from the training walk,
errors against the test walk at the target), and the real UR10 (ipa-robot-accuracy): A and C on block splits,
250 poses of A planned by ``plan`` (with ``bench_plan``'s options at a weight of 1) and 250 and 1,000
random ones; for A and C the hybrid
model too (``fast``, ``--steps`` a net), whose nets carry what the stage leaves.

Usage: python -m bench.bench_orientation_weight [--steps 2000] [--only SUBSTRING]
(``--only`` prints its rows and leaves BENCHMARKS.md alone.)
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bench.bench_plan import options, stage_result
from bench.bench_real import fit_recipe, load_series, model_errors, noise_floor
from bench.report import table, write_section
from hybrid_kinematics_ros.calibration import train
from hybrid_kinematics_ros.calibration.fit import split
from hybrid_kinematics_ros.calibration.plan import MEAN_OVER_RMS, plan
from hybrid_kinematics_ros.kinematics.chain import chain_from_urdf
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.simulation.portfolio import CELLS, build_cell

FIXED = {"orientation_length": 1.0}
HEAD = [
    "cell",
    "poses",
    "model",
    "weight chosen (m per rad)",
    "pos. mean (mm): weight 1 / chosen",
    "chosen / weight 1, pos.",
    "ori. mean (deg): weight 1 / chosen",
    "chosen / weight 1, ori.",
    "fit s: weight 1 / chosen",
]


def chosen_weight(capacity: dict | None) -> float:
    return float((capacity or {}).get("chosen", {}).get("orientation_length", 1.0))


def stage_row(name: str, cfg, train_pairs, test_pairs) -> list:
    """The stage alone, weight 1 and chosen, side by side."""
    figures = []
    for capacity in (FIXED, None):
        start = time.perf_counter()
        pos, rot, result = stage_result(cfg, train_pairs, test_pairs, capacity)
        figures.append((pos, rot, time.perf_counter() - start, chosen_weight(result.capacity)))
    return row(name, len(train_pairs), "stage", figures)


def hybrid_rows(name: str, cfg, train_pairs, test_pairs, steps: int) -> list[list]:
    """The stage and the hybrid model as ``train`` fits them, weight 1 and chosen, side by side."""
    out: dict[str, list] = {"parametric stage": [], "hybrid": []}
    for capacity in (FIXED, None):
        model, manifest, tr, seconds = fit_recipe(
            cfg, [train_pairs], train.PRESETS["fast"], (), 10.0, steps, capacity=capacity
        )
        errors = model_errors(cfg, model, manifest, tr, [test_pairs])
        weight = chosen_weight(manifest.get("capacity"))
        for label in out:
            e = errors[label]
            out[label].append((e["position_mm_mean"], e["orientation_deg_mean"], seconds, weight))
    return [row(name, len(train_pairs), label.replace("parametric ", ""), figures) for label, figures in out.items()]


def row(name: str, poses: int, model: str, figures: list[tuple[float, float, float, float]]) -> list:
    (p1, r1, s1, _), (p2, r2, s2, weight) = figures
    return [
        name,
        poses,
        model,
        round(weight, 3),
        f"{p1:.4f} / {p2:.4f}",
        round(p2 / p1, 3),
        "—" if np.isnan(r1) else f"{r1:.5f} / {r2:.5f}",
        "—" if np.isnan(r1) else round(r2 / r1, 3),
        f"{s1:.0f} / {s2:.0f}",
    ]


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--steps", type=int, default=2000, help="optimiser steps per net (the real hybrid rows)")
    parser.add_argument("--only", help="run only the cells whose name holds this")
    args = parser.parse_args()
    rows: list[list] = []

    def wanted(name: str) -> bool:
        return not args.only or args.only in name

    def show(new: list[list]) -> None:
        rows.extend(new)
        for r in new:
            print(" | ".join(str(v) for v in r), flush=True)

    for spec in CELLS:
        if wanted(spec.name):
            cell = build_cell(spec)
            show([stage_row(spec.name, cell.config, cell.train, cell.test)])
    cfg = load_robot_config("ur10")
    series = {name: load_series(name, cfg.chain.joint_names) for name in ("A", "C")}
    held = {name: split(p, 0, (0.0, 0.2)) for name, p in series.items()}
    pool, test = held["A"][0], held["A"][2]
    rng = np.random.default_rng(0)
    if wanted("real UR10 A, 250 planned"):
        urdf = chain_from_urdf(cfg.urdf_path, cfg.base_link, cfg.tip_link)
        noise_mm, noise_deg, _ = noise_floor(series["A"], cfg.chain)
        per_axis = MEAN_OVER_RMS * np.sqrt(3.0)
        # one plan for both weights: bench_plan's options for A as they were with a weight of 1 (the tracker's
        # noise, and 0.0712 mm that the stage on the whole pool left at that weight)
        planned = plan(
            cfg.chain.with_limits(urdf.lower, urdf.upper),
            pool.q,
            options(cfg, 250, (noise_mm / per_axis, noise_deg / per_axis), (0.0712, 0.0), None),
        ).rows
        show([stage_row("real UR10 A, 250 planned", cfg, pool.subset(planned), test)])
    for count in (250, 1000):
        subset = pool.subset(np.sort(rng.choice(len(pool), count, replace=False)))
        if wanted(f"real UR10 A, {count:,} random"):
            show([stage_row(f"real UR10 A, {count:,} random", cfg, subset, test)])
    for name in ("A", "C"):
        if wanted(f"real UR10 {name}"):
            show(hybrid_rows(f"real UR10 {name}", cfg, held[name][0], held[name][2], args.steps))
    body = (
        "Each row fits one cell twice, side by side in one run: the orientation residuals weighed at a fixed 1 m "
        "per rad (the former default, given as `--orientation-length 1`) and at the weight chosen from the "
        "cell's training pairs (`train`'s default: the ratio of the two kinds' residuals that the chosen stage "
        "leaves, repeated until it settles, then 1/9, 1/3, 3 and 9 times it, judged on held-out blocks). Errors "
        "are held-out means at the target. Virtual cells (`simulation/portfolio.py`): the stage alone, its "
        "capacity chosen from the training walk, tested on a separate walk. Real UR10: A and C on block splits "
        "(the held-out fifth in blocks, as `bench_real`); 250 poses that `plan` chooses from A's training part "
        "with `bench_plan`'s options as they were at a weight of 1 (with the chosen weight the whole pool leaves "
        "less, and `bench_plan` plans other poses); random subsets of it; for A and C also the stage and hybrid "
        "model "
        f"as `train` fits them (`fast`, {args.steps:,} steps a net, a tenth of the training part validating). "
        "*fit s*: the stage's identification with its capacity selection (the real hybrid rows: the whole fit)."
        "\n\n" + table(HEAD, rows)
    )
    if args.only:
        print(body)
        return
    write_section("orientation_weight", "The orientation residuals' weight: fixed against chosen", body)


if __name__ == "__main__":
    main()
