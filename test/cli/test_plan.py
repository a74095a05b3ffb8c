"""``hybrid-kinematics plan`` from the command line: a pool's rows come back unchanged in tour order, the
JointTrajectory YAML matches them, and bad input ends with one line naming what to fix."""

from __future__ import annotations

import csv
import json
import subprocess

import numpy as np
import yaml

from hybrid_kinematics_ros.calibration.parametric import identify
from hybrid_kinematics_ros.calibration.plan import draw_configurations
from hybrid_kinematics_ros.cli.main import main
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.simulation.truth import TrueRobot


def cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["hybrid-kinematics", "plan", *args], capture_output=True, text=True, check=False)


def test_a_pool_is_planned_into_its_own_rows_a_trajectory_and_a_summary(tmp_path):
    chain = load_robot_config("ur10").chain
    q = draw_configurations(np.full(6, -2.5), np.full(6, 2.5), 400, seed=1)
    pool = tmp_path / "pool.csv"
    with pool.open("w", newline="") as f:  # an extra column and the pool's own number format, kept as they are
        writer = csv.writer(f)
        writer.writerow(["label", *chain.joint_names])
        writer.writerows([f"pose{i}", *(f"{v:.5f}" for v in row)] for i, row in enumerate(q))
    out = tmp_path / "plan"
    result = cli("--robot", "ur10", "--candidates", str(pool), "--count", "30", "--out", str(out), "--curve")
    assert result.returncode == 0, result.stderr
    lines = pool.read_text().splitlines()
    planned = (out / "poses.csv").read_text().splitlines()
    assert planned[0] == lines[0] and len(planned) == 31
    assert set(planned[1:]) <= set(lines[1:]) and len(set(planned[1:])) == 30  # rows of the pool, unchanged
    message = yaml.safe_load((out / "trajectory.yaml").read_text())
    assert message["joint_names"] == list(chain.joint_names)
    for point, line in zip(message["points"], planned[1:], strict=True):
        assert np.allclose(point["positions"], [float(v) for v in line.split(",")[1:]])
    times = [p["time_from_start"]["sec"] + 1e-9 * p["time_from_start"]["nanosec"] for p in message["points"]]
    assert np.all(np.diff(times) >= 5.0)  # a move, then 5 s at each pose
    summary = json.loads((out / "plan.json").read_text())
    assert summary["poses"] == 30 and summary["predicted"]["position_mean_mm"] > 0
    assert [row["poses"] for row in summary["curve"]][:3] == [50, 100, 200]
    assert "self-occlusion" in " ".join(summary["tracker"]["not_checked"])
    # the pool's rows beyond the joint limits (the shoulder lift above 0) are never planned, and are counted
    beyond = ~np.all((q >= chain.lower) & (q <= chain.upper), axis=1)
    assert beyond.any() and summary["candidates"]["within the joint limits"] == int((~beyond).sum())
    planned_q = np.array([[float(v) for v in line.split(",")[1:]] for line in planned[1:]])
    assert np.all((planned_q >= chain.lower) & (planned_q <= chain.upper))
    # a curve stop's measuring time is that count's own plan (its own, shorter moves), not 30 poses' rate
    assert (
        main(["plan", "--robot", "ur10", "--candidates", str(pool), "--count", "200", "--out", str(tmp_path / "p")])
        == 0
    )
    alone = json.loads((tmp_path / "p" / "plan.json").read_text())["measuring_time_h"]
    assert summary["curve"][2]["measuring_time_h"] == alone


def test_bad_input_is_one_line_naming_it(tmp_path, capsys):
    """In this process (the entry point's ``main``): five starts of the executable would cost a minute."""
    pool = tmp_path / "pool.csv"
    pool.write_text("joint_1,joint_2\n0.1,0.2\n")
    cases = {
        ("--candidates", str(pool), "--count", "5"): f"{pool}: missing column(s) shoulder_pan_joint",
        (
            "--count",
            "30",
            "--joint-range",
            "elbow_joint:1.0:9.0",
        ): "--joint-range elbow_joint:1.0:9.0: needs LOW < HIGH",
        ("--count", "30", "--joint-range", "elbow:0:1"): "no joint 'elbow'",
        ("--count", "30", "--tracker-xyz", "3", "0", "0.5", "--max-distance-m", "0.5"): "only 0 usable",
        ("--count", "5", "--cone-deg", "30"): "--cone-deg needs --tracker-xyz",
        ("--count", "5", "--max-distance-m", "4"): "--max-distance-m needs --tracker-xyz",
    }
    for args, message in cases.items():
        code = main(["plan", "--robot", "ur10", "--out", str(tmp_path / "out"), *args])
        lines = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(lines) == 1 and message in lines[0], (args, lines)


def test_a_previous_calibration_adds_its_cyclic_errors_to_the_prediction(tmp_path, capsys):
    """``--prior-model`` reads a model's cyclic joint errors (here the parametric section of a stage identified
    with two harmonics on a virtual UR10 with gear ripple, as ``train`` writes it): the same poses, a larger
    predicted error. A model of other joints, or no model at all, is one line."""
    cfg = load_robot_config("ur10")
    truth = TrueRobot.from_config(cfg, seed=3)
    q = draw_configurations(np.full(6, -3.0), np.full(6, 3.0), 600, seed=2)
    stage = identify(cfg.chain, q, truth.fk(q), harmonics=2, payload_mass=cfg.payload_mass, gravity=cfg.gravity)
    manifest = {"joint_names": list(cfg.chain.joint_names), "parametric": stage.manifest()}
    (tmp_path / "model").mkdir()
    (tmp_path / "model" / "model.json").write_text(json.dumps(manifest))
    common = ["plan", "--robot", "ur10", "--count", "40"]
    assert main([*common, "--out", str(tmp_path / "blind")]) == 0
    assert main([*common, "--out", str(tmp_path / "prior"), "--prior-model", str(tmp_path / "model")]) == 0
    printed = capsys.readouterr().out
    assert "2 harmonics of each joint's error from --prior-model" in printed and "prior model found" in printed
    assert "predicted for the capacity that leaves the least: " in printed
    blind, prior = (json.loads((tmp_path / d / "plan.json").read_text()) for d in ("blind", "prior"))
    assert (tmp_path / "blind" / "poses.csv").read_text() == (tmp_path / "prior" / "poses.csv").read_text()
    assert prior["cyclic_prior"]["harmonics"] == 2 and "cyclic_prior" not in blind
    assert prior["predicted"]["parameters_part_mm"] > 1.2 * blind["predicted"]["parameters_part_mm"]

    manifest["joint_names"] = [f"j{k}" for k in range(6)]
    (tmp_path / "other.json").write_text(json.dumps(manifest))
    cases = {
        str(tmp_path / "missing"): f"{tmp_path / 'missing'}: cannot read a model.json",
        str(tmp_path / "other.json"): f"{tmp_path / 'other.json'}: joints ['j0'",
    }
    for path, message in cases.items():
        code = main([*common, "--out", str(tmp_path / "bad"), "--prior-model", path])
        lines = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(lines) == 1 and message in lines[0], (path, lines)
