"""``train``: pairs bags to a hybrid model directory."""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from pathlib import Path
from typing import TextIO

from tqdm import tqdm

from hybrid_kinematics_ros.calibration import capacity, train
from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.calibration.fit import SPLIT_BLOCKS, Hooks, fit, load_stations, split, split_summary
from hybrid_kinematics_ros.calibration.recipe import CAPACITY_SETTINGS, Recipe
from hybrid_kinematics_ros.cli.common import (
    add_payload_args,
    add_robot_args,
    chain_from_args,
    gravity_from_args,
    payload_from_args,
)
from hybrid_kinematics_ros.kinematics import approach
from hybrid_kinematics_ros.kinematics.chain import Chain

PLAIN_INTERVAL_S = 5.0  # off a terminal: one progress line this often


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train the residual nets from pairs bags into a model directory")
    p.add_argument("--bag", nargs="+", required=True, help="pairs bag(s) to train on")
    add_robot_args(p)
    p.add_argument("--out", required=True, type=Path, help="model directory to create")
    _net_args(p)
    p.add_argument(
        "--raw-frame-id", help="raw recordings: frame of their pairs (the base link if the tracker frame is it)"
    )
    _stage_args(p)
    add_payload_args(p)
    p.add_argument("--val-bag", nargs="+", help="separate validation bag(s); default: 10%% of --bag")
    p.add_argument("--test-bag", nargs="+", help="separate test bag(s); default: 10%% of --bag")
    _condition_args(p)
    p.add_argument(
        "--shared-target",
        action="append",
        metavar="FRAME,FRAME[,...]",
        help="tracker frames whose stations saw the same target on the flange (not remounted): they share one "
        "flange-to-target transform; repeat for several groups (default: one per frame)",
    )
    p.add_argument(
        "--split-blocks",
        type=int,
        default=SPLIT_BLOCKS,
        help=f"without --val-bag/--test-bag: cut --bag into this many contiguous time blocks and hold out whole "
        f"blocks, so that neighbours of a test pair do not train (default {SPLIT_BLOCKS}; 0: single random pairs)",
    )
    p.add_argument(
        "--recipe",
        type=Path,
        help="train with the recipe of an earlier model (its directory or model.json): the same preset, budget, "
        "seed, stage capacity, payload and conditions; no recipe flag may be given with it",
    )
    p.set_defaults(run=run, defaults={a.dest: a.default for a in p._actions})


def _net_args(p: argparse.ArgumentParser) -> None:
    """The nets' recipe: preset, architectures, budget, ensemble and seed."""
    p.add_argument("--preset", default="fast", choices=sorted(train.PRESETS), help="training recipe (default fast)")
    p.add_argument(
        "--arch-position",
        help="architecture of the position net (D1, D4, D4w, D4W, Rw, Rd, mlp:WxD), or several, "
        "simplest first, comma-separated: a larger one serves only if significantly better on validation "
        "(default: the preset's, fast: mlp:64x2:silu,mlp:256x3:silu)",
    )
    p.add_argument("--arch-orientation", help="architecture(s) of the orientation net, as --arch-position")
    p.add_argument(
        "--max-minutes", type=float, default=5.0, help="wall-clock training budget (nets train side by side)"
    )
    p.add_argument(
        "--max-epochs",
        type=int,
        help="stop (and end the cosine schedule) after this many epochs: the same model on a loaded machine, "
        "given a --max-minutes that is not reached",
    )
    p.add_argument(
        "--members",
        type=int,
        help="nets averaged per residual, each from its own seed, one after the other in the same budget; "
        "given, it fixes the ensemble (1: a single net). Default: chosen on validation, the last rung of the "
        "nets' ladder being an ensemble of 4 of the size served, or, where the clock ended that net's run and "
        "training it on beats it, one longer run (preset fast; paper: none)",
    )
    p.add_argument("--seed", type=int, default=0)


def _stage_args(p: argparse.ArgumentParser) -> None:
    """Whether to identify the parametric stage, and the capacity settings given instead of chosen."""
    p.add_argument(
        "--parametric",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="identify the elasto-geometric stage before the nets (default on; --no-parametric: nets on the URDF)",
    )
    p.add_argument(
        "--drop-outliers",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="leave out the training pairs the stage leaves beyond five robust standard deviations and fit again "
        "without them (default on; --no-drop-outliers: keep them, down-weighted)",
    )
    stage = p.add_argument_group(
        "the parametric stage's capacity",
        "each is chosen by cross-validation over contiguous blocks of the training pairs unless given here; "
        "model.json and the report record every choice with its validation figures",
    )
    stage.add_argument("--elastic", choices=list(capacity.ELASTIC), help="elastic terms beside the geometry")
    stage.add_argument("--harmonics", type=int, help="harmonics of each joint's cyclic errors (0: none)")
    stage.add_argument("--harmonic-prior", type=float, help="ridge prior of each cyclic coefficient, in pairs")
    stage.add_argument("--map-step", type=float, help="rad between the joint error map's knots (0: no map)")
    stage.add_argument("--map-smoothness", type=float, help="weight of the joint error map's curvature")
    stage.add_argument(
        "--orientation-length",
        type=float,
        metavar="M_PER_RAD",
        help="weight of the orientation residuals against the position ones, m per rad (default: chosen from the "
        "ratio of the two kinds' residuals, on held-out blocks; smaller favours position)",
    )


def _condition_args(p: argparse.ArgumentParser) -> None:
    """The nets' inputs beside the joints: condition channels and the joints' approach directions."""
    p.add_argument(
        "--condition",
        action="append",
        metavar="NAME",
        help="a condition channel of the pairs (e.g. temperature) that the nets take as an input beside the joints; "
        "the node then needs its current value (parameter conditions.NAME); repeat for several",
    )
    p.add_argument(
        "--offer-conditions",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="without --condition: offer each net every condition channel the pairs carry; a net takes them only "
        "where its validation errors are significantly better with them (model.json: offered_conditions)",
    )
    p.add_argument(
        "--approach",
        action=argparse.BooleanOptionalAction,
        help="give the nets each joint's approach direction (the way it last moved, from the order of the pairs) "
        "beside the joints, or not: backlash and friction depend on it; the node follows it from /joint_states. "
        "Default: chosen from the data with the stage's capacity (always off with --no-parametric)",
    )


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


RECIPE_FLAGS = (
    "preset",
    "arch_position",
    "arch_orientation",
    "max_minutes",
    "max_epochs",
    "members",
    "seed",
    "parametric",
    *CAPACITY_SETTINGS,
    "payload_mass",
    "payload_com",
    "condition",
    "offer_conditions",
    "shared_target",
    "drop_outliers",
)


def recipe_from_args(args: argparse.Namespace, preset: train.Preset, chain: Chain) -> Recipe:
    """The recipe the flags give, or with ``--recipe`` an earlier model's (no recipe flag may then be given)."""
    if args.recipe:
        given = [f"--{name.replace('_', '-')}" for name in RECIPE_FLAGS if getattr(args, name) != args.defaults[name]]
        if given:
            raise CalibrationError(f"--recipe {args.recipe}: give the recipe or {', '.join(given)}, not both")
        return Recipe.read(args.recipe)
    mass, com = payload_from_args(args)
    gravity = gravity_from_args(args)
    return Recipe(
        preset=preset,
        max_minutes=args.max_minutes,
        seed=args.seed,
        arch={k: v for k, v in (("position", args.arch_position), ("orientation", args.arch_orientation)) if v},
        parametric=args.parametric,
        capacity={name: getattr(args, name) for name in CAPACITY_SETTINGS},
        payload_mass=mass,
        payload_com=tuple(com),
        gravity=None if gravity is None else tuple(gravity),
        conditions=(
            *(args.condition or ()),
            *(approach.channel_names(chain.joint_names) if args.approach and not args.parametric else ()),
        ),
        offered=None if args.offer_conditions else (),
        shared_targets=tuple(tuple(names.split(",")) for names in args.shared_target or ()),
        drop_outliers=args.drop_outliers,
    )


def run(args: argparse.Namespace) -> int:
    preset = train.preset(args.preset, max_epochs=args.max_epochs, members=args.members)  # before reading bags
    chain = chain_from_args(args)
    stations = load_stations(args.bag, chain, args.raw_frame_id)
    blocks = None if args.split_blocks == 0 else args.split_blocks
    fractions = (0.0 if args.val_bag else 0.1, 0.0 if args.test_bag else 0.1)
    # each station is split on its own, so that every tracker frame is referenced, validated and tested
    splits = [split(p, args.seed, fractions, blocks) for p in stations]
    train_pairs, val_pairs, test_pairs = ([s[k] for s in splits] for k in range(3))
    val_pairs = load_stations(args.val_bag, chain) if args.val_bag else val_pairs
    test_pairs = load_stations(args.test_bag, chain) if args.test_bag else test_pairs
    dropped = sum((p.dropped for p in stations), Counter())
    count = [sum(len(p) for p in parts) for parts in (train_pairs, val_pairs, test_pairs)]
    print(
        f"pairs: {count[0]} train, {count[1]} validation, {count[2]} test"
        + (f" from {len(stations)} frames ({', '.join(p.frame_id for p in stations)})" if len(stations) > 1 else "")
        + (f"; dropped {dict(dropped)}" if dropped else "")
    )
    position_only = stations[0].position_only
    recipe = recipe_from_args(args, preset, chain)
    progress = Progress(60.0 * recipe.max_minutes, ("position",) if position_only else train.KINDS)
    try:
        _, manifest = fit(
            chain,
            train_pairs,
            val_pairs,
            test_pairs,
            args.out,
            recipe,
            Hooks(
                progress=progress,
                log=progress.write,
                data_summary={
                    "bags": [str(b) for b in args.bag],
                    "dropped": dict(dropped),
                    "split": split_summary(blocks, bool(args.val_bag), bool(args.test_bag)),
                },
            ),
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
                "floor": manifest.get("floor"),
                **({"tracker_floor": manifest["tracker_floor"]} if "tracker_floor" in manifest else {}),
            }
        )
    )
    return 0
