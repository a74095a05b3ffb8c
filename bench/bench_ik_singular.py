"""IK with and without the closed forms, side by side in one process: random targets, targets at and near each
singularity class, TRAC-IK's protocol on the URDF model, and the branch count against IK-Geo's.

The "iterative" rows are the same solver with its closed forms switched off (what it was before them). Hybrid
models are trained here first on a short budget: IK accuracy is measured against the hybrid FK itself.

Usage: python -m bench.bench_ik_singular [--targets N] [--train-minutes M] [--keep-models DIR | --models DIR]

``--keep-models DIR`` keeps the models trained here (``DIR/ur10``, ``DIR/rx160``) for tracing a miss afterwards:
a minute's training on a loaded machine gives another model, and the misses move with it. ``--models DIR``
serves the models kept there instead of training: two versions of the solver, measured on the same models.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.optimize import minimize_scalar

from bench.bench_ik import trained_model
from bench.report import table, write_section
from hybrid_kinematics_ros.ik.solver import IKOptions, IKSolver
from hybrid_kinematics_ros.kinematics import fk
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.model.hybrid import HybridModel
from hybrid_kinematics_ros.nodes.process import freeze_heap, one_blas_thread

BUDGET_S = 0.05


def smallest_singular_value(chain, q: np.ndarray) -> float:
    return float(np.linalg.svd(fk.fk_and_jacobian_single(chain, q)[1], compute_uv=False)[-1])


def singular_along(chain, q: np.ndarray, joint: int) -> float | None:
    """The value of ``joint`` nearest a singularity with the other joints of ``q`` kept, or None if the
    Jacobian does not lose rank along that joint (within the limits)."""
    lower, upper = max(chain.lower[joint], -np.pi), min(chain.upper[joint], np.pi)

    def sigma(x: float) -> float:
        v = q.copy()
        v[joint] = x
        return smallest_singular_value(chain, v)

    grid = np.linspace(lower, upper, 181)
    k = int(np.argmin([sigma(x) for x in grid]))
    step = grid[1] - grid[0]
    found = minimize_scalar(
        sigma,
        bounds=(max(lower, grid[k] - step), min(upper, grid[k] + step)),
        method="bounded",
        options={"xatol": 1e-12},
    )
    return float(found.x) if found.fun < 1e-7 else None


def cases(chain, n: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Configurations ``(n, 6)`` per case: random, the wrist (q5) at and near 0, the wrist centre at and near
    axis 1 (a shoulder singularity, found along q2), the elbow stretched (along q3)."""
    out = {"random": rng.uniform(chain.lower, chain.upper, (n, chain.dof))}
    for label, value in (("q5 = 0", 0.0), ("q5 = 1e-4 rad", 1e-4)):
        q = rng.uniform(chain.lower, chain.upper, (n, chain.dof))
        q[:, 4] = value
        out[label] = q
    for joint, name in ((1, "wrist centre on axis 1"), (2, "elbow stretched")):
        base = []
        while len(base) < n:
            q = rng.uniform(chain.lower, chain.upper, chain.dof)
            q[4] = rng.choice([-1, 1]) * rng.uniform(0.3, 1.5)  # away from the wrist singularity
            x = singular_along(chain, q, joint)
            if x is not None:
                q[joint] = x
                base.append(q)
        base = np.array(base)
        for offset in (0.0, 1e-6, 1e-4):
            q = base.copy()
            q[:, joint] += offset
            out[f"{name}{'' if not offset else f' + {offset:g} rad'}"] = q
    return out


def run(solver: IKSolver, targets: np.ndarray, analytic: bool) -> tuple[float, float, float, float]:
    """Solved within the budget (%), then the median, p99 and mean solve time (ms)."""
    results = [solver.solve(t, analytic=analytic) for t in targets]
    # an answer found after the budget counts as a miss
    ok = np.array([r.success and r.seconds <= solver.options.timeout_s for r in results])
    ms = 1e3 * np.array([r.seconds for r in results])
    return 100 * ok.mean(), float(np.median(ms)), float(np.percentile(ms, 99)), float(np.mean(ms))


def side_by_side(model: HybridModel, targets: np.ndarray, analytic: bool, options: IKOptions) -> list[str]:
    """Iterative / closed forms without the valley search / with it (the URDF model has no valley search: its
    middle figure is left out)."""
    solvers = [IKSolver(model, replace(options, closed_form=False)).warm_up()]
    if not analytic:
        solvers.append(IKSolver(model, replace(options, valley=False)).warm_up())
    solvers.append(IKSolver(model, options).warm_up())
    figures = [run(solver, targets, analytic) for solver in solvers]
    return [" / ".join(f"{f[k]:{spec}}" for f in figures) for k, spec in enumerate((".2f", ".3f", ".1f", ".3f"))]


def branch_counts(model: HybridModel, n: int) -> tuple[int, int]:
    """Targets where all branches (``solve_many``, URDF model) number as many as IK-Geo's exact in-limit ones."""
    solver = IKSolver(model, IKOptions()).warm_up()
    chain = model.chain
    q = np.random.default_rng(3).uniform(chain.lower, chain.upper, (n, chain.dof))
    agree = 0
    for target in fk.fk(chain, q):
        ours = solver.solve_many(target, max_solutions=64, analytic=True, deadline=time.perf_counter() + 1.0)
        agree += len(ours) == len(solver.closed_form.branches(target, chain.mid_limits()))
    return agree, n


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--targets", type=int, default=200, help="per case")
    parser.add_argument("--train-minutes", type=float, default=1.0)
    parser.add_argument("--keep-models", type=Path, default=None, help="train the models into DIR and keep them")
    parser.add_argument("--models", type=Path, default=None, help="serve the models --keep-models kept in DIR")
    args = parser.parse_args()
    options = IKOptions(timeout_s=BUDGET_S)
    rows, many, counts = [], [], []
    rng = np.random.default_rng(7)
    with tempfile.TemporaryDirectory() as tmp:
        models = args.keep_models or Path(tmp)
        for robot in ("ur10", "rx160"):
            if args.models:
                model = HybridModel.load(args.models / robot)
            else:
                model = trained_model(robot, models, args.train_minutes)
            urdf = HybridModel.analytic_only(model.chain)
            freeze_heap()  # as the node does: no full collection of the loaded models inside a timed solve
            one_blas_thread()  # and BLAS on this thread only (no pool's stall)
            family = IKSolver(urdf, options).path
            for label, q in cases(model.chain, args.targets, rng).items():
                for kind, m, analytic in (("hybrid", model, False), ("URDF", urdf, True)):
                    figures = side_by_side(m, m.fk(q), analytic, options)
                    rows.append([robot, family if kind == "URDF" else "", label, kind, *figures[:3]])
                    print(" | ".join(rows[-1]), flush=True)
            # several solutions through the hybrid model
            targets = model.fk(rng.uniform(model.chain.lower, model.chain.upper, (args.targets, 6)))
            for closed in (False, True):
                solver = IKSolver(model, replace(options, closed_form=closed)).warm_up()
                start = time.perf_counter()
                found = [
                    len(solver.solve_many(t, max_solutions=8, deadline=time.perf_counter() + 8 * BUDGET_S))
                    for t in targets
                ]
                ms = 1e3 * (time.perf_counter() - start) / len(targets)
                many.append([robot, "closed forms" if closed else "iterative", f"{np.mean(found):.2f}", f"{ms:.2f}"])
            counts.append([robot, *branch_counts(urdf, 1000)])
        # TRAC-IK's protocol on the UR10's URDF model
        trac_model = HybridModel.analytic_only(load_robot_config("ur10").chain)
        freeze_heap()
        q = np.random.default_rng(5).uniform(trac_model.chain.lower, trac_model.chain.upper, (10_000, 6))
        trac = side_by_side(trac_model, trac_model.fk(q), True, IKOptions(timeout_s=0.005))
    head = [
        "robot",
        "closed-form family",
        "targets",
        "model",
        "solved within 50 ms (%): iterative / closed forms [/ + valley]",
        "median ms: iterative / closed forms [/ + valley]",
        "p99 ms: iterative / closed forms [/ + valley]",
    ]
    body = (
        f"{args.targets} targets per case, from the hybrid FK (rows `hybrid`, the model trained here for "
        f"{args.train_minutes:g} min) or the URDF model (rows `URDF`), mid-limits seed, {1e3 * BUDGET_S:.0f} ms "
        "budget, solved = within 1e-4 mm and 1e-4° through the same model, within the budget (an answer found after it "
        "counts as a miss). Each row runs the same solver twice, "
        "side by side: with its closed forms switched off (*iterative*, the solver before them) and on. Hybrid "
        "rows give three figures: iterative / closed forms without the root search along the URDF model's "
        "singular valley / with it (`ik/valley.py`, the default). "
        "The wrist-centre and elbow cases are found along q2 and q3 (the smallest singular value of the URDF "
        "Jacobian below 1e-7), then moved off by the offset in the row.\n\n"
        + table(head, rows)
        + "\n\nSeveral solutions through the hybrid model (`solve_many`, up to 8, budget 8 × 50 ms):\n\n"
        + table(["robot", "solver", "solutions found (mean)", "ms per target"], many)
        + "\n\nBranches: targets (of 1,000, URDF model) where `solve_many` returns as many branches as IK-Geo's "
        "exact answers within the limits:\n\n"
        + table(["robot", "targets that agree", "targets"], counts)
        + f"\n\nTRAC-IK's protocol on the UR10's URDF model (10,000 random targets, 5 ms budget, 1e-4 mm and "
        f"1e-4°): solved {trac[0]} % (iterative / closed forms), median {trac[1]} ms, p99 {trac[2]} ms, "
        f"mean {trac[3]} ms.\n"
    )
    write_section("ik_singular", "IK with the closed forms: random targets, singularities, branches", body)


if __name__ == "__main__":
    main()
