"""Real data: a UR10 measured by a Leica tracker with a T-Mac probe (../shared/datasets/ipa-robot-accuracy,
MIT, Landgraf et al., CASE 2021), read from the raw CSV files with the shipped import specs.

Every error is measured in the tracker frame at the probe, on held-out data that no model saw, chosen as
contiguous blocks of rows (neighbouring rows of a grid are near-duplicates). Rows: the URDF model, the
geometry-only fit (joint offsets and origins: what robot_calibration or pybotics users get), the
parametric stage, the hybrid model with our recipe and with the paper's. Training runs by epochs with a
wall-clock cap, so a loaded machine gives the same models.

Usage: python -m bench.bench_real [A] [C] [CB] [all] [curve] [floor] [--minutes M] [--steps S] [--recipes R,...]

Every run writes the floor (repeatability and noise floor) to its own section; ``floor`` alone writes
only that.

The hybrid recipes named by ``--recipes`` are compared on A and C; the other parts (C tested on B, all
series together, the data-amount curve) train our recipe only, to keep the whole run near an hour.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from bench.report import table, write_section
from hybrid_kinematics_ros.calibration import train
from hybrid_kinematics_ros.calibration.evaluate import error_stats, target_errors
from hybrid_kinematics_ros.calibration.fit import fit, reference_all, split
from hybrid_kinematics_ros.calibration.floor import measurement_floor
from hybrid_kinematics_ros.calibration.recipe import Recipe
from hybrid_kinematics_ros.calibration.report import net_label, repeated_poses
from hybrid_kinematics_ros.io.import_spec import load_spec_dict, spec_from_dict
from hybrid_kinematics_ros.io.importer import import_table
from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.kinematics import approach
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.model.parametric import model_from_manifest
from hybrid_kinematics_ros.model.referencing import to_base_frame

DATA = Path(__file__).resolve().parents[2] / "shared" / "datasets" / "ipa-robot-accuracy"
SERIES = {  # name: (file, import spec, stamp start override: B and C share a spec)
    "A": ("Series_A/measurements_grid.csv", "ipa_robot_accuracy_a", None),
    "B": ("Series_B/measurements_joint_configurations.csv", "ipa_robot_accuracy_bc", None),
    "C": ("Series_C/measurements_random_poses.csv", "ipa_robot_accuracy_bc", "2020-12-01T00:00:00"),
    "D": ("Series_D/measurements_iso_cubes.csv", "ipa_robot_accuracy_d", None),
}


RECIPES = (
    "Hybrid rows: *ours* is what `train` does by default (the stage's capacity chosen from the data; the nets' "
    "ladder of sizes, the condition channels the pairs carry (here the temperature) offered to each net and "
    "taken only where its validation errors are significantly better with them, then an ensemble or a longer "
    "run); *ours + temperature* gives the nets the temperature without asking; *paper* is the paper's recipe "
    "(D4w nets on the joints alone)."
)
TITLES = {
    "A": "series A",
    "C": "series C",
    "CB": "trained on C, tested on B",
    "all": "all series together, and each alone",
    "curve": "data-amount curve on A",
}


def load_series(name: str, joints: tuple[str, ...]) -> Pairs:
    path, spec_name, start = SERIES[name]
    data = load_spec_dict(spec_name)
    if start is not None:
        data = {**data, "stamp": {**data["stamp"], "start": start}}
    return import_table(DATA / path, spec_from_dict(data, spec_name), joints).pairs.with_approach()


def repeatability_mm(pairs: Pairs) -> tuple[float, int]:
    """Mean distance of repeated measurements of one commanded pose from their mean, and the pose count."""
    label = repeated_poses(pairs.q)
    spread = []
    groups = 0
    for g in np.flatnonzero(np.bincount(label) >= 2):
        p = pairs.T[label == g, :3, 3]
        spread.extend(np.linalg.norm(p - p.mean(axis=0), axis=1))
        groups += 1
    return 1e3 * float(np.mean(spread)), groups


def noise_floor(pairs: Pairs, chain) -> tuple[float, float, int]:
    """The data's measurement floor (:func:`measurement_floor`): position (mm), orientation (deg), pairs."""
    floor = measurement_floor([pairs], chain, reference_all(chain, [pairs]))
    return (float("nan"), float("nan"), 0) if floor is None else (floor.position_mm, floor.orientation_deg, floor.pairs)


def fit_recipe(
    cfg,
    train_sets,
    preset,
    conditions,
    minutes,
    steps,
    seed=0,
    capacity=None,
    choose_capacity=True,
    out=None,
    **recipe_fields,
):
    """Fit one recipe on ``train_sets`` (a tenth of each validates); returns the model, its manifest, the
    training pairs and the seconds. ``steps``: optimiser steps per net, the budget that load does not
    change (the paper's recipe stops early on validation, or at ``minutes``). ``minutes``: the cap per net
    trained, so a recipe that trains more nets (the ladder's sizes, an ensemble's members) gets more.
    ``capacity`` and ``choose_capacity``: the stage's, as :class:`Recipe` takes them. ``out``: the model
    directory to keep (None: a temporary one). ``recipe_fields``: any other :class:`Recipe` field."""
    tr, va = zip(*[split(p, seed, (0.1, 0.0))[:2] for p in train_sets], strict=True)
    per_epoch = max(1, sum(len(p) for p in tr) // preset.batch)
    epochs = preset.max_epochs if preset.patience else max(1, steps // per_epoch)
    recipe = Recipe(
        replace(preset, max_epochs=epochs),
        minutes * preset.nets,
        seed=seed,
        capacity=capacity or {},
        choose_capacity=choose_capacity,
        payload_mass=cfg.payload_mass,
        payload_com=tuple(cfg.payload_com),
        conditions=tuple(conditions),
        offered=() if preset.name == "paper" else None,  # the paper's nets read the joints alone
        **recipe_fields,
    )
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        model, manifest = fit(cfg.chain, list(tr), list(va), list(va), out or Path(tmp) / "m", recipe)
        seconds = time.perf_counter() - start
    return model, manifest, list(tr), seconds


def model_errors(cfg, model, manifest, train_pairs, tests, hybrid_label="hybrid"):
    """Errors of the URDF model, the geometry alone, the stage and the hybrid model on the pairs of every
    test set in ``tests`` together, in each one's tracker frame at the probe."""
    # no stage served (worse than the URDF model on validation): no geometry-only fit either
    stage = manifest.get("parametric")
    geometry = None if stage is None else model_from_manifest(cfg.chain, stage, rigid=True)
    # the URDF model with its own referencing of each station: the stage's referencings carry its base and
    # tool corrections (a station seen over a small volume can move them by decimetres)
    nominal = reference_all(cfg.chain, train_pairs)
    errors: dict[str, list] = {}
    for te in tests:
        urdf = to_base_frame([te], cfg.chain, nominal)
        base = to_base_frame([te], cfg.chain, model.referencings)
        for label, pairs, T in (
            ("URDF model", urdf, model.fk(urdf.q, analytic=True)),
            *([] if geometry is None else [("geometry only", base, geometry.fk(base.q))]),
            (
                "parametric stage",
                base,
                model.fk(base.q, nets=False, conditions=model.conditions_of(base.conditions, len(base))),
            ),
            (hybrid_label, base, model.fk(base.q, conditions=model.conditions_of(base.conditions, len(base)))),
        ):
            errors.setdefault(label, []).append(target_errors(pairs, T))
    return {
        label: error_stats(*(np.concatenate([e[k] for e in parts]) for k in (0, 1))) for label, parts in errors.items()
    }


def rows_for(cfg, train_sets, test_sets, recipes, minutes, steps, seed=0):
    """Fit each recipe (preset, condition channels) once; errors of every model on each test set, in the
    tracker frame at the probe (:func:`fit_recipe`, :func:`model_errors`). Also the seconds of each fit, and
    the nets each served (:data:`SERVED`)."""
    out: dict[str, dict[str, dict]] = {}
    seconds = {}
    for recipe, (preset, conditions) in recipes.items():
        model, manifest, tr, seconds[recipe] = fit_recipe(cfg, train_sets, preset, conditions, minutes, steps, seed)
        nets = manifest.get("nets", {})
        SERVED[f"{recipe}, {', '.join(test_sets)}"] = ", ".join(
            f"{kind} " + ("off" if net.get("silenced") else net_label(net)) for kind, net in nets.items()
        )
        for name, te in test_sets.items():
            out.setdefault(name, {}).update(model_errors(cfg, model, manifest, tr, [te], f"hybrid, {recipe}"))
    return out, seconds


SERVED: dict[str, str] = {}  # each fit's nets (recipe, test sets) as it served them (report.net_label), for the text


def table_of(results: dict[str, dict[str, dict]]) -> str:
    rows = []
    for test, models in results.items():
        for label, s in models.items():
            rows.append(
                [
                    test,
                    label,
                    s["count"],
                    s["position_mm_mean"],
                    s["position_mm_p95"],
                    s["position_mm_max"],
                    s.get("orientation_deg_mean", float("nan")),
                    s.get("orientation_deg_p95", float("nan")),
                ]
            )
    head = ["test set", "model", "poses", "pos. mean (mm)", "pos. p95 (mm)", "pos. max (mm)", "ori. mean (deg)"]
    return table([*head, "ori. p95 (deg)"], rows)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("parts", nargs="*", default=["A", "C"])
    parser.add_argument(
        "--minutes",
        type=float,
        default=10.0,
        help="wall-clock cap per net trained (each size of the ladder, each member of an ensemble)",
    )
    parser.add_argument("--recipes", default="ours,ours + temperature,paper", help="comma-separated hybrid rows")
    parser.add_argument("--main", default="ours", help="the recipe of the CB, all and curve parts")
    parser.add_argument("--steps", type=int, default=20_000, help="optimiser steps per net (our recipe's budget)")
    args = parser.parse_args()
    cfg = load_robot_config("ur10")
    series = {name: load_series(name, cfg.chain.joint_names) for name in SERIES}
    fast, directions = train.PRESETS["fast"], approach.channel_names(cfg.chain.joint_names)
    every = {
        "ours": (fast, ()),
        "ours + temperature": (fast, ("temperature",)),
        "ours + approach": (fast, directions),
        "ours (4 nets)": (replace(fast, members=4), ()),
        "ours + approach (4 nets)": (replace(fast, members=4), directions),
        "paper": (train.PRESETS["paper"], ()),
    }
    recipes = {name: every[name] for name in args.recipes.split(",")}
    ours = {args.main: every[args.main]}
    held = {name: split(p, 0, (0.0, 0.2)) for name, p in series.items()}  # train, _, test (a fifth, blocks)
    intro = (
        "Real UR10 (ipa-robot-accuracy), tracker frame, at the probe; held-out fifth of each series in "
        "contiguous blocks of rows. " + ", ".join(f"{k}: {len(v)} poses" for k, v in series.items()) + "."
    )
    floor = []
    for name in ("B", "D"):
        spread, groups = repeatability_mm(series[name])
        floor.append(f"Repeatability, series {name}: {spread:.4f} mm from the mean over {groups} repeated poses.")
    floors = {name: noise_floor(series[name], cfg.chain) for name in SERIES}
    floor.append(
        "Noise floor (the mean error a perfect model would still show, from pairs of measurements of the "
        "same joints to 1 mrad: mean |Δ residual| / √2; the spread about the mean is smaller by about √2 "
        "and is not this floor): "
        + ", ".join(f"{k} {mm:.4f} mm / {deg:.4f} deg ({n} pairs)" for k, (mm, deg, n) in floors.items() if n)
        + ". A's pairs are not repeats of one command: they are grid poses commanded with other Euler angles "
        "(roll and yaw 10 deg apart at pitch 90 deg) that the controller reached with joints up to 1 mrad "
        "apart; B's and D's are the same command measured again."
    )
    write_section("real_floor", "Real UR10 data: the floor (bench_real)", "\n\n".join(floor))
    parts = [p for p in args.parts if p != "floor"]
    if not parts:
        return
    for part in parts:
        if part in ("A", "C"):
            results, seconds = rows_for(cfg, [held[part][0]], {part: held[part][2]}, recipes, args.minutes, args.steps)
        elif part == "CB":
            results, seconds = rows_for(
                cfg, [series["C"]], {"B (trained on C)": series["B"]}, ours, args.minutes, args.steps
            )
        elif part == "all":
            frames: dict[str, list[Pairs]] = {}  # one set per tracker frame, as the CLI reads them: B and C share one
            for n in SERIES:
                frames.setdefault(held[n][0].frame_id, []).append(held[n][0])
            results, seconds = rows_for(
                cfg,
                [Pairs.concatenate(group) for group in frames.values()],
                {f"{n} (all)": held[n][2] for n in SERIES},
                ours,
                args.minutes,
                args.steps,
            )
            seconds = {"all": seconds[args.main]}
            for n in SERIES:  # the target compares each series with itself trained alone: side by side
                r, s = rows_for(cfg, [held[n][0]], {f"{n} (alone)": held[n][2]}, ours, args.minutes, args.steps)
                results.update(r)
                seconds[f"{n} alone"] = s[args.main]
        elif part == "curve":
            results, seconds = {}, {}
            for count in (250, 500, 1000, 2000, 4000):  # all of them: the A part's row
                pool = held["A"][0]  # a random draw of the training fifths: the amount matters, not the place
                subset = pool.subset(np.sort(np.random.default_rng(0).permutation(len(pool))[:count]))
                r, s = rows_for(
                    cfg,
                    [subset],
                    {f"A, {count} train": held["A"][2]},
                    ours,
                    args.minutes,
                    args.steps,
                )
                results.update(r)
                seconds.update({f"{count}": s[args.main]})
        else:
            raise SystemExit(f"unknown part {part}")
        timing = "Training time per model (referencing, parametric stage, nets): " + ", ".join(
            f"{k} {v:.0f} s" for k, v in seconds.items()
        )
        served = "Nets served (`+ temperature`: the net took the channel offered): " + "; ".join(
            f"{k}: {v}" for k, v in SERVED.items()
        )
        SERVED.clear()
        # each part its own section, written as soon as it is done: parts can be rerun one at a time
        write_section(
            f"real_{part}",
            f"Real UR10 data, {TITLES[part]} (bench_real)",
            f"{intro} {RECIPES}\n\n{table_of(results)}\n\n{timing}.\n\n{served}.",
        )


if __name__ == "__main__":
    main()
