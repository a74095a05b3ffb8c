"""verify: a check recording judged against the model's own bound, from a tracker station the model knows or
one placed from the check itself; a drift is named by the parameter group that explains it."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from bench.bench_bounds import shoulder_configurations
from hybrid_kinematics_ros.calibration.verify import Tolerance, verify
from hybrid_kinematics_ros.io.pairs import Pairs, write_pairs
from hybrid_kinematics_ros.kinematics import se3
from hybrid_kinematics_ros.simulation.cell import VirtualCell
from test.cli.inprocess import cli

ELBOW = 2  # the joint whose zero offset drifts


def check_pairs(ur10, drift_rad: float = 0.0, seed: int = 7) -> Pairs:
    """Fresh poses in the shoulder model's range, measured on its cell; the elbow's zero moved by ``drift_rad``."""
    q = shoulder_configurations(300, (-2.0, -1.0), seed=seed)
    shifted = q.copy()
    shifted[:, ELBOW] += drift_rad
    return replace(VirtualCell.from_config(ur10, noise=False).pairs(shifted, seed=seed), q=q)


def in_new_station(pairs: Pairs) -> Pairs:
    """The same measurements from a tracker standing 3 m away, in a frame the model was never referenced to."""
    station = se3.from_rotvec(np.array([2.5, -1.0, 0.4]), np.array([0.0, 0.02, 2.2]))[0]
    return replace(pairs, T=se3.inverse(station) @ pairs.T, frame_id="tracker_new")


def test_a_good_model_stays_calibrated_from_a_station_it_knows_and_from_a_new_one(ur10, shoulder_model):
    _, model, _, _ = shoulder_model
    pairs = check_pairs(ur10)
    known = verify(model, [pairs], Tolerance(0.1))
    assert not known.drifted and known.holds and known.stations["base_link"] == "the base frame"
    moved = verify(model, [in_new_station(pairs)])
    assert not moved.drifted and "placed from the other 4 fifths" in moved.stations["tracker_new"]
    assert len(moved.position_mm) == len(pairs)  # every pose judged, with the station placed from the others


@pytest.mark.parametrize("station", ["known", "new"])
def test_a_drifted_zero_offset_is_caught_and_named(ur10, shoulder_model, station):
    _, model, _, _ = shoulder_model
    pairs = check_pairs(ur10, drift_rad=np.radians(0.02))
    result = verify(model, [pairs if station == "known" else in_new_station(pairs)])
    assert result.drifted and not result.holds
    assert result.diagnosis[0]["group"] == f"zero offset of {ur10.chain.joint_names[ELBOW]}", result.diagnosis
    assert result.manifest()["causes"][0]["joint"] == ur10.chain.joint_names[ELBOW]


def test_a_moved_tool_is_seen_from_a_new_station_unless_the_target_is_refitted(ur10, shoulder_model):
    _, model, _, _ = shoulder_model
    pairs = in_new_station(check_pairs(ur10))
    shift = np.eye(4)
    shift[:3, 3] = [2e-4, -1e-4, 1e-4]  # in the target's frame, which rides on the flange
    moved = replace(pairs, T=pairs.T @ shift)
    held = verify(model, [moved])
    assert held.drifted and held.diagnosis[0]["group"].startswith("the tool"), held.diagnosis
    assert "the target at the model's" in held.stations["tracker_new"]
    refitted = verify(model, [moved], refit_target=True)
    assert not refitted.drifted and "the target with it" in refitted.stations["tracker_new"]


def test_verify_exits_with_its_verdict_and_writes_json_and_html(ur10, shoulder_model, tmp_path):
    model_dir, _, _, _ = shoulder_model
    for name, drift in (("good", 0.0), ("drifted", np.radians(0.02))):
        write_pairs(tmp_path / name, in_new_station(check_pairs(ur10, drift)))
    args = ("verify", "--model", str(model_dir), "--tolerance-mm", "0.1")
    good = cli(*args, "--bag", str(tmp_path / "good"), "--json", str(tmp_path / "good.json"))
    assert good.returncode == 0, good.stderr + good.stdout
    assert "STILL CALIBRATED" in good.stdout and "PASS" in good.stdout
    outcome = json.loads((tmp_path / "good.json").read_text())
    assert outcome["holds"] is True and outcome["drifted"] is False and outcome["passed"] is True
    drifted = cli(*args, "--bag", str(tmp_path / "drifted"), "--out", str(tmp_path / "page"))
    assert drifted.returncode == 1 and "DRIFTED" in drifted.stdout and "zero offset of elbow_joint" in drifted.stdout
    assert "DRIFTED" in (tmp_path / "page" / "index.html").read_text()
    few = cli(*args, "--bag", str(tmp_path / "few"))
    assert few.returncode == 2
