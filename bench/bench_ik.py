"""Inverse kinematics: the paper's Tables IV/V protocol, TRAC-IK's protocol, eq. 2 against the 6-vector
cost, and trajectories. Models are trained here first (short budget: IK accuracy is measured against the
hybrid FK itself, whatever the nets' accuracy)."""

from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from bench.bench_hybrid import dataset
from bench.report import table, write_section
from hybrid_kinematics_ros.calibration import train
from hybrid_kinematics_ros.calibration.fit import fit
from hybrid_kinematics_ros.calibration.recipe import Recipe
from hybrid_kinematics_ros.ik.baselines import scipy_refine_solver, wang_baseline
from hybrid_kinematics_ros.ik.solver import IKOptions, IKSolver
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.model.hybrid import HybridModel
from hybrid_kinematics_ros.nodes.process import freeze_heap, one_blas_thread

# the hard targets (at singularities) need many branches: one RX160 target took 0.65 s; most take a few ms
LONG_BUDGET_S = 1.0
FAST_MS = 5.0  # #35: ≥ 99.9 % of random targets within this


def trained_model(robot: str, tmp: Path, minutes: float) -> HybridModel:
    cfg = load_robot_config(robot)
    tr, va, te = dataset(robot, 30_000, 1), dataset(robot, 3_000, 2), dataset(robot, 3_000, 3)
    model, _ = fit(cfg.chain, tr, va, te, tmp / robot, Recipe(train.PRESETS["fast"], minutes, parametric=False))
    return model


def paper_protocol(model: HybridModel, n: int, options: IKOptions) -> tuple[list, list]:
    solver = IKSolver(model, options).warm_up()
    patient = IKSolver(model, replace(options, timeout_s=LONG_BUDGET_S)).warm_up()
    freeze_heap()  # as the node does: no full collection of the loaded models inside a timed solve
    one_blas_thread()  # and BLAS on this thread only (no pool's stall)
    q = np.random.default_rng(11).uniform(model.chain.lower, model.chain.upper, (n, model.chain.dof))
    targets = model.fk(q)
    rows = []
    for label, run in (
        (f"ours (LM, then bounded LM on the hybrid FK), {1e3 * options.timeout_s:.0f} ms budget", solver.solve),
        (f"ours, {1e3 * LONG_BUDGET_S:.0f} ms budget", patient.solve),
        ("Wang et al. [26] baseline (compensated target, analytic IK)", lambda t: wang_baseline(solver, t)),
    ):
        results = [run(t) for t in targets]
        ok = np.array([r.success for r in results])
        pos = np.array([r.position_error_mm for r in results])
        rot = np.array([r.orientation_error_deg for r in results])
        ms = 1e3 * np.array([r.seconds for r in results])
        rows.append(
            [
                label,
                f"{100 * ok.mean():.2f}",
                f"{100 * np.mean(ok & (ms <= FAST_MS)):.2f}",
                f"{pos.mean():.3g}",
                f"{pos.std():.3g}",
                f"{rot.mean():.3g}",
                f"{rot.std():.3g}",
                f"{pos[ok].mean():.3g} / {rot[ok].mean():.3g}" if ok.any() else "-",
                f"{np.median(ms):.2f}",
                f"{np.percentile(ms, 95):.2f}",
                f"{ms.max():.1f}",
            ]
        )
    return rows, targets


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--targets", type=int, default=5000)
    parser.add_argument("--train-minutes", type=float, default=1.5)
    args = parser.parse_args()
    head = [
        "robot / method",
        "success (%)",
        f"solved within {FAST_MS:g} ms (%)",
        "position mean (mm)",
        "position std (mm)",
        "orientation mean (deg)",
        "orientation std (deg)",
        "solved only: mean (mm / deg)",
        "median solve (ms)",
        "p95 solve (ms)",
        "max solve (ms)",
    ]
    rows = []
    options = IKOptions(timeout_s=0.05)
    with tempfile.TemporaryDirectory() as tmp:
        for robot in ("ur10", "rx160"):
            model = trained_model(robot, Path(tmp), args.train_minutes)
            part, targets = paper_protocol(model, args.targets, options)
            rows += [[f"{robot}: {r[0]}", *r[1:]] for r in part]
            if robot == "ur10":
                ur10, ur10_targets = model, targets
        # cost comparison on the UR10
        cost_rows = []
        for cost, refine in (("pose6", "scipy"), ("eq2", "scipy"), ("pose6", "lm")):
            solver = IKSolver(ur10, options).warm_up() if refine == "lm" else scipy_refine_solver(ur10, options, cost)
            results = [solver.solve(t) for t in ur10_targets[:500]]
            cost_rows.append(
                [
                    f"{cost}, {'scipy least_squares' if refine == 'scipy' else 'our LM (chord, then exact)'}",
                    f"{100 * np.mean([r.success for r in results]):.1f}",
                    f"{np.mean([r.position_error_mm for r in results]):.3g}",
                    f"{np.mean([r.orientation_error_deg for r in results]):.3g}",
                    f"{1e3 * np.median([r.seconds for r in results]):.2f}",
                ]
            )
        # TRAC-IK protocol, analytic stage
        chain = ur10.chain
        analytic = HybridModel.analytic_only(chain)
        solver = IKSolver(
            analytic, IKOptions(timeout_s=0.005, position_tolerance_mm=1e-2, orientation_tolerance_deg=np.degrees(1e-5))
        ).warm_up()
        q = np.random.default_rng(5).uniform(chain.lower, chain.upper, (10_000, chain.dof))
        targets = analytic.fk(q)
        times, ok = [], 0
        for t in targets:
            r = solver.solve(t, analytic=True)
            times.append(r.seconds)
            ok += r.success
        trac = (100 * ok / len(targets), 1e3 * np.mean(times))
        # trajectory: each pose seeded by the previous answer, against independent solves
        solver = IKSolver(ur10, options).warm_up()
        q0 = np.array([0.2, -1.3, 1.4, -1.2, 1.0, 0.1])
        path = q0 + np.linspace(0, 1, 1000)[:, None] * np.array([0.8, 0.4, -0.5, 0.3, 0.4, 0.6])
        targets = ur10.fk(path)
        start = time.perf_counter()
        traj = solver.solve_trajectory(targets, seed=q0)
        t_traj = (time.perf_counter() - start) / len(targets)
        start = time.perf_counter()
        single = [solver.solve(t) for t in targets[:200]]
        t_single = (time.perf_counter() - start) / 200
    body = (
        f"Paper protocol (Tables IV and V): {args.targets} random configurations within the working range, "
        "targets from the hybrid FK, solved from a mid-limits seed (the budget per target is in each row), "
        "error of the answer measured with the hybrid FK. Paper (virtual): 6.02e-6 mm and 4.85e-4° mean. "
        "Targets: success ≥ 99.9 % (100 % within 50 ms and ≥ 99.9 % within 5 ms since #35), mean ≤ 1e-6 mm and "
        "≤ 1e-6°, median ≤ 5 ms. The means and stds are over all "
        "targets, misses included; one column gives the means over the solved targets alone.\n\n"
        + table(head, rows)
        + "\n\nCost of the refinement (UR10, 500 targets): the 6-vector residual (position in mm, rotation vector"
        " scaled to mm per rad) against the paper's eq. 2, both with scipy's bounded least squares as in the paper"
        " (the refinement alone is switched), and our default.\n\n"
        + table(
            ["cost, refinement", "success (%)", "position mean (mm)", "orientation mean (deg)", "median solve (ms)"],
            cost_rows,
        )
        + f"\n\nTRAC-IK's protocol, our analytic stage (UR10, 10,000 random reachable targets, mid-limits seed, "
        f"tolerance 1e-5, 5 ms budget): **{trac[0]:.2f} % solved, {trac[1]:.2f} ms mean** (TRAC-IK, C++: "
        f"99.79 % at 0.41 ms; time ratio {trac[1] / 0.41:.1f}).\n\n"
        f"Trajectory of 1,000 poses, each seeded by the previous answer: {1e3 * t_traj:.3f} ms per pose "
        f"({100 * np.mean([r.success for r in traj]):.1f} % solved) against {1e3 * t_single:.2f} ms for "
        f"independent solves ({100 * np.mean([r.success for r in single]):.1f} % solved): "
        f"**{t_single / t_traj:.1f}× faster** (target ≥ 5×)."
    )
    write_section("ik", "Inverse kinematics through the hybrid model", body)


if __name__ == "__main__":
    main()
