"""``plan``: the configurations to measure, in tour order, with the accuracy they are predicted to give.

Writes ``poses.csv`` (joint names as the header, radians; with ``--candidates``, the pool's own rows unchanged),
``trajectory.yaml`` (a ``trajectory_msgs/JointTrajectory``, one point per pose to stop at) and ``plan.json``
(the summary) into ``--out``.
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.calibration.plan import (
    CyclicPrior,
    Plan,
    PlanOptions,
    TrackerView,
    draw_configurations,
    plan,
    trajectory_message,
    travel_seconds,
)
from hybrid_kinematics_ros.cli.common import (
    add_payload_args,
    add_robot_args,
    chain_from_args,
    gravity_from_args,
    payload_from_args,
    read_csv,
    write_csv,
)
from hybrid_kinematics_ros.io.errors import DataError
from hybrid_kinematics_ros.kinematics.chain import Chain

DRAWN = 20000  # configurations drawn in the working range when no pool is given


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("plan", help="choose and order the poses to measure, and predict their accuracy")
    add_robot_args(p)
    add_payload_args(p)
    p.add_argument("--count", type=int, required=True, help="how many poses to measure")
    p.add_argument("--out", type=Path, required=True, help="folder for poses.csv, trajectory.yaml and plan.json")
    p.add_argument("--candidates", type=Path, help="CSV of configurations to choose from (header: joint names, rad)")
    p.add_argument(
        "--joint-range",
        action="append",
        default=[],
        metavar="NAME:LOW:HIGH",
        help="working range of one joint (rad), within its limits; repeat for several joints",
    )
    p.add_argument("--box", type=float, nargs=6, metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"), help="target box (m)")
    p.add_argument("--tracker-xyz", type=float, nargs=3, metavar=("X", "Y", "Z"), help="tracker, base frame (m)")
    p.add_argument("--cone-deg", type=float, help="target's acceptance half-angle about the tip's z axis (deg)")
    p.add_argument("--min-distance-m", type=float, default=0.0, help="closest the tracker measures (m)")
    p.add_argument("--max-distance-m", type=float, default=float("inf"), help="farthest the tracker measures (m)")
    p.add_argument(
        "--target", type=float, nargs=3, metavar=("X", "Y", "Z"), help="plain reflector at this tip-frame offset (m)"
    )
    p.add_argument("--noise-mm", type=float, default=0.015, help="tracker position noise per axis (mm)")
    p.add_argument("--noise-deg", type=float, default=0.001, help="tracker orientation noise per axis (deg)")
    p.add_argument(
        "--floor-mm",
        type=float,
        default=0.0,
        help="mean error the stage cannot learn (mm), if known: a previous calibration's held-out error of its "
        "stage without a joint error map or backlash (train --map-step 0 --no-approach), less the tracker's noise",
    )
    p.add_argument("--floor-deg", type=float, default=0.0, help="mean orientation error it cannot learn (deg)")
    p.add_argument(
        "--prior-model",
        type=Path,
        help="a previous calibration of this robot (model directory or model.json): the prediction then counts the "
        "cyclic joint errors its stage found",
    )
    p.add_argument("--coverage-weight", type=float, default=3.0, help="weight of joint-space coverage (0: none)")
    p.add_argument("--seconds-per-pose", type=float, default=5.0, help="settling and measuring at each pose (s)")
    p.add_argument("--joint-speed", type=float, default=0.5, help="joint speed between poses (rad/s)")
    p.add_argument("--curve", action="store_true", help="also predict the accuracy for 50 to 2,000 poses")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(run=run)


def working_range(chain: Chain, specs: list[str]) -> tuple[np.ndarray, np.ndarray]:
    lower, upper = chain.lower.copy(), chain.upper.copy()
    for spec in specs:
        parts = spec.split(":")
        if len(parts) != 3:
            raise DataError(f"--joint-range {spec}: expected NAME:LOW:HIGH in radians")
        name = parts[0]
        if name not in chain.joint_names:
            raise DataError(f"--joint-range {spec}: no joint {name!r} (joints: {', '.join(chain.joint_names)})")
        try:
            low, high = float(parts[1]), float(parts[2])
        except ValueError:
            raise DataError(f"--joint-range {spec}: LOW and HIGH must be numbers (rad)") from None
        j = chain.joint_names.index(name)
        if not (chain.lower[j] <= low < high <= chain.upper[j]):
            raise DataError(
                f"--joint-range {spec}: needs LOW < HIGH within the joint's limits "
                f"[{chain.lower[j]:.4g}, {chain.upper[j]:.4g}] rad"
            )
        lower[j], upper[j] = low, high
    return lower, upper


def prior_from(path: Path, chain: Chain) -> CyclicPrior:
    """The cyclic joint errors of a previous calibration of this robot, from its model directory or model.json."""
    file = path / "model.json" if path.is_dir() else path
    try:
        manifest = json.loads(file.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise DataError(f"{file}: cannot read a model.json ({exc}); --prior-model takes a trained model") from None
    joints = manifest.get("joint_names") if isinstance(manifest, dict) else None
    if joints != list(chain.joint_names):
        raise DataError(f"{file}: joints {joints} differ from the chain's {list(chain.joint_names)}")
    return CyclicPrior.from_manifest(manifest, str(file))


def run(args: argparse.Namespace) -> int:
    chain = chain_from_args(args)
    _check(args)
    candidates, header_and_rows, lower, upper = _candidates(args, chain)
    cyclic = None if args.prior_model is None else prior_from(args.prior_model, chain)
    options = _options(args, cyclic)
    try:
        result = plan(chain, candidates, options, _view(args), lower, upper)
    except CalibrationError as exc:
        where = f"{args.candidates}: " if args.candidates else ""
        raise CalibrationError(where + str(exc)) from None
    args.out.mkdir(parents=True, exist_ok=True)
    if args.candidates:
        with (args.out / "poses.csv").open("w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(header_and_rows[0])
            writer.writerows(header_and_rows[1 + int(r)] for r in result.rows)
    else:
        write_csv(args.out / "poses.csv", list(chain.joint_names), result.q)
    message = trajectory_message(chain.joint_names, result.q, travel_seconds(result.q, options))
    (args.out / "trajectory.yaml").write_text(yaml.safe_dump(message, sort_keys=False))
    summary = result.summary()
    (args.out / "plan.json").write_text(json.dumps(summary, indent=2) + "\n")
    _say(args.out, result, summary, cyclic)
    return 0


def _check(args: argparse.Namespace) -> None:
    """Flags that contradict each other or are out of range, before anything is read."""
    if args.candidates and args.joint_range:
        raise DataError("--candidates and --joint-range: the pool is the working range; give one of them")
    if args.cone_deg is not None and not args.tracker_xyz:
        raise DataError("--cone-deg needs --tracker-xyz: the cone is checked against the direction to the tracker")
    for name, default in (("min_distance_m", 0.0), ("max_distance_m", float("inf"))):
        if getattr(args, name) != default and not args.tracker_xyz:
            raise DataError(f"--{name.replace('_', '-')} needs --tracker-xyz: the distance is to the tracker")
    for name in ("noise_mm", "noise_deg", "floor_mm", "floor_deg", "coverage_weight", "seconds_per_pose"):
        if getattr(args, name) < 0:
            raise DataError(f"--{name.replace('_', '-')} {getattr(args, name)}: must not be negative")
    if args.joint_speed <= 0:
        raise DataError(f"--joint-speed {args.joint_speed}: must be positive (rad/s)")


def _candidates(
    args: argparse.Namespace, chain: Chain
) -> tuple[np.ndarray, list[list[str]] | None, np.ndarray | None, np.ndarray | None]:
    """The pool to choose from: the rows of ``--candidates`` (with that file's header and rows as read, so
    the chosen ones are written back unchanged), or configurations drawn from the working range (with it)."""
    if not args.candidates:
        lower, upper = working_range(chain, args.joint_range)
        return draw_configurations(lower, upper, DRAWN, args.seed), None, lower, upper
    _, candidates = read_csv(args.candidates, chain.joint_names)
    with args.candidates.open(newline="") as f:
        raw = list(csv.reader(f))
    if not len(candidates):
        raise DataError(f"{args.candidates}: no rows under the header")
    return candidates, raw, None, None


def _view(args: argparse.Namespace) -> TrackerView:
    """Where the tracker stands and what it sees, as the flags give it."""
    return TrackerView(
        position=None if args.tracker_xyz is None else np.asarray(args.tracker_xyz),
        cone_deg=args.cone_deg,
        min_distance=args.min_distance_m,
        max_distance=args.max_distance_m,
        box=None if args.box is None else np.asarray(args.box).reshape(2, 3),
    )


def _options(args: argparse.Namespace, cyclic: CyclicPrior | None) -> PlanOptions:
    """The plan's options from the flags (SI units inside)."""
    payload = payload_from_args(args)
    return PlanOptions(
        count=args.count,
        target=None if args.target is None else np.asarray(args.target),
        position_noise_m=1e-3 * args.noise_mm,
        floor_mm=args.floor_mm,
        floor_deg=args.floor_deg,
        orientation_noise_rad=np.radians(args.noise_deg),
        coverage_weight=args.coverage_weight,
        seconds_per_pose=args.seconds_per_pose,
        joint_speed=args.joint_speed,
        curve=args.curve,
        seed=args.seed,
        payload_mass=payload[0],
        payload_com=payload[1],
        gravity=gravity_from_args(args),
        cyclic=cyclic,
    )


def _say(out: Path, result: Plan, summary: dict[str, Any], cyclic: CyclicPrior | None) -> None:
    """The plan's summary on stdout: its size and time, the predicted error and what it stands on."""
    predicted = result.predicted
    print(
        f"planned {len(result.rows)} poses into {out}: about {summary['measuring_time_h']} h of measuring; "
        f"predicted mean position error of the parametric stage {predicted['position_mean_mm']:.4f} mm "
        f"(parameters {predicted['parameters_part_mm']:.4f} mm, floor {predicted['floor_mm']:g} mm, "
        f"tracker noise {predicted['tracker_noise_mm']:.4f} mm); {result.parameters} identifiable parameters"
        + (f", {cyclic.harmonics} harmonics of each joint's error from --prior-model" if cyclic else "")
    )
    if "capacity" in predicted:
        chosen = predicted["capacity"]
        parts = (
            [f"{chosen['harmonics']} harmonics, ridge {chosen['harmonic_prior']:g} pairs"]
            if "harmonics" in chosen
            else []
        )
        if "orientation_length" in chosen:
            parts.append(f"orientation weighed at {chosen['orientation_length']:g} m per rad")
        print("predicted for the capacity that leaves the least: " + ", ".join(parts))
    print(f"the prediction is {result.caveat}")
    print("checked: " + ("; ".join(result.checks["checked"]) or "nothing about the tracker"))
    print("not checked: " + "; ".join(result.checks["not_checked"]))
    for row in result.curve:
        print(f"  {row['poses']:5d} poses: {row['position_mean_mm']:.4f} mm, {row['measuring_time_h']} h")
