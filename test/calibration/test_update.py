"""update: a parent model and a few new poses from a station it never saw make a child that serves the robot as
it is now, names what changed, and leaves the parent untouched."""

from __future__ import annotations

import json

import numpy as np

from hybrid_kinematics_ros.calibration.evaluate import pose_errors_of, target_errors
from hybrid_kinematics_ros.calibration.update import update, write_updated
from hybrid_kinematics_ros.calibration.verify import place_station
from hybrid_kinematics_ros.io.pairs import write_pairs
from hybrid_kinematics_ros.model.hybrid import HybridModel
from test.calibration.test_verify import ELBOW, check_pairs, in_new_station
from test.cli.inprocess import cli

DRIFT = np.radians(0.02)


def test_a_few_poses_of_a_drifted_robot_make_a_child_that_serves_it(ur10, shoulder_model, tmp_path):
    model_dir, model, _, _ = shoulder_model
    parent_json = (model_dir / "model.json").read_bytes()
    new, later = in_new_station(check_pairs(ur10, DRIFT, seed=21)), in_new_station(check_pairs(ur10, DRIFT, seed=22))
    bag = tmp_path / "new"
    write_pairs(bag, new.subset(np.arange(64)))
    out, report = tmp_path / "child", tmp_path / "update.json"
    result = cli("update", "--model", str(model_dir), "--bag", str(bag), "--out", str(out), "--json", str(report))
    assert result.returncode == 0, result.stderr
    assert (model_dir / "model.json").read_bytes() == parent_json  # the parent stays as it was
    record = json.loads(report.read_text())
    assert record["changed"][0]["name"] == f"zero offset {ur10.chain.joint_names[ELBOW]}"
    child = HybridModel.load(out)
    assert child.manifest["parent"]["path"] == str(model_dir) and child.manifest["update"]["poses"] == 64
    # on later poses of the drifted robot from the same station: the child against the parent with the station
    # placed from the same 64 poses
    placed, _ = place_station(model, new.subset(np.arange(64)))
    parent_mm, _ = target_errors(placed.to_base(later, "base_link"), model.fk(later.q))
    errors = pose_errors_of(child, later)  # the new station is the child's, for the URDF model too ("before")
    assert np.mean(errors["hybrid"][0]) < 0.5 * np.mean(parent_mm)
    assert np.mean(errors["hybrid"][0]) < np.mean(errors["analytic"][0])


def test_the_stations_alone_are_chosen_when_the_robot_did_not_change(ur10, shoulder_model):
    _, model, _, _ = shoulder_model
    unchanged = in_new_station(check_pairs(ur10, 0.0, seed=23)).subset(np.arange(64))
    updated = update(model, [unchanged])
    assert updated.record["position_mm_mean"] <= updated.record["stations_only_position_mm_mean"] + 1e-3
    assert all(c["sigmas"] < 50 for c in updated.record["changed"])


def test_too_few_poses_and_an_existing_directory_get_one_line(ur10, shoulder_model, tmp_path):
    model_dir, *_ = shoulder_model
    bag = tmp_path / "few"
    write_pairs(bag, in_new_station(check_pairs(ur10, 0.0, seed=24)).subset(np.arange(10)))
    few = cli("update", "--model", str(model_dir), "--bag", str(bag), "--out", str(tmp_path / "child"))
    assert few.returncode == 2 and "at least 20" in few.stderr and len(few.stderr.strip().splitlines()) == 1
    taken = cli("update", "--model", str(model_dir), "--bag", str(bag), "--out", str(model_dir))
    assert taken.returncode == 2 and "exists already" in taken.stderr


def test_each_net_moves_only_as_far_as_its_held_out_blocks_choose(ur10, shoulder_model, tmp_path):
    _, model, _, _ = shoulder_model
    new = in_new_station(check_pairs(ur10, DRIFT, seed=26)).subset(np.arange(64))
    updated = update(model, [new])
    child = HybridModel.load(write_updated(model, updated, tmp_path / "child"))
    q = check_pairs(ur10, 0.0, seed=27).q
    for k, kind in enumerate(("position", "orientation")):
        tuning = updated.record["nets"][kind]
        errors = tuning["held_out_by_steps"]
        assert str(tuning["steps"]) == min(errors, key=lambda s: errors[s])
        moved = np.abs(child.residuals(q)[k] - model.residuals(q)[k]).max()
        assert (moved > 0) == (tuning["steps"] > 0) == (kind in updated.nets)
    assert child.manifest["nets"]["orientation"]["update_steps"] == updated.record["nets"]["orientation"]["steps"]
