"""``train``: pairs bags to a hybrid model directory."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import TextIO

from tqdm import tqdm

from hybrid_kinematics_ros.calibration import train
from hybrid_kinematics_ros.calibration.fit import fit, load_pairs, split
from hybrid_kinematics_ros.cli.common import add_robot_args, chain_from_args, payload_from_args

PLAIN_INTERVAL_S = 5.0  # off a terminal: one progress line this often


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train the residual nets from pairs bags into a model directory")
    p.add_argument("--bag", nargs="+", required=True, help="pairs bag(s) to train on")
    add_robot_args(p)
    p.add_argument("--out", required=True, type=Path, help="model directory to create")
    p.add_argument("--preset", default="fast", choices=sorted(train.PRESETS), help="training recipe (default fast)")
    p.add_argument("--arch-position", help="architecture of the position net (D1, D4, D4w, D4W, Rw, Rd, mlp:WxD)")
    p.add_argument("--arch-orientation", help="architecture of the orientation net")
    p.add_argument(
        "--max-minutes", type=float, default=5.0, help="wall-clock training budget (nets train side by side)"
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--raw-frame-id", help="raw recordings: frame of their pairs (the base link if the tracker frame is it)"
    )
    p.add_argument(
        "--parametric",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="identify the elasto-geometric stage before the nets (default on; --no-parametric: nets on the URDF)",
    )
    p.add_argument("--payload-mass", type=float, help="kg, with --urdf (a --robot config has its own)")
    p.add_argument("--payload-com", type=float, nargs=3, metavar=("X", "Y", "Z"), help="m, in the tip frame")
    p.add_argument("--val-bag", nargs="+", help="separate validation bag(s); default: 10%% of --bag")
    p.add_argument("--test-bag", nargs="+", help="separate test bag(s); default: 10%% of --bag")
    p.set_defaults(run=run)


class Progress:
    """Training progress per net: epoch, loss and validation error, advancing with training time.

    On a terminal, one tqdm bar per net. Off a terminal (CI logs, ``make demo > log``) tqdm's redraws
    would be thousands of carriage-return and cursor-movement lines, so one plain line is printed every
    ``interval`` seconds instead, and a last one at the end.
    """

    def __init__(
        self,
        seconds: float,
        kinds: tuple[str, ...] = train.KINDS,
        stream: TextIO | None = None,
        interval: float = PLAIN_INTERVAL_S,
    ) -> None:
        self.stream = sys.stderr if stream is None else stream
        self.total = round(seconds)
        self.plain = not _is_terminal(self.stream)
        self.interval = interval
        self.latest: dict[str, dict] = {}
        self._last_line = time.monotonic()
        self.bars = (
            {}
            if self.plain
            else {
                kind: tqdm(
                    total=self.total,
                    desc=f"{kind:<11}",
                    unit="s",
                    position=i,
                    leave=True,
                    file=self.stream,
                    bar_format="{desc} {bar} {n_fmt}/{total_fmt} s {postfix}",
                )
                for i, kind in enumerate(kinds)
            }
        )

    @staticmethod
    def describe(entry: dict) -> str:
        unit = train.UNIT[entry["kind"]][0]
        return (
            f"epoch {entry['epoch']} loss {entry['loss']:.4f} val {entry[f'val_{unit}']:.5f} {unit} "
            f"best {entry[f'best_val_{unit}']:.5f} {unit}"
        )

    def __call__(self, entry: dict) -> None:
        if self.plain:
            self.latest[entry["kind"]] = entry
            if time.monotonic() - self._last_line >= self.interval:
                self._print_line()
            return
        bar = self.bars[entry["kind"]]
        bar.n = min(round(entry["seconds"]), bar.total)
        bar.set_postfix_str(self.describe(entry))

    def _print_line(self) -> None:
        parts = [
            f"{kind} {min(round(e['seconds']), self.total)}/{self.total} s {self.describe(e)}"
            for kind, e in self.latest.items()
        ]
        print("train: " + "; ".join(parts), file=self.stream, flush=True)
        self._last_line = time.monotonic()

    def write(self, line: str) -> None:
        """A log line that does not break the bars."""
        if self.plain:
            print(line, file=self.stream, flush=True)
        else:
            tqdm.write(line, file=self.stream)

    def close(self) -> None:
        if self.plain and self.latest:
            self._print_line()
        for bar in self.bars.values():
            bar.close()


def _is_terminal(stream: TextIO) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):  # closed or file-like without isatty
        return False


def run(args: argparse.Namespace) -> int:
    chain = chain_from_args(args)
    pairs = load_pairs(args.bag, chain, args.raw_frame_id, allow_tracker_frame=True)
    if args.val_bag or args.test_bag:
        train_pairs, val_pairs, test_pairs = split(
            pairs, args.seed, (0.0 if args.val_bag else 0.1, 0.0 if args.test_bag else 0.1)
        )
        val_pairs = load_pairs(args.val_bag, chain, allow_tracker_frame=True) if args.val_bag else val_pairs
        test_pairs = load_pairs(args.test_bag, chain, allow_tracker_frame=True) if args.test_bag else test_pairs
    else:
        train_pairs, val_pairs, test_pairs = split(pairs, args.seed)
    print(
        f"pairs: {len(train_pairs)} train, {len(val_pairs)} validation, {len(test_pairs)} test"
        + (f"; dropped {dict(pairs.dropped)}" if pairs.dropped else "")
    )
    progress = Progress(60.0 * args.max_minutes, ("position",) if pairs.position_only else train.KINDS)
    try:
        _, manifest = fit(
            chain,
            train_pairs,
            val_pairs,
            test_pairs,
            args.out,
            train.preset(args.preset),
            args.max_minutes,
            seed=args.seed,
            arch={"position": args.arch_position, "orientation": args.arch_orientation},
            data_summary={"bags": [str(b) for b in args.bag], "dropped": dict(pairs.dropped)},
            progress=progress,
            parametric=args.parametric,
            payload=payload_from_args(args),
            log=progress.write,
        )
    finally:
        progress.close()
    test = manifest["metrics"]["test"]
    print(
        json.dumps(
            {
                "model": str(args.out),
                "training_seconds": manifest["training_seconds"],
                "test_analytic": test["analytic"],
                **({"test_parametric": test["parametric"]} if "parametric" in test else {}),
                "test_hybrid": test["hybrid"],
            }
        )
    )
    return 0
