"""Calibrating from poses that keep one tool orientation (a drilling or inspection path): the referencing
holds the target offset the poses cannot determine at its prior and says so, a few turned poses determine it,
"before" is the URDF model with its own referencing, and the served model never loses to that rigid-only one.
The cells are the portfolio's surface cells (``simulation.portfolio.SURFACE_CELLS``), made smaller."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from hybrid_kinematics_ros.calibration import train
from hybrid_kinematics_ros.calibration.evaluate import target_errors
from hybrid_kinematics_ros.calibration.fit import fit, reference_all, split, worse_than_rigid
from hybrid_kinematics_ros.calibration.recipe import Recipe
from hybrid_kinematics_ros.calibration.summary import capacity_lines
from hybrid_kinematics_ros.kinematics import fk, se3
from hybrid_kinematics_ros.model.referencing import to_base_frame
from hybrid_kinematics_ros.simulation.portfolio import SURFACE_CELLS, TRACKER_FAR, build_cell
from hybrid_kinematics_ros.simulation.tracker import Tracker

SURFACE, REFLECTOR, TURNED = (replace(spec, poses=800, test_poses=300) for spec in SURFACE_CELLS)
PRESET = replace(train.PRESETS["fast"], arch="mlp:32x2:silu", max_epochs=5, ensemble=1)


def test_the_surface_cell_keeps_one_tool_orientation():
    cell = build_cell(SURFACE)
    rotations = cell.train.T[:, :3, :3]
    spread = np.degrees(se3.rotation_angle(rotations @ np.swapaxes(rotations[:1], 1, 2)))
    assert spread.max() < 0.2
    turned = build_cell(TURNED).train.T[:, :3, :3]
    assert np.degrees(se3.rotation_angle(turned @ np.swapaxes(turned[:1], 1, 2))).max() > 25.0


@pytest.mark.parametrize("spec", [SURFACE, REFLECTOR], ids=["6-D", "position-only"])
def test_the_offset_the_poses_do_not_determine_stays_at_the_prior_and_is_named(spec):
    cell = build_cell(spec)
    (ref,) = reference_all(cell.config.chain, [cell.train]).values()
    assert np.allclose(ref.flange_to_target[:3, 3], 0.0, atol=1e-9)  # the config's tool: the chain's tip
    (note,) = ref.undetermined
    assert "every direction" in note and "turn the tool" in note
    assert ref.rms_position_mm < 1.0  # the tracker's placement absorbs the offset along the path


def test_a_few_turned_poses_determine_the_offset():
    cell = build_cell(TURNED)
    (ref,) = reference_all(cell.config.chain, [cell.train]).values()
    assert ref.undetermined == ()
    truth = Tracker.from_config(TRACKER_FAR).flange_to_target[:3, 3]
    # the URDF model's referencing: its own errors leave a fraction of a millimetre of a 0.11 m offset
    assert np.linalg.norm(ref.flange_to_target[:3, 3] - truth) < 1e-3


def test_one_orientation_trains_a_model_no_worse_than_the_rigid_one_and_reports_like_with_like(tmp_path):
    cell = build_cell(SURFACE)
    chain = cell.config.chain
    tr, va, _ = split(cell.train, 0, (0.1, 0.0))
    model, manifest = fit(chain, tr, va, cell.test, tmp_path / "m", Recipe(PRESET, 1.0))
    assert model.referencing.undetermined, "the served referencing keeps the note"
    test = manifest["metrics"]["test"]
    # "before": the URDF model with the tracker and target fitted to it alone, on the same held-out poses
    rigid = to_base_frame([cell.test], chain, reference_all(chain, [tr]))
    before = target_errors(rigid, fk.fk(chain, rigid.q))[0].mean()
    assert test["analytic"]["position_mm_mean"] == pytest.approx(before, rel=1e-9)
    assert test["hybrid"]["position_mm_mean"] < test["analytic"]["position_mm_mean"]
    assert not manifest["rigid_candidate"]["worse"]
    assert any("target offset partly held" in line for line in capacity_lines(manifest))  # the report's summary


def test_a_served_model_worse_than_the_rigid_one_is_caught_and_a_tie_is_not():
    cell = build_cell(SURFACE)
    chain = cell.config.chain
    rigid = to_base_frame([cell.test], chain, reference_all(chain, [cell.train]))
    rigid_mm = target_errors(rigid, fk.fk(chain, rigid.q))[0]
    rng = np.random.default_rng(0)
    assert worse_than_rigid(rigid_mm + 0.05, rigid_mm)["worse"]
    assert not worse_than_rigid(rng.permutation(rigid_mm), rigid_mm)["worse"]
    assert not worse_than_rigid(rigid_mm, rigid_mm)["worse"]
