"""IK for the side the joints arrive from, on the virtual cell with backlash (simulation.backlash): where the
robot really stops, commanded to the IK answer, against the target.

Models are trained here first on a random walk of the cell (its approach directions from the order of the
poses), one with the directions as net inputs and one without. Three ways to answer each target:
- the model without directions;
- the model with directions, refined with the directions the joints last moved in (stale: the robot then
  arrives from the other side);
- the model with directions, refined with the directions of the move from the seed to the answer
  (``IKOptions.arrive_from_seed``, the default), a trajectory's poses from the pose before.

Usage: python -m bench.bench_ik_approach [--targets N] [--paths P] [--train-minutes M]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from bench.report import table, write_section
from hybrid_kinematics_ros.calibration import train
from hybrid_kinematics_ros.calibration.evaluate import evaluate
from hybrid_kinematics_ros.calibration.fit import fit, split
from hybrid_kinematics_ros.calibration.recipe import Recipe
from hybrid_kinematics_ros.ik.solver import IKOptions, IKSolver
from hybrid_kinematics_ros.kinematics.approach import approach_directions, arrival_directions, channel_names
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.model.hybrid import HybridModel
from hybrid_kinematics_ros.simulation.backlash import BacklashCell

PRESET = replace(train.PRESETS["fast"], arch="mlp:64x2:silu", max_epochs=300)
OPTIONS = IKOptions(position_tolerance_mm=1e-3, orientation_tolerance_deg=1e-3, timeout_s=5.0)
LABELS = {"plain": "without directions", "approach": "with the approach directions"}
WAYS = ("model without directions", "directions last moved (stale)", "directions of arrival (ours)")


def single_moves(cell: BacklashCell, models: dict[str, HybridModel], count: int) -> dict[str, tuple]:
    """``count`` moves from a random seed (where the robot stands) to a pose up to 0.3 rad per joint away:
    errors (mm) and solve times (s) of each way."""
    chain = cell.cell.config.chain
    rng = np.random.default_rng(5)
    lower, upper = 0.6 * chain.lower, 0.6 * chain.upper
    out: dict[str, tuple[list, list]] = {way: ([], []) for way in WAYS}
    for _ in range(count):
        seed = rng.uniform(lower, upper)
        goal = np.clip(seed + rng.uniform(-0.3, 0.3, chain.dof), lower, upper)
        arrive = np.sign(goal - seed)
        target = cell.measure(goal, arrive, rng)[0]
        for way in WAYS:
            model = models["plain" if way == WAYS[0] else "approach"]
            if way != WAYS[0]:
                model = model.with_approach(-arrive)  # the joints last moved the other way
            result = IKSolver(model, replace(OPTIONS, arrive_from_seed=way == WAYS[2])).warm_up().solve(target, seed)
            directions = arrival_directions(seed, result.q, -arrive)
            out[way][0].append(cell.miss_mm(result.q, directions, target)[0] if result.success else np.nan)
            out[way][1].append(result.seconds)
    return {way: (np.array(e), np.array(s)) for way, (e, s) in out.items()}


def trajectories(cell: BacklashCell, models: dict[str, HybridModel], count: int) -> dict[str, tuple]:
    """``count`` paths of 12 poses within the joint limits on which every joint turns back halfway, solved
    as trajectories from the robot's pose: errors (mm) per pose and solve times (s) per pose of each way."""
    chain = cell.cell.config.chain
    rng = np.random.default_rng(6)
    steps = np.r_[np.linspace(0.0, 0.3, 8)[1:], np.linspace(0.3, 0.1, 6)[1:]]
    out: dict[str, tuple[list, list]] = {way: ([], []) for way in WAYS}
    done = 0
    while done < count:
        seed = rng.uniform(0.5 * chain.lower, 0.5 * chain.upper)
        path = seed + np.outer(steps, rng.choice([-1.0, 1.0], chain.dof))
        if np.any(path < chain.lower) or np.any(path > chain.upper):
            continue  # beyond a joint limit (the shoulder's upper one is 0 rad): no IK can reach it
        done += 1
        arrive = approach_directions(np.vstack([seed, path]), start=np.zeros(chain.dof))[1:]
        targets = cell.measure(path, arrive, rng)
        for way in WAYS:
            model = models["plain" if way == WAYS[0] else "approach"]
            if way != WAYS[0]:
                model = model.with_approach(np.zeros(chain.dof))
            start = time.perf_counter()
            solver = IKSolver(model, replace(OPTIONS, arrive_from_seed=way == WAYS[2])).warm_up()
            results = solver.solve_trajectory(targets, seed)
            seconds = (time.perf_counter() - start) / len(targets)
            q = np.array([r.q for r in results])
            directions = approach_directions(np.vstack([seed, q]), start=np.zeros(chain.dof))[1:]
            errors = cell.miss_mm(q, directions, targets)
            errors[[not r.success for r in results]] = np.nan
            out[way][0].extend(errors)
            out[way][1].extend([seconds] * len(targets))
    return {way: (np.array(e), np.array(s)) for way, (e, s) in out.items()}


def rows_of(results: dict[str, tuple]) -> list[list]:
    rows = []
    for way, (errors, seconds) in results.items():
        ok = np.isfinite(errors)
        rows.append(
            [
                way,
                f"{100 * ok.mean():.1f}",
                f"{np.mean(errors[ok]):.4f}",
                f"{np.percentile(errors[ok], 95):.4f}",
                f"{np.max(errors[ok]):.4f}",
                f"{1e3 * np.median(seconds):.2f}",
            ]
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--targets", type=int, default=200, help="single moves")
    parser.add_argument("--paths", type=int, default=20, help="trajectories of 12 poses")
    parser.add_argument("--train-minutes", type=float, default=5.0)
    args = parser.parse_args()
    cfg = load_robot_config("ur10")
    cell = BacklashCell.from_config(cfg)
    tr, va, _ = split(cell.walk(3000, seed=1), seed=0)
    test = cell.walk(500, seed=2)
    models, fk_rows = {}, []
    with tempfile.TemporaryDirectory() as tmp:
        for name, conditions in (("plain", ()), ("approach", channel_names(cfg.chain.joint_names))):
            path = Path(tmp) / name
            fit(
                cfg.chain,
                tr,
                va,
                test,
                path,
                # "plain": without the directions, which the data would choose
                Recipe(PRESET, args.train_minutes, conditions=conditions, capacity={"approach": bool(conditions)}),
            )
            models[name] = HybridModel.load(path)
            hybrid = evaluate(models[name], test)["hybrid"]
            fk_rows.append([LABELS[name], f"{hybrid['position_mm_mean']:.4f}", f"{hybrid['position_mm_p95']:.4f}"])
    head = ["IK answers with", "solved (%)", "mean (mm)", "p95 (mm)", "max (mm)", "median solve (ms per pose)"]
    single = rows_of(single_moves(cell, models, args.targets))
    paths = rows_of(trajectories(cell, models, args.paths))
    body = (
        f"Virtual UR10 with backlash (±{', '.join(f'{1e3 * h:.1f}' for h in cell.half)} mrad per joint), no "
        f"measurement noise. Trained on a random walk of {len(tr)} poses (validation {len(va)}); held-out walk of "
        f"{len(test)} poses, hybrid FK with the directions the joints really arrived in:\n\n"
        + table(["model", "position mean (mm)", "position p95 (mm)"], fk_rows)
        + f"\n\nSingle IK, {args.targets} moves from the robot's pose (the seed) to a pose up to 0.3 rad per joint "
        "away, the joints last moved the other way; error of where the robot really stops:\n\n"
        + table(head, single)
        + f"\n\nTrajectories: {args.paths} paths of 12 poses on which every joint turns back halfway, solved "
        "from the robot's pose (directions unknown at the start); error per pose:\n\n" + table(head, paths)
    )
    write_section("ik_approach", "IK for the side the joints arrive from (bench_ik_approach)", body)


if __name__ == "__main__":
    main()
