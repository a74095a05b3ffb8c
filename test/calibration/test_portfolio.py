"""The portfolio's guard: small cells of ``simulation.portfolio``, fixed seeds and step budgets, each held to
a bound set against its own floor, so that a change that makes any of them worse fails here.

The bounds were set from measured figures (in the comments) with about 25 % of headroom over the floor.
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from hybrid_kinematics_ros.calibration import train
from hybrid_kinematics_ros.calibration.capacity import RESOLUTION
from hybrid_kinematics_ros.calibration.evaluate import error_stats, target_errors
from hybrid_kinematics_ros.calibration.fit import fit, identify_stations, reference_all, split
from hybrid_kinematics_ros.calibration.recipe import CAPACITY_SETTINGS, Recipe
from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.kinematics import se3
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.model.referencing import to_base_frame
from hybrid_kinematics_ros.simulation.cell import VirtualCell
from hybrid_kinematics_ros.simulation.portfolio import TRACKER_FAR, CellSpec, build_cell
from hybrid_kinematics_ros.simulation.sampling import sample_joints

CLEAN = CellSpec("UR10: geometry and compliance", poses=800, test_poses=400, effects={"gear": False, "bending": False})
GEARS = CellSpec(
    "UR10: gear harmonics, tracker 3 m away, outliers", poses=1500, test_poses=400, tracker=TRACKER_FAR, outliers=0.004
)
REFLECTOR = CellSpec("UR10: plain reflector", poses=800, test_poses=400, tracker=TRACKER_FAR, plain_reflector=True)
# a short walk, tested on another that mostly leaves its joint range: what the stage carries, not what it fits
SHORT = CellSpec("UR10: 300 poses, tracker 3 m away, outliers", poses=300, tracker=TRACKER_FAR, outliers=0.004)


@pytest.fixture(scope="module")
def geared():
    """The geared cell and its stage with the capacity chosen: the floor test and the rule's test read it."""
    cell = build_cell(GEARS)
    return cell, *stage_errors(cell)


def stage_errors(cell, **capacity):
    """The parametric stage with its capacity chosen (or given) from the training pairs: held-out stats."""
    cfg = cell.config
    train_pairs = [cell.train]
    refs, result = identify_stations(
        cfg.chain, train_pairs, reference_all(cfg.chain, train_pairs), (cfg.payload_mass, cfg.payload_com), 0, capacity
    )
    base = to_base_frame([cell.test], cfg.chain, refs)
    return error_stats(*target_errors(base, result.model.fk(base.q))), result


@pytest.mark.parametrize(
    ("spec", "bound"),
    [
        # the stage alone: its cubic and signed compliances, cyclic errors and map carry what the truth has
        (CLEAN, 1.3),  # measured 1.04x its floor (2.57x before the cubic compliance)
        (GEARS, 1.3),  # measured 1.01x (2.83x)
        (REFLECTOR, 1.35),  # measured 1.09x (2.85x)
    ],
    ids=["clean", "gears-tracker-outliers", "reflector"],
)
def test_stage_lies_near_the_floor_of_each_cell(spec, bound, request):
    if spec is GEARS:  # shared with the rule's test
        cell, stats, result = request.getfixturevalue("geared")
    else:
        cell = build_cell(spec)
        stats, result = stage_errors(cell)
    assert stats["position_mm_mean"] <= bound * cell.floor["position_mm_mean"], (stats, cell.floor, result.capacity)
    if not spec.plain_reflector:
        assert stats["orientation_deg_mean"] <= bound * cell.floor["orientation_deg_mean"]  # measured 1.03x, 1.01x


def test_a_short_walk_gets_the_capacity_that_carries_beyond_it():
    """Folds that hold out a contiguous fifth of the recording judge a candidate by how it carries to poses
    the rest did not visit. Interleaved folds (every fifth block) chose 5 harmonics here, fitted between the
    blocks: 2.14x the floor in position and 3.45x in orientation on the other walk."""
    cell = build_cell(SHORT)
    stats, result = stage_errors(cell)
    assert result.capacity["chosen"]["harmonics"] == 2, result.capacity["chosen"]  # the truth's: 1 and 2
    assert stats["position_mm_mean"] <= 2.06 * cell.floor["position_mm_mean"]  # measured 1.98x
    assert stats["orientation_deg_mean"] <= 2.9 * cell.floor["orientation_deg_mean"]  # measured 2.45x


def test_capacity_choices_are_recorded_and_follow_the_rule(geared):
    """Each choice is the simplest candidate within the validation noise (or a micrometre) of the best,
    recorded with every candidate's held-out figures; a cell whose joints have cyclic errors gets harmonics."""
    _, _, result = geared
    decisions = {d["setting"]: d for d in result.capacity["decisions"]}
    assert decisions["harmonics"]["chosen"] > 0
    for decision in decisions.values():
        rows = decision["candidates"]
        labels = [c["candidate"] for c in rows]
        chosen = labels.index(decision["chosen"])
        margin = [max(c["noise_mm"], 1e3 * RESOLUTION) for c in rows]
        assert rows[chosen]["worse_than_best_mm"] <= margin[chosen] + 1e-12
        # no simpler candidate was within the noise
        assert all(c["worse_than_best_mm"] > m for c, m in zip(rows[:chosen], margin, strict=False))
        assert all(c["val_position_mm"] > 0 for c in rows)


def test_given_settings_are_kept_and_recorded():
    cell = build_cell(CLEAN)
    _, result = stage_errors(cell, harmonics=3, map_step=0.0)
    decisions = {d["setting"]: d for d in result.capacity["decisions"]}
    assert decisions["harmonics"] == {"setting": "harmonics", "chosen": 3, "given": True}
    assert sum(p.kind == "harmonic" for p in result.params) == 2 * 3 * cell.config.chain.dof


def test_hybrid_is_no_worse_than_its_stage_and_near_the_floor(geared, tmp_path):
    """The whole ``fit`` on the geared cell with a fixed step budget: the nets may only help. The stage takes
    the capacity chosen on the cell (the tests above test that choice)."""
    cell, _, chosen = geared
    cfg = cell.config
    tr, va, _ = split(cell.train, 0, (0.1, 0.0))
    preset = replace(train.PRESETS["fast"], max_epochs=800)  # 1 step an epoch at 1,350 pairs: 800 steps
    capacity = {k: v for k, v in chosen.capacity["chosen"].items() if k in CAPACITY_SETTINGS}
    recipe = Recipe(
        preset, 5.0, payload_mass=cfg.payload_mass, payload_com=tuple(cfg.payload_com), capacity=capacity,
        choose_capacity=False,
    )  # fmt: skip
    model, manifest = fit(cfg.chain, tr, va, va, tmp_path / "m", recipe)
    assert manifest["recipe"]["capacity"] == json.loads(json.dumps(capacity))  # the stage's settings, recorded
    base = to_base_frame([cell.test], cfg.chain, model.referencings)
    stage = error_stats(*target_errors(base, model.fk(base.q, nets=False)))
    hybrid = error_stats(*target_errors(base, model.fk(base.q)))
    assert hybrid["position_mm_mean"] <= 1.05 * stage["position_mm_mean"]
    assert hybrid["position_mm_mean"] <= 1.3 * cell.floor["position_mm_mean"], (hybrid, cell.floor)
    assert np.isfinite(hybrid["orientation_deg_mean"])


def test_a_noise_free_cell_gets_no_terms_that_only_fit_inside_its_range():
    """Noise-free pairs make the validation noise vanish: without a floor on the difference that counts,
    40 harmonics beat the truth's 2 by a fraction of a micrometre, and outside the joints' trained range
    they extrapolate to 0.09 mm (measured). Trained on the middle 60 % of every joint, tested on all of it."""
    cfg = load_robot_config("ur10")
    cell = VirtualCell.from_config(cfg, noise=False)

    def pairs(n: int, seed: int, fraction: float) -> Pairs:
        q = sample_joints(cfg.chain, n, np.random.default_rng(seed), fraction)
        T = cell.measure(q, np.random.default_rng(seed + 1))
        return Pairs(q, T, np.arange(n), cfg.chain.joint_names, cfg.base_link)

    train_pairs, test = pairs(3000, 1, 0.6), pairs(2000, 3, 1.0)
    refs = reference_all(cfg.chain, [train_pairs])
    _, result = identify_stations(cfg.chain, [train_pairs], refs, (cfg.payload_mass, cfg.payload_com), 0)
    outside = np.any((test.q < train_pairs.q.min(0)) | (test.q > train_pairs.q.max(0)), axis=1)
    position, _ = se3.pose_errors(test.T, result.model.fk(test.q))
    assert result.capacity["chosen"]["harmonics"] < 40
    assert position[outside].mean() < 0.06, result.capacity["chosen"]  # measured 0.045 mm (0.091 mm before)
    assert position[~outside].mean() < 0.005  # measured 0.0024 mm
