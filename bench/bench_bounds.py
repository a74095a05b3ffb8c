"""The bound on each answer's error: does it hold, does it follow the error, does it grow beyond the trained range?

Each model is trained as ``train`` does by default (capacity chosen, ``fast`` nets), its bounds calibrated
on its own validation blocks (:mod:`calibration.bounds`), then checked on held-out test pairs it never saw:
real UR10 series A and C on block splits, C's model on series B (another part of the workspace), and three
virtual cells of the portfolio. Also the cost of a bound beside one FK.

Usage: python -m bench.bench_bounds [--steps S]
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import spearmanr

from bench.bench_real import fit_recipe, load_series
from bench.report import table, write_section
from hybrid_kinematics_ros.calibration import train
from hybrid_kinematics_ros.calibration.bounds import fit_scale
from hybrid_kinematics_ros.calibration.evaluate import pose_errors_of
from hybrid_kinematics_ros.calibration.fit import split
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.model.bounds import excess, features
from hybrid_kinematics_ros.simulation.cell import VirtualCell
from hybrid_kinematics_ros.simulation.portfolio import CELLS, build_cell

VIRTUAL = ("UR10: realistic, 1,000 poses", "RX160: every effect", "UR10: plain reflector (position only)")
HEAD = [
    "model",
    "tested on",
    "pairs",
    "pos. error median (mm)",
    "pos. bound median (mm)",
    "pos. under bound (%)",
    "Spearman pos. bound / error",
    "ori. error median (deg)",
    "ori. bound median (deg)",
    "ori. under bound (%)",
    "Spearman ori. bound / error",
    "beyond the trained range (%)",
    "steepest growth pos. (mm per rad)",
    "without the scale: pos. bound median (mm)",
    "without the scale: pos. under bound (%)",
    "without the scale: Spearman pos. / ori.",
    "yardsticks pos.: neighbours in joints / in time / the scale fitted on the errors",
    "yardsticks ori.: neighbours in joints / in time / the scale fitted on the errors",
]
NEIGHBOURS = 20  # the yardstick's neighbours in joint space (10 and 40 gave the same or less on real A)


PART_OF_THE_RANGE = ((2000, (-2.0, -1.0), 1), (600, (-0.8, -0.2), 2))  # poses, shoulder range (rad), seed
FARTHER = {  # the same cell asked farther from its shoulder range: label, shoulder range (rad), seed
    "the shoulder 1-3.5 rad beyond": ((1.0, 2.5), 3),
    "the shoulder 0.5-1 rad below": ((-3.0, -2.5), 4),
}
POLICIES = ("warn", "parametric", "bound")
# Payloads served by the noise-free shoulder cell's model, trained with the UR10's own (kg; centre of mass in the
# tip frame, m), each checked on a cell that carries it: a heavier tool at the same point, and a much heavier one
# off-centre. Configurations inside the trained range (the first row of PART_OF_THE_RANGE), a seed of their own.
PAYLOADS = ((4.0, None), (15.0, (0.0, 0.05, 0.15)))
PAYLOAD_POSES, PAYLOAD_SEED = 300, 5
PAYLOAD_HEAD = [
    "payload served (kg)",
    "pairs",
    "pos. error median (mm)",
    "ori. error median (deg)",
    "calibrated bound: pos. median (mm)",
    "calibrated bound: pos. / ori. under bound (%)",
    "payload bound: pos. median (mm)",
    "payload bound: ori. median (deg)",
    "payload bound: pos. / ori. under bound (%)",
]
POLICY_HEAD = [
    "model",
    "tested on",
    "pairs",
    *(f"pos. error mean, {p} (mm)" for p in POLICIES),
    *(f"ori. error mean, {p} (deg)" for p in POLICIES),
    "bound: nets served, pos. / ori. (%)",
    "bound: pos. / ori. under bound (%)",
]


def shoulder_configurations(count: int, shoulder: tuple[float, float], seed: int) -> np.ndarray:
    """UR10 configurations with the shoulder in ``shoulder``, the elbow in [0.5, 2] rad, the rest anywhere."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(-np.pi, np.pi, (count, 6))
    q[:, 1] = rng.uniform(*shoulder, count)
    q[:, 2] = rng.uniform(0.5, 2.0, count)
    return q


def unscaled(model, q: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """The same model's bounds without the scale: one quantile inside the range (as before the scale), from
    the same validation errors (``figures``' ``*_quantile_without_scale``)."""
    revolute = model.chain.revolute
    x = excess(q, model.trained_lower, model.trained_upper, revolute)
    figures = model.bounds.figures
    out = []
    for kind, bound in (("position", model.bounds.position), ("orientation", model.bounds.orientation)):
        flat = None if bound is None else replace(bound, quantile=figures[f"{kind}_quantile_without_scale"], scale=None)
        out.append(None if flat is None else flat(q, x, revolute))
    return out[0], out[1]


def yardsticks(q: np.ndarray, stamps: np.ndarray, error: np.ndarray, revolute: np.ndarray) -> list[float]:
    """How far anything could rank these test errors, three ways; each reads the errors themselves, so no
    bound can use them. The Spearman correlation between each error and: the mean error of its NEIGHBOURS
    nearest test configurations (joints by their sines and cosines), of its NEIGHBOURS nearest in measurement
    order (what drifts slowly: temperature, the tracker), both with itself left out; and the bound's own
    scale (:func:`calibration.bounds.fit_scale`) fitted on these very errors: about the most its form can
    rank them with the answers in hand (the fit is least squares on the logarithm, not on ranks)."""
    f = features(q, revolute)[:, 1:]
    _, near = cKDTree(f).query(f, NEIGHBOURS + 1)
    order = np.argsort(stamps, kind="stable")
    ordered = error[order]
    half = NEIGHBOURS // 2
    padded = np.r_[np.zeros(half), ordered, np.zeros(half)]
    count = np.r_[np.zeros(half), np.ones(len(ordered)), np.zeros(half)]
    window = np.ones(2 * half + 1)
    # the window's sum less the pair itself, over the pairs inside it (fewer at the ends)
    sums = np.convolve(padded, window, "valid") - ordered
    counts = np.convolve(count, window, "valid") - 1.0
    in_time = np.empty(len(error))
    in_time[order] = sums / counts
    scale = fit_scale(q, error, revolute)
    return [
        float(spearmanr(error[near[:, 1:]].mean(axis=1), error)[0]),
        float(spearmanr(in_time, error)[0]),
        float(spearmanr(scale(q, revolute), error)[0]),
    ]


def checked(model, pairs) -> dict:
    pos_mm, rot_deg = pose_errors_of(model, pairs)["hybrid"]
    bound_pos, bound_rot = model.error_bounds(pairs.q)  # joints are the same in any frame
    flat_pos, flat_rot = unscaled(model, pairs.q)
    beyond = excess(pairs.q, model.trained_lower, model.trained_upper, model.chain.revolute) > 0
    out = {
        "pairs": len(pos_mm),
        "beyond": float(np.mean(beyond.any(axis=1))),
        "pos": (np.median(pos_mm), np.median(1e3 * bound_pos), np.mean(pos_mm <= 1e3 * bound_pos)),
        "pos_rho": spearmanr(1e3 * bound_pos, pos_mm)[0],
        "flat_pos": (np.median(1e3 * flat_pos), np.mean(pos_mm <= 1e3 * flat_pos)),
        "flat_rho": [spearmanr(1e3 * flat_pos, pos_mm)[0]],
        "yardsticks": [yardsticks(pairs.q, pairs.stamps, pos_mm, model.chain.revolute)],
    }
    if bound_rot is not None:
        deg = np.degrees(bound_rot)
        out["ori"] = (np.median(rot_deg), np.median(deg), np.mean(rot_deg <= deg))
        out["ori_rho"] = spearmanr(deg, rot_deg)[0]
        out["flat_rho"].append(spearmanr(flat_rot, rot_deg)[0])
        out["yardsticks"].append(yardsticks(pairs.q, pairs.stamps, rot_deg, model.chain.revolute))
    return out


def row(label: str, tested: str, c: dict, model) -> list:
    def spearman(rho: float) -> str:  # undefined where every bound is the same (all inside the trained range)
        return "— (one bound)" if np.isnan(rho) else f"{rho:.2f}"

    def part(key: str) -> list:
        if key not in c:
            return ["—"] * 4
        err, bound, covered = c[key]
        return [f"{err:.4f}", f"{bound:.4f}", f"{100 * covered:.1f}", spearman(c[key + "_rho"])]

    steepest = 1e3 * float(model.bounds.position.rates.max())
    flat_median, flat_covered = c["flat_pos"]
    return [
        label,
        tested,
        c["pairs"],
        *part("pos"),
        *part("ori"),
        f"{100 * c['beyond']:.0f}",
        f"{steepest:.3g}",
        f"{flat_median:.4f}",
        f"{100 * flat_covered:.1f}",
        " / ".join(spearman(r) for r in c["flat_rho"]),
        *(" / ".join(f"{r:.2f}" for r in kind) for kind in c["yardsticks"]),
        *(["—"] * (2 - len(c["yardsticks"]))),
    ]


def policies(label: str, tested: str, model, pairs) -> list:
    """One row of the range policies' table: the mean errors under each policy, where ``bound`` served the
    nets, and the coverage of the bounds it served. Leaves the model's policy at ``warn``."""
    errors = {}
    for policy in POLICIES:
        errors[policy] = pose_errors_of(model.with_range_policy(policy), pairs)["hybrid"]
    bound_pos, bound_rot = model.error_bounds(pairs.q)
    bound = model.with_range_policy("bound")
    served = bound._nets_apply(bound.same_turn(pairs.q))
    served = np.ones((len(pairs), 2)) if served is True else served
    pos_mm, rot_deg = errors["bound"]
    covered = f"{100 * np.mean(pos_mm <= 1e3 * bound_pos):.1f}"
    if bound_rot is not None:
        covered += f" / {100 * np.mean(rot_deg <= np.degrees(bound_rot)):.1f}"
    return [
        label,
        tested,
        len(pairs),
        *(f"{errors[p][0].mean():.4f}" for p in POLICIES),
        *(f"{errors[p][1].mean():.5f}" if bound_rot is not None else "—" for p in POLICIES),
        f"{100 * served[:, 0].mean():.0f} / {100 * served[:, 1].mean():.0f}",
        covered,
    ]


def payloads(cfg, model) -> list[list]:
    """The bound under another payload than the trained one (``HybridModel._payload_bounds``) beside the
    calibrated bound, which the model served there before: both against the errors of a cell carrying it."""
    rows = []
    q = shoulder_configurations(PAYLOAD_POSES, PART_OF_THE_RANGE[0][1], PAYLOAD_SEED)
    for mass, com in PAYLOADS:
        com = cfg.payload_com if com is None else np.asarray(com)
        heavy = model.with_payload(mass, com)
        cell = VirtualCell.from_config(replace(cfg, payload_mass=mass, payload_com=com), noise=False)
        pairs = cell.pairs(q, PAYLOAD_SEED)
        pos_mm, rot_deg = pose_errors_of(heavy, pairs)["hybrid"]
        (own_pos, own_rot), (new_pos, new_rot) = model.error_bounds(pairs.q), heavy.error_bounds(pairs.q)
        rows.append(
            [
                f"{mass:g}",
                len(pairs),
                f"{np.median(pos_mm):.4f}",
                f"{np.median(rot_deg):.5f}",
                f"{1e3 * np.median(own_pos):.4f}",
                f"{100 * np.mean(pos_mm <= 1e3 * own_pos):.0f} / {100 * np.mean(rot_deg <= np.degrees(own_rot)):.0f}",
                f"{1e3 * np.median(new_pos):.4f}",
                f"{np.degrees(np.median(new_rot)):.4f}",
                f"{100 * np.mean(pos_mm <= 1e3 * new_pos):.0f} / {100 * np.mean(rot_deg <= np.degrees(new_rot)):.0f}",
            ]
        )
    return rows


def cost(model, q: np.ndarray) -> tuple[float, float]:
    """Median µs of one FK alone, and of one FK with its bound, interleaved."""
    plain, bounded = [], []
    for x in q:
        t0 = time.perf_counter()
        model.fk_single(x)
        t1 = time.perf_counter()
        model.fk_single(x)
        model.error_bounds(x)
        t2 = time.perf_counter()
        plain.append(t1 - t0)
        bounded.append(t2 - t1)
    return 1e6 * float(np.median(plain)), 1e6 * float(np.median(bounded))


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--steps", type=int, default=2000, help="optimiser steps per net")
    args = parser.parse_args()
    cfg = load_robot_config("ur10")
    series = {name: load_series(name, cfg.chain.joint_names) for name in "ABC"}
    rows, costs, policy_rows = [], [], []

    def fitted(config, trains):
        model, *_ = fit_recipe(config, trains, train.PRESETS["fast"], (), 10.0, args.steps)
        return model

    for name in "AC":
        tr, _, te = split(series[name], 0, (0.0, 0.2))
        model = fitted(cfg, [tr])
        rows.append(row(f"real UR10 {name}", f"{name}'s held-out blocks", checked(model, te), model))
        print(rows[-1], flush=True)
    rows.append(row("real UR10 C", "series B (elsewhere)", checked(model, series["B"]), model))
    print(rows[-1], flush=True)
    policy_rows.append(policies("real UR10 C", "C's held-out blocks", model, te))
    policy_rows.append(policies("real UR10 C", "series B (elsewhere)", model, series["B"]))
    print(policy_rows[-2:], flush=True)
    costs.append(("real UR10 C", *cost(model, series["C"].q[:2000])))
    # a cell measured in part of its range, asked about the rest: the shoulder and elbow within a radian
    # and a half while the other joints go anywhere, then the shoulder 0.2-0.8 rad beyond
    cell = VirtualCell.from_config(cfg)
    inside, beyond = (cell.pairs(shoulder_configurations(n, s, seed), seed) for n, s, seed in PART_OF_THE_RANGE)
    tr, _, te = split(inside, 0, (0.0, 0.2))
    model = fitted(cfg, [tr])
    label = "UR10 (virtual, noise): shoulder in [-2, -1] rad"
    rows.append(row(label, "its held-out blocks", checked(model, te), model))
    rows.append(row(label, "the shoulder 0.2-0.8 rad beyond", checked(model, beyond), model))
    print(rows[-2:], flush=True)
    # the range policies on the same cell without noise, where the capacity selection keeps the nets
    cell = VirtualCell.from_config(cfg, noise=False)
    inside, beyond = (cell.pairs(shoulder_configurations(n, s, seed), seed) for n, s, seed in PART_OF_THE_RANGE)
    tr, _, te = split(inside, 0, (0.0, 0.2))
    model = fitted(cfg, [tr])
    label = "UR10 (virtual, no noise): shoulder in [-2, -1] rad"
    policy_rows.append(policies(label, "its held-out blocks", model, te))
    policy_rows.append(policies(label, "the shoulder 0.2-0.8 rad beyond", model, beyond))
    for tested, (shoulder, seed) in FARTHER.items():
        far = cell.pairs(shoulder_configurations(400, shoulder, seed), seed)
        policy_rows.append(policies(label, tested, model, far))
    print(policy_rows[-4:], flush=True)
    payload_rows = payloads(cfg, model)
    print(payload_rows, flush=True)
    for spec in (c for c in CELLS if c.name in VIRTUAL):
        cell = build_cell(spec)
        model = fitted(cell.config, [cell.train])
        rows.append(row(spec.name, "a separate walk", checked(model, cell.test), model))
        print(rows[-1], flush=True)
    body = (
        "Each model as `train` makes it by default (capacity chosen from its data, `fast` nets, "
        f"{args.steps:,} steps each), its bounds calibrated at 95 % on its own validation blocks; tested on "
        "pairs it never saw. *Under bound*: the share of test errors at most their bound (the aim: 90-98 %). "
        "*Spearman*: rank correlation between bound and error over the test pairs. *Beyond the trained range*: "
        "the test pairs with a joint outside the range the model was trained on, where the bound grows. "
        "*Steepest growth*: the fastest of the per-joint rates at which the bound grows there, measured on the "
        "stage's errors with each end of each joint's range held out of its fit (`calibration/bounds.py`). "
        "Inside the range the bound is a conformal quantile times the configuration's *scale*, how large the "
        "stage's training errors are around it (`model/bounds.py`); *without the scale*: the same model with "
        "one quantile for every configuration, as before the scale, from the same validation errors. "
        "*Yardsticks*: how far anything could rank the test errors, each reading the errors themselves, so no "
        "bound can use them: the Spearman correlation between each test error and the mean error of its "
        f"{NEIGHBOURS} nearest test configurations in joint space, and of its {NEIGHBOURS} nearest in measurement "
        "order (what drifts slowly: temperature, the tracker), itself left out of both; and the bound's own scale "
        "fitted on the test errors themselves: about the most its form can rank them with the answers in hand. They "
        "are references, not ceilings: beyond the trained range a bound that grows with the distance follows the "
        "error's growth more closely than a mean over neighbours. "
        "Real cells: the held-out fifth of each series in contiguous blocks; series B lies elsewhere in the "
        "workspace than C, beyond C's range. The virtual UR10 with its shoulder in one radian: its own truth and "
        "tracker noise, trained on 1,600 poses, asked about its held-out blocks and about 600 poses beyond.\n\n"
        + table(HEAD, rows)
        + "\n\nCost of a bound, one configuration at a time (median µs over 2,000 configurations, interleaved):\n\n"
        + table(
            ["model", "FK (µs)", "FK + bound (µs)", "ratio"],
            [[label, f"{a:.1f}", f"{b:.1f}", f"{b / a:.2f}"] for label, a, b in costs],
        )
        + "\n\nThe range policies beyond the trained range (`out_of_range_policy`, `fk --out-of-range`): `warn` "
        "serves the nets everywhere, `parametric` drops them outside the trained range, `bound` serves each net "
        "(position, orientation) where its bound, grown by the nets' unchecked change beyond the range, is below "
        "the parametric stage's alone. Mean errors of the same models on the same pairs; the bounds served under "
        "`bound`. The virtual cell here is the one above without the tracker's noise: with it, the capacity "
        "selection drops the nets (1,600 poses), and every policy serves the stage alone:\n\n"
        + table(POLICY_HEAD, policy_rows)
        + f"\n\nAnother payload than the trained one ({cfg.payload_mass:g} kg), served by the same noise-free "
        "model (`payload_mass` / `payload_com`, `HybridModel.with_payload`) and checked on a cell that carries "
        f"it, {PAYLOAD_POSES} configurations inside the trained range, policy `warn`. *Calibrated bound*: the "
        "bound calibrated at the trained payload, which the model served under any payload before. *Payload "
        "bound*: what it serves now, where no measurement checked the payload: the stage's calibrated bound, "
        "plus the move that the payload change made in the stage's answer, plus the nets' whole correction "
        '(docs/model.md, "Another payload"). The 15 kg payload sits off-centre, at (0, 0.05, 0.15) m in the '
        "tip frame:\n\n" + table(PAYLOAD_HEAD, payload_rows)
    )
    write_section("bounds", "Error bounds on each answer: coverage, correlation, growth", body)


if __name__ == "__main__":
    main()
