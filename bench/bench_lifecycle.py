"""A calibration's life after its first fit, on the real UR10 and a virtual one.

- ``lifecycle_real``: a model of series A (``train``'s recipe, four fifths in contiguous blocks) met again on
  series D, measured months later from a tracker station it never saw. Every tenth of D's poses (64, spread over
  the run) is the check, the other 568 the test. Compared on the test: A's model with D's station placed from
  the check (the stations alone), ``update`` from the check, a model of the check alone, and a retrain of A's
  training part with the check as a second station.
- ``lifecycle_verify_real``: ``verify`` with A's model on A's held-out fifth and on all of D.
- ``lifecycle_compare``: A's model against a model of series C, both with ``train``'s recipe.
- ``lifecycle_monitor``: the tracker monitor on the simulated cell's raw streams (tracker clock 12.3 ms ahead,
  1 kHz, a station the model never saw): ten minutes of an unchanged robot, and the shoulder lift joint slipping
  by 0.2 mrad after five minutes, for five trajectories each.
- ``lifecycle_verify`` (on the monitor's model): ``verify`` with 30 check poses, 100 draws each of an unchanged
  robot, a 0.1 mrad joint offset and a tool moved by 0.1 mm, with the target held and refitted.
- ``lifecycle_sigma``: a virtual UR10 identified 20 times, each parameter's spread against its reported σ, over
  new poses and new noise (what σ claims), and over new noise on the same poses.

Usage: python -m bench.bench_lifecycle [--steps S] [--sections SECTION ...]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.bench_export import trained_on_a
from bench.bench_real import fit_recipe, load_series
from bench.report import table, write_section
from hybrid_kinematics_ros.calibration import train
from hybrid_kinematics_ros.calibration.compare import compare
from hybrid_kinematics_ros.calibration.evaluate import pose_errors_of, target_errors
from hybrid_kinematics_ros.calibration.fit import split
from hybrid_kinematics_ros.calibration.monitor import DriftMonitor, MonitorOptions
from hybrid_kinematics_ros.calibration.parametric import identify
from hybrid_kinematics_ros.calibration.update import update, write_updated
from hybrid_kinematics_ros.calibration.verify import Tolerance, place_station, verify
from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.model.hybrid import HybridModel
from hybrid_kinematics_ros.simulation.cell import VirtualCell
from hybrid_kinematics_ros.simulation.recording import PLACED, RecordingSpec, simulated_recording
from hybrid_kinematics_ros.simulation.sampling import sample_joints
from hybrid_kinematics_ros.simulation.tracker import Tracker
from hybrid_kinematics_ros.simulation.trajectory import JointStep

TOLERANCE_MM = 0.1
CHECK_EVERY = 10
SECTIONS = (
    "lifecycle_real",
    "lifecycle_verify_real",
    "lifecycle_compare",
    "lifecycle_sigma",
    "lifecycle_monitor",
    "lifecycle_verify",
)
SLIP_RAD = 2e-4  # the live monitor's slip: 0.2 mrad on the shoulder lift joint
STREAM_S = 600.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--steps", type=int, default=6000, help="optimiser steps per net")
    parser.add_argument("--sections", nargs="+", default=list(SECTIONS), choices=SECTIONS)
    args = parser.parse_args()
    if "lifecycle_sigma" in args.sections:
        sigma_section()
    if {"lifecycle_monitor", "lifecycle_verify"} & set(args.sections):
        virtual_sections(args.steps, args.sections)
    if {"lifecycle_real", "lifecycle_verify_real", "lifecycle_compare"} & set(args.sections):
        with tempfile.TemporaryDirectory() as tmp:
            model, train_pairs, held_out = trained_on_a(args.steps, Path(tmp) / "a")
            if "lifecycle_real" in args.sections:
                real_section(model, train_pairs, held_out, args.steps)
            if "lifecycle_verify_real" in args.sections:
                body = _verify_table(model, held_out, load_series("D", model.chain.joint_names))
                write_section("lifecycle_verify_real", "verify on the real UR10 (bench_lifecycle)", body)
            if "lifecycle_compare" in args.sections:
                compare_section(model, args.steps)


def _stats(pos_mm: np.ndarray, rot_deg: np.ndarray) -> list[str]:
    return [f"{np.mean(pos_mm):.4f}", f"{np.percentile(pos_mm, 95):.4f}", f"{np.nanmean(rot_deg):.4f}"]


def real_section(model: HybridModel, train_pairs: Pairs, held_out: Pairs, steps: int) -> None:
    cfg = load_robot_config("ur10")
    series_d = load_series("D", cfg.chain.joint_names)
    pick = np.zeros(len(series_d), dtype=bool)
    pick[::CHECK_EVERY] = True
    check, test = series_d.subset(np.flatnonzero(pick)), series_d.subset(np.flatnonzero(~pick))
    rows = []
    start = time.perf_counter()
    placed, _ = place_station(model, check)
    seconds = time.perf_counter() - start
    tips = model.fk(test.q, conditions=model.conditions_of(test.conditions, len(test)))
    rows.append(
        [
            "A's model, D's station placed from the check",
            *_stats(*target_errors(placed.to_base(test, "base_link"), tips)),
            f"{seconds:.1f}",
        ]
    )
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        updated = update(model, [check])
        child = HybridModel.load(write_updated(model, updated, Path(tmp) / "child"))
        seconds = time.perf_counter() - start
        rows.append(
            [
                f"update from the check ({_weight(updated.record)})",
                *_stats(*pose_errors_of(child, test)["hybrid"]),
                f"{seconds:.1f}",
            ]
        )
    for label, sets in (
        ("the check alone, trained", [check]),
        ("A's training part and the check, trained", [train_pairs, check]),
    ):
        start = time.perf_counter()
        fitted, *_ = fit_recipe(cfg, sets, train.PRESETS["fast"], (), 10.0, steps)
        seconds = time.perf_counter() - start
        rows.append([label, *_stats(*pose_errors_of(fitted, test)["hybrid"]), f"{seconds:.0f}"])
    head = ["model", "pos. mean (mm)", "pos. p95 (mm)", "ori. mean (deg)", "seconds"]
    body = (
        f"Real UR10: A's model from {len(train_pairs)} poses; D's check {len(check)} poses (every "
        f"{CHECK_EVERY}th), its test the other {len(test)}, in D's tracker frame at its probe.\n\n"
        + table(head, rows)
        + "\n\nupdate's choice of the prior's weight, each judged on 4 held-out blocks of the check by the error "
        + "the fit weighs (position and orientation × the orientation length); means; inf: the stations alone:\n\n"
        + table(*_by_weight(updated.record))
        + "\n\nEach net tuned on what the chosen stage leaves, judged on the same blocks (0 steps keeps the "
        + "parent's net):\n\n"
        + table(*_by_steps(updated.record))
        + "\n\nWhat update changed most (σ: the parent's):\n\n"
        + table(["parameter", "from", "to", "unit", "change (σ)"], _changes(updated.record["changed"][:6]))
    )
    write_section(
        "lifecycle_real", "A calibration met again: verify and update on the real UR10 (bench_lifecycle)", body
    )


def _by_steps(record: dict) -> tuple[list[str], list[list[str]]]:
    """Each net's held-out mean after every count of steps tried, the chosen count marked."""
    nets = record["nets"]
    steps = list(next(iter(nets.values()))["held_out_by_steps"]) if nets else []
    head = ["net", *[f"{s} steps" for s in steps]]
    rows = []
    for kind, tuning in nets.items():
        unit = "mm" if kind == "position" else "deg"
        by = tuning["held_out_by_steps"]
        marked = [f"**{by[s]:.4f}**" if s == str(tuning["steps"]) else f"{by[s]:.4f}" for s in steps]
        rows.append([f"{kind} ({unit})", *marked])
    return head, rows


def _by_weight(record: dict) -> tuple[list[str], list[list[str]]]:
    """Every other weight tried, the chosen one and the stations alone, with their held-out means."""
    by = record["held_out_by_weight"]
    chosen = "inf" if record["prior_weight"] is None else f"{record['prior_weight']:.3g}"
    keep = [w for k, w in enumerate(by) if k % 2 == 0 or w in (chosen, "inf")]
    head = ["prior weight", "weighed (mm)", "position (mm)", "orientation (deg)"]
    rows = []
    for w in keep:
        e = by[w]
        mark = " (chosen)" if w == chosen else ""
        rows.append([w + mark, f"{e['weighed_mm']:.4f}", f"{e['position_mm']:.4f}", f"{e['orientation_deg']:.4f}"])
    return head, rows


def _changes(changed: list[dict]) -> list[list[str]]:
    return [[c["name"], f"{c['from']:.4g}", f"{c['to']:.4g}", c["unit"], f"{c['sigmas']:.1f}"] for c in changed]


def _weight(record: dict) -> str:
    return "stations alone chosen" if record["prior_weight"] is None else f"prior weight {record['prior_weight']:g}"


def _verify_table(model: HybridModel, held_out: Pairs, series_d: Pairs) -> str:
    rows = []
    for label, pairs in (("A, held-out fifth", held_out), ("D, another station", series_d)):
        result = verify(model, [pairs], Tolerance(TOLERANCE_MM))
        rows.append(
            [
                label,
                len(result.position_mm),
                f"{np.mean(result.position_mm):.4f}",
                f"{result.over_bound} ({100 * result.over_bound / len(result.position_mm):.1f} %)",
                f"{result.p_value:.2g}",
                "drifted" if result.drifted else "still calibrated",
                "PASS" if result.tolerance["passed"] else "FAIL",
                "; ".join(f"{d['what']}: {d['explained']:.0%}" for d in result.diagnosis) or "—",
            ]
        )
    head = [
        "verify on",
        "poses judged",
        "pos. mean (mm)",
        "beyond the 95 % bound",
        "p",
        "verdict",
        f"within {TOLERANCE_MM} mm (95 %)",
        "what explains the residual",
    ]
    return "A's model (four fifths of A, contiguous blocks), D from a station it never saw (cross-fitted):\n\n" + table(
        head, rows
    )


def compare_section(model: HybridModel, steps: int) -> None:
    cfg = load_robot_config("ur10")
    train_c, _, _ = split(load_series("C", cfg.chain.joint_names), 0, (0.0, 0.2))
    model_c, *_ = fit_recipe(cfg, [train_c], train.PRESETS["fast"], (), 10.0, steps)
    result = compare(model, model_c)
    tip = result.tip_stats()
    rows = [[p["name"], f"{p['a']:.4g}", f"{p['b']:.4g}", p["unit"], f"{p['sigmas']:.1f}"] for p in result.flagged[:10]]
    body = (
        f"A's model against C's: {len(result.flagged)} of {len(result.parameters)} parameters both identified "
        f"moved by more than 3 σ. Tip difference over {tip['configurations']} configurations {result.where()}: "
        f"position max {tip['position_mm_max']:.4f} mm, p95 {tip['position_mm_p95']:.4f} mm; "
        f"orientation max {tip['orientation_deg_max']:.4f} deg, p95 {tip['orientation_deg_p95']:.4f} deg.\n\n"
        + table(["parameter (the ten largest changes)", "A", "C", "unit", "change (σ)"], rows)
    )
    write_section("lifecycle_compare", "compare: two calibrations of the real UR10 (bench_lifecycle)", body)


def sigma_section(draws: int = 20, count: int = 1000) -> None:
    cfg = load_robot_config("ur10")
    cell = VirtualCell.from_config(cfg, seed=3)
    fixed = sample_joints(cfg.chain, count, np.random.default_rng(0))
    rows = []
    for label, new_poses in (("new poses and new noise (what σ claims)", True), ("new noise on the same poses", False)):
        values, sigmas, fitted = [], [], None
        for d in range(draws):
            q = sample_joints(cfg.chain, count, np.random.default_rng(100 + d)) if new_poses else fixed
            pairs = cell.pairs(q, seed=200 + d)
            result = identify(cfg.chain, pairs.q, pairs.T, cfg.payload_mass, cfg.payload_com, seed=d)
            values.append(result.values)
            sigmas.append(result.uncertainty.sigma)
            fitted = result.identifiable if fitted is None else fitted & result.identifiable
        ratio = np.std(np.array(values)[:, fitted], axis=0, ddof=1) / np.mean(np.array(sigmas)[:, fitted], axis=0)
        inside = np.mean((ratio > 0.7) & (ratio < 1.3))
        rows.append(
            [label, int(fitted.sum()), *(f"{v:.2f}" for v in np.percentile(ratio, [10, 50, 90])), f"{100 * inside:.0f}"]
        )
    head = ["fits differ by", "parameters", "spread / σ, p10", "median", "p90", "within 0.7-1.3× σ (%)"]
    body = (
        f"Virtual UR10 (seed 3, every effect, 15 µm tracker noise), the stage identified {draws} times on "
        f"{count} poses; each parameter's spread over the fits against the mean of its reported σ.\n\n"
        + table(head, rows)
    )
    write_section("lifecycle_sigma", "Parameter σ against repeated fits (bench_lifecycle)", body)


def virtual_sections(steps: int, sections: list[str]) -> None:
    """The monitor's and verify's sections, on one virtual UR10 model of 4,000 poses."""
    cfg = load_robot_config("ur10")
    cell = VirtualCell.from_config(cfg)
    poses = cell.pairs(sample_joints(cfg.chain, 4000, np.random.default_rng(0), 0.6), seed=0)
    with tempfile.TemporaryDirectory() as tmp:
        model, *_ = fit_recipe(cfg, [poses], train.PRESETS["fast"], (), 10.0, steps, out=Path(tmp) / "m")
        if "lifecycle_monitor" in sections:
            monitor_section(model)
        if "lifecycle_verify" in sections:
            verify_section(model, cell)


def monitor_section(model: HybridModel, seeds: int = 5) -> None:
    rows = []
    for seed in range(seeds):
        quiet = _monitored(model, None, seed)
        slipped = _monitored(model, JointStep(1, SLIP_RAD, STREAM_S / 2), seed)
        after = [s for t, s in slipped if t >= STREAM_S / 2]
        flagged = next((k + 1 for k, s in enumerate(after) if s.drifted), None)
        false_alarms = sum(s.drifted for _, s in quiet)
        last = quiet[-1][1]
        rows.append(
            [seed, len(quiet), f"{last.position_mm_mean:.4f}", false_alarms, len(after), flagged or "not flagged"]
        )
    head = [
        "trajectory (seed)",
        "still poses in 10 min",
        "unchanged: mean error of the last window (mm)",
        "unchanged: poses flagged",
        "slipped: poses after the slip",
        "slipped: flagged at pose",
    ]
    body = (
        f"Virtual UR10 (every effect, 15 µm tracker noise), a model of 4,000 poses (`train`'s recipe); the "
        f"monitor with its defaults ({MonitorOptions().window}-pose window, {MonitorOptions().reference_poses} "
        f"poses to place the station, p < {MonitorOptions().p_value:g}). Slip: {SLIP_RAD * 1e3:g} mrad on "
        f"shoulder_lift_joint at {STREAM_S / 2:.0f} s.\n\n" + table(head, rows)
    )
    write_section("lifecycle_monitor", "The tracker monitor on a live stream (bench_lifecycle)", body)


CHECK_POSES = 30
DRAWS = 100


def verify_section(model: HybridModel, cell: VirtualCell) -> None:
    """``verify`` over 100 draws of 30 check poses each: an unchanged robot, a joint offset and a moved tool, from
    the model's station and from a new one, with the target held where the model has it or refitted."""
    tracker = cell.tracker
    new_station = Tracker(
        tracker.position_noise,
        tracker.orientation_noise,
        Tracker.from_config({**cell.config.tracker, **PLACED}).base_to_tracker,
        tracker.flange_to_target,
        "tracker_new",
    )
    remounted = Tracker.from_config({**cell.config.tracker, **PLACED})
    rows = []
    for label, station, slip, shift, refit in (
        ("unchanged, the model's station", tracker, 0.0, 0.0, False),
        ("unchanged, a new station", new_station, 0.0, 0.0, False),
        ("shoulder_lift_joint +0.1 mrad, a new station", new_station, 1e-4, 0.0, False),
        ("tool moved 0.1 mm, the model's station", tracker, 0.0, 1e-4, False),
        ("tool moved 0.1 mm, a new station", new_station, 0.0, 1e-4, False),
        ("unchanged, a new station and a re-mounted target, `--refit-target`", remounted, 0.0, 0.0, True),
        ("tool moved 0.1 mm, a new station, `--refit-target`", new_station, 0.0, 1e-4, True),
    ):
        drifted = named = 0
        for draw in range(DRAWS):
            result = verify(model, [_check(cell, station, slip, shift, draw)], refit_target=refit)
            drifted += result.drifted
            cause = result.diagnosis[0]["group"] if result.diagnosis else ""
            named += result.drifted and ("shoulder_lift" in cause if slip else "tool" in cause)
        rows.append([label, f"{100 * drifted / DRAWS:.0f}", f"{100 * named / DRAWS:.0f}" if slip or shift else "—"])
    head = [f"check ({CHECK_POSES} poses, {DRAWS} draws)", "drifted (%)", "drifted and the right cause first (%)"]
    body = (
        "The virtual UR10 model of the monitor section. A new station is cross-fitted: each fifth of the check is "
        "judged with the tracker placed from the other four, the target where the model has it, so a tool that "
        "moved is seen. With `--refit-target` (the target was re-mounted) the target is placed from the check too, "
        "and a tool that moved there is a target placed elsewhere.\n\n" + table(head, rows)
    )
    write_section("lifecycle_verify", "verify on the virtual cell (bench_lifecycle)", body)


def _check(cell: VirtualCell, station: Tracker, slip: float, shift: float, draw: int) -> Pairs:
    """One draw of check poses measured from ``station``: ``slip`` rad on the shoulder lift joint, the tool
    moved by ``shift`` m in a random direction."""
    rng = np.random.default_rng(1000 + draw)
    q = sample_joints(cell.config.chain, CHECK_POSES, rng, 0.6)
    reached = JointStep(1, slip, 0.0).reached(q, np.zeros(len(q)))
    direction = rng.normal(size=3)
    tool = np.eye(4)
    tool[:3, 3] = shift * direction / np.linalg.norm(direction)
    moved = Tracker(
        station.position_noise,
        station.orientation_noise,
        station.base_to_tracker,
        station.flange_to_target @ tool,
        station.frame_id,
    )
    T = moved.measure(cell.robot.fk(reached), rng)
    frame = station.frame_id or cell.config.base_link
    return Pairs(q, T, 10**9 + 10**7 * np.arange(len(q)), cell.config.chain.joint_names, frame)


def _monitored(model: HybridModel, step: JointStep | None, seed: int) -> list:
    """The monitor's statuses over a simulated stream, with their robot-clock time (s)."""
    spec = RecordingSpec(
        seconds=STREAM_S, speed=1.0, waypoints=200, tracker_hz=1000.0, frames=PLACED, step=step, seed=seed
    )
    rec = simulated_recording(spec).recording
    monitor = DriftMonitor(model)
    joints, poses = rec.joint_stamps, rec.pose_stamps
    out, k = [], 0
    for i, stamp in enumerate(joints):
        while k < len(poses) and poses[k] <= stamp:
            monitor.tracker(int(poses[k]), rec.positions[k], rec.quats[k], rec.pose_frame)
            k += 1
        status = monitor.joints(int(stamp), rec.q[i])
        if status is not None:
            out.append(((stamp - joints[0]) * 1e-9, status))
    return out


if __name__ == "__main__":
    main()
