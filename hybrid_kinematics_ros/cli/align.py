"""``align``: a raw recording (joint states + tracker poses) to a calibration-pairs bag."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from hybrid_kinematics_ros.calibration.alignment import AlignOptions, align_raw
from hybrid_kinematics_ros.cli.common import add_robot_args, chain_from_args
from hybrid_kinematics_ros.io.pairs import RAW_JOINTS_TOPIC, RAW_POSE_TOPIC, write_pairs


def add_align_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--joints-topic", default=RAW_JOINTS_TOPIC, help="raw joint-state topic")
    p.add_argument("--tracker-topic", default=RAW_POSE_TOPIC, help="raw tracker-pose topic")
    p.add_argument(
        "--offset-s",
        type=float,
        help="tracker-minus-robot clock offset at the first joint state (s); default: estimate",
    )
    p.add_argument("--skew-ppm", type=float, default=0.0, help="with --offset-s: the tracker clock's skew (ppm)")
    p.add_argument("--max-gap-s", type=float, default=0.02, help="longest tracker gap to interpolate across (s)")
    p.add_argument("--max-joint-speed", type=float, default=1.0, help="reject samples above this joint speed (rad/s)")
    p.add_argument("--static-min-s", type=float, default=0.0, help="> 0: one averaged pair per still window")
    p.add_argument("--frame-id", help="frame of the pairs, e.g. the base link when the tracker frame is the base")


def align_options(args: argparse.Namespace) -> AlignOptions:
    return AlignOptions(
        max_gap_s=args.max_gap_s,
        max_joint_speed=args.max_joint_speed,
        offset_s=args.offset_s,
        skew_ppm=args.skew_ppm,
        still_min_s=args.static_min_s,
    )


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("align", help="turn a raw recording into calibration pairs")
    p.add_argument("--bag", required=True, type=Path, help="raw recording (rosbag2 MCAP)")
    p.add_argument("--out", required=True, type=Path, help="pairs bag to write")
    add_robot_args(p)
    add_align_args(p)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    chain = chain_from_args(args)
    result, rec = align_raw(args.bag, chain, align_options(args), args.frame_id, args.joints_topic, args.tracker_topic)
    write_pairs(args.out, result.pairs)
    print(
        json.dumps(
            {
                "pairs": len(result.pairs),
                "out": str(args.out),
                "clock_offset_ms": result.offset_s * 1e3,
                "clock_skew_ppm": result.skew_ppm,
                "rejected": dict(result.rejected),
                "frame_id": result.pairs.frame_id,
                "truncated_recording": rec.truncated,
            }
        )
    )
    return 0
