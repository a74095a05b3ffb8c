"""The portfolio: every virtual cell of ``simulation.portfolio`` and the real UR10, each against its floor.

Each cell is trained twice, side by side in one run: with the capacity chosen from its training pairs
(``train``'s default) and with the stage's former fixed constants (every elastic term, 40 harmonics,
prior 30, a 0.01 rad joint error map). Errors are held-out means and p95, at the target in the measuring frame.

Usage: python -m bench.bench_portfolio [--steps S] [--virtual-only] [--only SUBSTRING]
(``--only`` and ``--virtual-only`` print their rows and leave BENCHMARKS.md alone.)
"""

from __future__ import annotations

import argparse

import numpy as np

from bench.bench_real import SERIES, fit_recipe, load_series, model_errors, noise_floor
from bench.report import served, table, write_section
from hybrid_kinematics_ros.calibration import capacity as capacity_module
from hybrid_kinematics_ros.calibration import train
from hybrid_kinematics_ros.calibration.evaluate import pose_errors_of
from hybrid_kinematics_ros.calibration.fit import split
from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.kinematics import approach
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.model.bounds import excess
from hybrid_kinematics_ros.simulation.portfolio import CELLS, build_cell

FORMER = {"elastic": "bending", "harmonics": 40, "harmonic_prior": 30.0, "map_step": 0.01, "map_smoothness": 0.03}


def evaluate_cell(
    config, train_sets: list[Pairs], tests: list[Pairs], approach_inputs: bool, steps: int, fixed, **recipe_fields
):
    """Fit one model (capacity chosen, or ``fixed``); the errors of each stage on the pooled test pairs.
    Chosen, the data also decide whether the nets take the approach directions; ``fixed``, they take them
    where ``approach_inputs`` (as the former recipe was told). ``recipe_fields``: any other recipe field."""
    conditions = approach.channel_names(config.chain.joint_names) if approach_inputs and fixed else ()
    model, manifest, tr, seconds = fit_recipe(
        config,
        train_sets,
        train.PRESETS["fast"],
        conditions,
        10.0,
        steps,
        capacity=fixed,
        choose_capacity=fixed is None,
        **recipe_fields,
    )
    errors = model_errors(config, model, manifest, tr, tests)
    # the test pairs inside the trained joint range, where the model interpolates, and their hybrid errors
    pos_mm = np.concatenate([pose_errors_of(model, te)["hybrid"][0] for te in tests])
    trained = (model.trained_lower, model.trained_upper, config.chain.revolute)
    inside = ~(np.concatenate([excess(te.q, *trained) for te in tests]) > 0).any(axis=1)
    errors["inside"] = {"share": float(inside.mean()), "mean": float(pos_mm[inside].mean()) if inside.any() else None}
    return errors, manifest, seconds


HEAD = [
    "cell",
    "poses",
    "floor pos. mean / p95 (mm)",
    "URDF pos. (mm)",
    "geometry pos. (mm)",
    "stage pos. mean / p95 (mm)",
    "hybrid pos. mean / p95 (mm)",
    "hybrid / floor",
    "hybrid pos. inside the trained range: mean (mm) / share of test (%)",
    "floor ori. (deg)",
    "stage ori. (deg)",
    "hybrid ori. mean / p95 (deg)",
    "former constants: stage / hybrid pos. (mm)",
    "former: hybrid ori. (deg)",
    "capacity chosen",
    "nets served",
    "train s (chosen / former)",
]


def _pair(s: dict, key: str, digits: int = 4) -> str:
    mean, p95 = s.get(f"{key}_mean"), s.get(f"{key}_p95")
    return "—" if mean is None else f"{mean:.{digits}f} / {p95:.{digits}f}"


def row(name, poses, floor, chosen, former) -> list:
    (after, manifest, seconds), (before, _, before_seconds) = chosen, former
    hyb, inside = after["hybrid"], after["inside"]
    return [
        name,
        poses,
        _pair(floor, "position_mm"),
        f"{after['URDF model']['position_mm_mean']:.3f}",
        f"{after['geometry only']['position_mm_mean']:.4f}" if "geometry only" in after else "— (no stage served)",
        _pair(after["parametric stage"], "position_mm"),
        _pair(hyb, "position_mm"),
        f"{hyb['position_mm_mean'] / floor['position_mm_mean']:.2f}",
        "—" if inside["mean"] is None else f"{inside['mean']:.4f} / {100 * inside['share']:.0f}",
        "—" if "orientation_deg_mean" not in floor else f"{floor['orientation_deg_mean']:.4f}",
        "—" if "orientation_deg_mean" not in floor else f"{after['parametric stage']['orientation_deg_mean']:.4f}",
        "—" if "orientation_deg_mean" not in floor else _pair(hyb, "orientation_deg"),
        f"{before['parametric stage']['position_mm_mean']:.4f} / {before['hybrid']['position_mm_mean']:.4f}",
        "—" if "orientation_deg_mean" not in floor else f"{before['hybrid']['orientation_deg_mean']:.4f}",
        capacity_module.summary(manifest["capacity"]).replace(",", ";"),
        served(manifest).replace(",", ";").replace("mlp:", "").replace(":silu", ""),
        f"{seconds:.0f} / {before_seconds:.0f}",
    ]


def real_cells():
    """The real UR10 (ipa-robot-accuracy): A and C on block splits, A subsampled, all four stations."""
    config = load_robot_config("ur10")
    series = {name: load_series(name, config.chain.joint_names) for name in SERIES}
    held = {name: split(p, 0, (0.0, 0.2)) for name, p in series.items()}
    floors = {}
    for name in SERIES:
        pos, rot, _ = noise_floor(series[name], config.chain)
        floors[name] = {"position_mm_mean": pos, "position_mm_p95": float("nan"), "orientation_deg_mean": rot}
    # A's pairs repeat no command (see bench_real floor): B's floor stands for every series
    floor = floors["B"]

    def sub(p: Pairs, count: int) -> Pairs:
        return p.subset(np.sort(np.random.default_rng(0).permutation(len(p))[:count]))

    yield "real UR10 A", config, [held["A"][0]], [held["A"][2]], floor
    yield "real UR10 C", config, [held["C"][0]], [held["C"][2]], floor
    yield "real UR10 A, 250 poses", config, [sub(held["A"][0], 250)], [held["A"][2]], floor
    yield "real UR10 A, 1,000 poses", config, [sub(held["A"][0], 1000)], [held["A"][2]], floor
    yield (
        "real UR10 A+B+C+D (tested on each)",
        config,
        [held[n][0] for n in SERIES],
        [held[n][2] for n in SERIES],
        floor,
    )


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--steps", type=int, default=3000, help="optimiser steps per net")
    parser.add_argument("--virtual-only", action="store_true")
    parser.add_argument("--only", help="run only the cells whose name holds this")
    args = parser.parse_args()
    rows = []

    def run(name, config, trains, tests, floor, approach_inputs):
        if args.only and args.only not in name:
            return
        chosen = evaluate_cell(config, trains, tests, approach_inputs, args.steps, None)
        former = evaluate_cell(config, trains, tests, approach_inputs, args.steps, FORMER)
        rows.append(row(name, sum(len(p) for p in trains), floor, chosen, former))
        print(" | ".join(str(v) for v in rows[-1]), flush=True)

    for spec in CELLS:
        cell = build_cell(spec)
        run(spec.name, cell.config, [cell.train], [cell.test], cell.floor, spec.approach)
    if not args.virtual_only:
        for name, config, trains, tests, floor in real_cells():
            run(name, config, trains, tests, floor, True)
    body = (
        "Each row is a cell: held-out errors at the target, in the frame it was measured in. The **floor** is "
        "what a perfect model of the joints (and approach sides) would still score: for a virtual cell the "
        "noise-free, drift-free truth against the test measurements; for the real UR10, pairs of "
        "measurements of the same joints (series B; mean only). Virtual cells: separate random walks of the "
        "joints for training and test (`simulation/portfolio.py` says what each effect is). Real cells: "
        "the held-out fifth of each series in contiguous blocks, as `bench_real`. Whether the nets take the "
        "joints' approach directions is chosen from the data too (the former recipe was given them in the real "
        f"and the backlash cells). Nets: `fast`, {args.steps:,} steps a net; each residual's size, whether "
        "to average an ensemble of it (x4) and whether to correct at all are chosen on validation (*nets "
        "served*, for the chosen capacity). The **capacity** of the stage is chosen from each cell's "
        "training pairs (`train`'s default); "
        "the *former constants* columns train the same cell with the fixed capacity used before (every elastic "
        "term, 40 harmonics, prior 30, a 0.01 rad joint error map; the elastic terms now include the cubic and "
        "signed compliances, so the column isolates the capacity's choice). *Inside the trained range*: the "
        "test pairs with every joint within the range of the training pairs, where the model interpolates "
        "(a short walk leaves much of the test walk beyond it).\n\n" + table(HEAD, rows)
    )
    if args.only or args.virtual_only:
        print(body)  # a partial table must not replace the whole one in BENCHMARKS.md
        return
    write_section("portfolio", "Portfolio: every cell against its floor", body)


if __name__ == "__main__":
    main()
