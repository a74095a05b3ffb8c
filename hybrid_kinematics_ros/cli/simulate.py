"""``simulate``: calibration pairs from the virtual cell, written as pairs bags."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from tqdm import tqdm

from hybrid_kinematics_ros.io.pairs import PairsWriter
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.simulation.cell import VirtualCell
from hybrid_kinematics_ros.simulation.errors import SimulationError

STAMP_START_NS = 1_700_000_000_000_000_000
STAMP_STEP_NS = 10_000_000  # one static sample every 10 ms of simulated time


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("simulate", help="write calibration pairs from the virtual cell into a bag")
    p.add_argument("--robot", required=True, help="robot config YAML, or an embedded robot: ur10, rx160, kr16")
    p.add_argument("--samples", type=int, required=True, help="number of pairs")
    p.add_argument("--out", required=True, type=Path, help="output bag directory (with --split: a folder of bags)")
    p.add_argument("--seed", type=int, default=0, help="seed of the joint samples and the tracker noise")
    p.add_argument(
        "--split", help="fractions train,val,test (e.g. 0.8,0.1,0.1): writes OUT/train, OUT/val and OUT/test"
    )
    p.add_argument("--range-fraction", type=float, default=1.0, help="sample a reduced joint range about its middle")
    p.add_argument("--no-noise", action="store_true", help="noise-free tracker (the truth itself)")
    p.add_argument("--position-only", action="store_true", help="a plain reflector: positions only (zero quaternions)")
    p.set_defaults(run=run)


def parse_split(text: str | None, samples: int) -> dict[str, int]:
    if not text:
        return {"": samples}
    try:
        fractions = [float(x) for x in text.split(",")]
    except ValueError as exc:
        raise SimulationError(f"--split must be three numbers train,val,test, got '{text}'") from exc
    if len(fractions) != 3 or min(fractions) < 0 or sum(fractions) <= 0:
        raise SimulationError(f"--split must be three non-negative numbers train,val,test, got '{text}'")
    total = sum(fractions)
    counts = [round(samples * f / total) for f in fractions[:2]]
    counts.append(samples - sum(counts))
    return dict(zip(("train", "val", "test"), counts, strict=True))


def run(args: argparse.Namespace) -> int:
    cfg = load_robot_config(args.robot)
    cell = VirtualCell.from_config(cfg, noise=not args.no_noise)
    parts = parse_split(args.split, args.samples)
    if args.split:
        if args.out.exists():
            raise SimulationError(f"{args.out} exists already, not overwriting")
        args.out.mkdir(parents=True)
    summary = {}
    with tqdm(total=args.samples, unit="pair", desc="simulate") as bar:
        for index, (name, count) in enumerate(parts.items()):
            path = args.out / name if name else args.out
            with PairsWriter(path, cfg.chain.joint_names, cell.frame_id, args.position_only) as writer:
                for q, T in cell.samples(count, seed=args.seed * 10 + index, fraction=args.range_fraction):
                    stamps = STAMP_START_NS + STAMP_STEP_NS * (writer.count + np.arange(len(q)))
                    writer.write(q, T, stamps)
                    bar.update(len(q))
            summary[str(path)] = count
    print(json.dumps({"robot": cfg.name, "frame_id": cell.frame_id, "bags": summary}))
    return 0
