"""Planned poses against random ones: what N measured poses give the parametric stage, and whether ``plan``
predicts it.

Real UR10 (series A, ../shared/datasets/ipa-robot-accuracy): the pool is A's block-split training part, the
test its held-out blocks. For each N, ``plan`` chooses N poses from the pool and the stage is identified on
those alone, its capacity chosen from them by cross-validation (as ``train`` does); the same for N random
poses of the pool, the mean over ``--draws`` draws. Errors are at the probe, in the tracker frame. The
prediction takes the tracker's noise from A's noise floor and what the stage cannot learn from the stage
fitted on the whole pool without a joint error map or backlash (its held-out error, less the noise): the
stage the prediction models, whose linearisation has neither. Both are properties of the cell, measured
once, and the prediction for each N adds what the parameters' covariance gives.

Virtual UR10 cell (config/ur10.yaml's truth: geometry, compliance, bending, gear ripple; the tracker's
noise): a pool of random configurations, errors against the truth at other configurations.

The stage alone is compared here: the nets' share needs a training per subset, minutes each.

Usage: python -m bench.bench_plan [--counts 60,120,250,500,1000] [--draws 5]
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np

from bench.bench_real import load_series, noise_floor
from bench.report import table, write_section
from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.calibration.evaluate import target_errors
from hybrid_kinematics_ros.calibration.fit import approach_of, identify_stations, reference_all, split
from hybrid_kinematics_ros.calibration.plan import (
    MEAN_OVER_RMS,
    CyclicPrior,
    PlanOptions,
    TrackerView,
    draw_configurations,
    plan,
    visible,
)
from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.kinematics import se3
from hybrid_kinematics_ros.kinematics.chain import chain_from_urdf
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.model.referencing import to_base_frame
from hybrid_kinematics_ros.simulation.cell import VirtualCell


def stage_errors(cfg, train: Pairs, test: Pairs) -> tuple[float, float]:
    """Mean position (mm) and orientation (deg) errors on ``test`` of the stage identified on ``train``, its
    capacity chosen from it."""
    return stage_fit(cfg, train, test)[:2]


def stage_fit(cfg, train: Pairs, test: Pairs, capacity: dict | None = None) -> tuple[float, float, CyclicPrior | None]:
    """:func:`stage_errors`, and the cyclic joint errors the stage found (what ``plan --prior-model`` reads);
    ``capacity``: settings given instead of chosen."""
    position, orientation, result = stage_result(cfg, train, test, capacity)
    return position, orientation, cyclic_of(result)


# The stage the prediction models (``plan``'s linearisation has neither a joint error map nor backlash), as
# ``train --map-step 0 --no-approach`` fits it; the rest of its capacity is chosen.
MODELLED = {"map_step": 0.0, "approach": False}


def stage_result(cfg, train: Pairs, test: Pairs, capacity: dict | None = None) -> tuple[float, float, Any]:
    """Mean position (mm) and orientation (deg) errors on ``test`` of the stage identified on ``train``, and
    the stage (``ParametricResult``); ``capacity``: settings given instead of chosen."""
    payload = (cfg.payload_mass, cfg.payload_com)
    refs = reference_all(cfg.chain, [train])
    refs, result = identify_stations(cfg.chain, [train], refs, payload, capacity=capacity, gravity=cfg.gravity)
    base = to_base_frame([test], cfg.chain, refs)
    tip = result.model.fk(result.model.approached(base.q, approach_of(base)))
    position, orientation = target_errors(base, tip)
    return float(np.mean(position)), float(np.mean(orientation)), result


def cyclic_of(result) -> CyclicPrior | None:
    """The cyclic errors of an identified stage, read as ``plan --prior-model`` reads its model.json."""
    try:
        return CyclicPrior.from_manifest({"parametric": result.manifest(), "capacity": result.capacity})
    except CalibrationError:  # the capacity selection chose no harmonics
        return None


def describe(cyclic: CyclicPrior | None) -> str:
    if cyclic is None:
        return "none chosen"
    joints = np.sqrt(np.mean(np.square(cyclic.joint_order_rms_rad), axis=1))
    return (
        f"{cyclic.harmonics} harmonics a joint, coefficients {1e6 * cyclic.rms_rad:.0f} µrad RMS, "
        f"{1e6 * joints.min():.0f}-{1e6 * joints.max():.0f} µrad by joint; the prediction takes each joint's "
        "and order's own"
    )


def options(
    cfg, count: int, noise: tuple[float, float], floor: tuple[float, float], cyclic: CyclicPrior | None
) -> PlanOptions:
    """``noise``: the tracker's per axis (mm, deg); ``floor``: the mean errors the stage cannot learn;
    ``cyclic``: the cyclic joint errors of the stage fitted on the whole pool."""
    return PlanOptions(
        count=count,
        position_noise_m=1e-3 * noise[0],
        orientation_noise_rad=np.radians(noise[1]),
        floor_mm=floor[0],
        floor_deg=floor[1],
        payload_mass=cfg.payload_mass,
        payload_com=cfg.payload_com,
        gravity=cfg.gravity,
        cyclic=cyclic,
    )


def compare(
    cfg,
    chain,
    pool_q: np.ndarray,
    error_of,
    counts,
    draws: int,
    noise: tuple,
    floor: tuple,
    cyclic: CyclicPrior | None,
    noisy_test: bool = True,
) -> list[list]:
    """One row per count: planned, random (mean ± sd of ``draws``), predicted, and the plan's hours. A test
    against the truth (``noisy_test`` False) is predicted without the test measurement's noise."""
    rng = np.random.default_rng(0)
    rows = []
    within = np.flatnonzero(visible(chain, pool_q, TrackerView(), None)[0])  # what plan may choose from
    for count in counts:
        start = time.perf_counter()
        planned = plan(chain, pool_q, options(cfg, count, noise, floor, cyclic))
        seconds = time.perf_counter() - start
        mine = error_of(planned.rows)
        random = [error_of(np.sort(rng.choice(within, count, replace=False))) for _ in range(draws)]
        # the same plan's prediction without the cyclic errors (what plan says without --prior-model)
        blind = plan(chain, pool_q, options(cfg, count, noise, floor, None)).predicted
        predicted, without = (
            p["position_mean_mm"] if noisy_test else float(np.hypot(p["parameters_part_mm"], floor[0]))
            for p in (planned.predicted, blind)
        )
        rows.append(
            [
                count,
                round(mine, 4),
                f"{np.mean(random):.4f} ± {np.std(random):.4f}",
                round(mine / np.mean(random), 3),
                round(predicted, 4),
                f"{100 * (predicted / mine - 1):+.0f} %",
                round(without, 4),
                f"{100 * (without / mine - 1):+.0f} %",
                round(planned.seconds / 3600, 2),
                round(seconds, 1),
            ]
        )
        print(rows[-1], flush=True)
    return rows


HEADERS = [
    "poses",
    "planned: stage mean (mm)",
    "random: stage mean (mm)",
    "planned / random",
    "predicted (mm)",
    "prediction off by",
    "predicted without the cyclic errors (mm)",
    "off by",
    "measuring (h, 5 s a pose)",
    "planning (s)",
]


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--counts", default="60,120,250,500,1000")
    parser.add_argument("--draws", type=int, default=5)
    args = parser.parse_args()
    counts = [int(c) for c in args.counts.split(",")]
    cfg = load_robot_config("ur10")

    series = load_series("A", cfg.chain.joint_names)
    pool, _, test = split(series, 0, (0.0, 0.2))
    noise_mm, noise_deg, _ = noise_floor(series, cfg.chain)
    per_axis = MEAN_OVER_RMS * np.sqrt(3.0)
    whole = stage_errors(cfg, pool, test)
    *modelled, cyclic = stage_fit(cfg, pool, test, MODELLED)
    floor = (
        float(np.sqrt(max(modelled[0] ** 2 - noise_mm**2, 0.0))),
        float(np.sqrt(max(modelled[1] ** 2 - noise_deg**2, 0.0))),
    )
    print(f"A: pool {len(pool)}, test {len(test)}, noise {noise_mm:.4f} mm {noise_deg:.4f} deg, {whole} {modelled}")
    # the robot measured A within its URDF's joint limits; config/ur10.yaml's narrower working range (for
    # sampling virtual cells: the shoulder lift at most 0) would leave out the rows it measured beyond
    urdf = chain_from_urdf(cfg.urdf_path, cfg.base_link, cfg.tip_link)
    measured = cfg.chain.with_limits(urdf.lower, urdf.upper)
    outside = len(pool) - int(visible(cfg.chain, pool.q, TrackerView(), None)[0].sum())
    real = compare(
        cfg,
        measured,
        pool.q,
        lambda rows: stage_errors(cfg, pool.subset(rows), test)[0],
        counts,
        args.draws,
        (noise_mm / per_axis, noise_deg / per_axis),
        floor,
        cyclic,
    )

    cell = VirtualCell.from_config(cfg, seed=3)
    rng = np.random.default_rng(1)
    lower, upper = 0.95 * cfg.chain.lower, 0.95 * cfg.chain.upper
    pool_q = draw_configurations(lower, upper, 5000, seed=2)
    pool_T = cell.measure(pool_q, rng)
    test_q = draw_configurations(lower, upper, 1000, seed=4)
    test_T = cell.robot.fk(test_q)
    stamps = 10**9 + 10**7 * np.arange(len(pool_q))

    def virtual_fit(rows: np.ndarray, capacity: dict | None = None) -> tuple[float, CyclicPrior | None]:
        train = Pairs(pool_q[rows], pool_T[rows], stamps[rows], cfg.chain.joint_names, "base_link")
        refs = reference_all(cfg.chain, [train])
        _, result = identify_stations(
            cfg.chain, [train], refs, (cfg.payload_mass, cfg.payload_com), capacity=capacity, gravity=cfg.gravity
        )
        return float(np.mean(se3.pose_errors(result.model.fk(test_q), test_T)[0])), cyclic_of(result)

    virtual_noise = (
        float(cfg.tracker.get("position_noise_mm", 0.015)),
        float(cfg.tracker.get("orientation_noise_deg", 0.001)),
    )
    virtual_whole, virtual_cyclic = virtual_fit(np.arange(len(pool_q)), MODELLED)
    virtual = compare(
        cfg,
        cfg.chain,
        pool_q,
        lambda rows: virtual_fit(rows)[0],
        counts,
        args.draws,
        virtual_noise,
        (virtual_whole, 0.0),
        virtual_cyclic,
        False,
    )
    body = (
        f"Stage alone, capacity chosen from each subset. Real A: pool {len(pool)} poses (the block-split training "
        f"part; planned within the URDF's joint limits, where the robot measured it: config/ur10.yaml's working "
        f"range would leave out {outside} of its rows), test {len(test)} held-out poses; noise floor "
        f"{noise_mm:.4f} mm / {noise_deg:.4f} deg. The stage on the whole pool, as `train` fits it: "
        f"{whole[0]:.4f} mm / {whole[1]:.4f} deg. Without a joint error map or backlash, the stage the prediction "
        f"models (`train --map-step 0 --no-approach`): {modelled[0]:.4f} mm / {modelled[1]:.4f} deg, so "
        f"{floor[0]:.4f} mm / {floor[1]:.4f} deg it cannot learn (the floor). The prediction uses those two "
        f"figures, the parameters' covariance of each plan at the orientation weight and harmonics that leave the "
        f"least, and the cyclic joint errors of that stage on the whole pool "
        f"({describe(cyclic)}: what `plan --prior-model` reads from a previous calibration's model.json); without "
        f"them, what `plan` predicts without a prior model.\n\n{table(HEADERS, real)}\n\n"
        f"Virtual UR10 (config/ur10.yaml's truth, {virtual_noise[0]} mm tracker noise per axis): pool of 5,000 "
        f"random configurations within 95 % of the limits, errors against the truth at 1,000 others; the stage "
        f"on the whole pool, without a map or backlash, {virtual_whole:.4f} mm (the prediction's floor; the test "
        f"has no noise), its cyclic "
        f"errors {describe(virtual_cyclic)}.\n\n"
        f"{table(HEADERS, virtual)}"
    )
    write_section("plan", "Planning the measurement: planned against random poses (bench_plan)", body)


if __name__ == "__main__":
    main()
