"""train, evaluate and fk on a tiny bag: the first train through the console entry point, the rest in process."""

from __future__ import annotations

import json
import subprocess

import numpy as np

from hybrid_kinematics_ros.cli.main import main
from hybrid_kinematics_ros.kinematics import se3
from hybrid_kinematics_ros.model.hybrid import HybridModel
from test.cli.inprocess import cli


def run(*args):
    return subprocess.run(["hybrid-kinematics", *args], capture_output=True, text=True, check=False)


def test_train_evaluate_fk_workflow(tmp_path, capsys):
    bag = tmp_path / "bag"
    assert main(["simulate", "--robot", "ur10", "--samples", "1500", "--out", str(bag), "--seed", "3"]) == 0
    model_dir = tmp_path / "model"
    result = run(
        "train",
        "--bag",
        str(bag),
        "--robot",
        "ur10",
        "--out",
        str(model_dir),
        "--max-minutes",
        "0.1",
        "--arch-position",
        "mlp:32x2",
        "--arch-orientation",
        "mlp:32x2",
        "--map-step",  # given, so the report's joint error map is exercised; the rest is chosen from the data
        "0.02",
    )
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout.strip().splitlines()[-1])
    assert summary["test_hybrid"]["position_mm_mean"] < summary["test_analytic"]["position_mm_mean"]
    assert "epoch" in result.stderr  # progress shows epoch, loss and validation error

    plots = tmp_path / "plots"
    result = cli(
        "evaluate",
        "--model",
        str(model_dir),
        "--bag",
        str(bag),
        "--json",
        str(tmp_path / "e.json"),
        "--plots",
        str(plots),
    )
    assert result.returncode == 0, result.stderr
    report = json.loads((tmp_path / "e.json").read_text())
    assert report["hybrid"]["position_mm_mean"] < report["analytic"]["position_mm_mean"]
    assert sum(b["count"] for b in report["coverage"]["bins"]) == report["pairs"]
    assert (plots / "position_error_distribution.png").stat().st_size > 1000

    model = HybridModel.load(model_dir)
    q = np.random.default_rng(0).uniform(-1, 0, (4, 6))
    joints = tmp_path / "joints.csv"
    # columns in another order than the model's: the header names them
    order = [5, 0, 1, 2, 3, 4]
    joints.write_text(
        ",".join(model.joint_names[i] for i in order)
        + "\n"
        + "\n".join(",".join(repr(float(v)) for v in row[order]) for row in q)
        + "\n"
    )
    for flag, analytic in (([], False), (["--analytic"], True)):
        out = tmp_path / f"poses{analytic}.csv"
        result = cli("fk", "--model", str(model_dir), "--joints", str(joints), "--out", str(out), *flag)
        assert result.returncode == 0, result.stderr
        rows = np.loadtxt(out, delimiter=",", skiprows=1)
        np.testing.assert_allclose(
            se3.matrix_from_pose(rows[:, :3], rows[:, 3:]), model.fk(q, analytic=analytic), atol=1e-12
        )
    # each pose with its error bounds, in mm and degrees, as the model gives them
    out = tmp_path / "bounded.csv"
    result = cli("fk", "--model", str(model_dir), "--joints", str(joints), "--out", str(out), "--bounds")
    assert result.returncode == 0, result.stderr
    header = out.read_text().splitlines()[0].split(",")
    assert header[-2:] == ["position_bound_mm", "orientation_bound_deg"]
    rows = np.loadtxt(out, delimiter=",", skiprows=1)
    position, orientation = model.error_bounds(q)
    np.testing.assert_allclose(rows[:, -2], 1e3 * position, rtol=1e-9)
    np.testing.assert_allclose(rows[:, -1], np.degrees(orientation), rtol=1e-9)
    assert np.all(rows[:, -2] > 0.0)
    refused = cli("fk", "--model", str(model_dir), "--joints", str(joints), "--out", str(out), "--bounds", "--analytic")
    assert refused.returncode != 0 and "--bounds: --analytic answers carry none" in refused.stderr
    outside = np.zeros(6)
    outside[2] = model.trained_upper[2] + 0.005
    far = tmp_path / "far.csv"
    far.write_text(",".join(model.joint_names) + "\n" + ",".join(repr(float(v)) for v in outside) + "\n")
    out = str(tmp_path / "far_poses.csv")
    refused = cli("fk", "--model", str(model_dir), "--joints", str(far), "--out", out, "--out-of-range", "refuse")
    assert refused.returncode == 2 and "outside the calibrated joint range" in refused.stderr
    assert model.joint_names[2] in refused.stderr
    warned = cli("fk", "--model", str(model_dir), "--joints", str(far), "--out", out)
    assert warned.returncode == 0 and "1 configuration(s) outside the calibrated range" in warned.stderr
    assert "their correction is extrapolated" in warned.stderr  # what the policy did, in the node's words
    # inside every joint's range, but far from the training data: outside once a coverage radius is given
    middle = tmp_path / "middle.csv"
    centre = 0.5 * (model.trained_lower + model.trained_upper)
    middle.write_text(",".join(model.joint_names) + "\n" + ",".join(repr(float(v)) for v in centre) + "\n")
    radius = str(0.5 * float(model.coverage_distance(centre)[0]))
    args = ("fk", "--model", str(model_dir), "--joints", str(middle), "--out", out, "--out-of-range", "refuse")
    assert cli(*args).returncode == 0
    refused = cli(*args, "--coverage-radius", radius)
    assert refused.returncode == 2 and "from the nearest training configuration" in refused.stderr

    urdf = tmp_path / "calibrated.urdf"
    result = cli("export-urdf", "--model", str(model_dir), "--out", str(urdf), "--bag", str(bag))
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["exported"]["position_mm_mean"] < report["nominal"]["position_mm_mean"]
    assert report["parametric"]["position_mm_mean"] < report["exported"]["position_mm_mean"]
    assert "_calibrated" in urdf.read_text()
    assert "compliance" in " ".join(report["left_behind"]) and "kinematics node" in result.stderr

    # the report shows the parametric stage's joint error map, as a row per joint and as a plot
    result = cli("report", "--model", str(model_dir), "--bag", str(bag), "--out", str(tmp_path / "report"))
    assert result.returncode == 0, result.stderr
    page = (tmp_path / "report" / "index.html").read_text()
    assert "joint error map of shoulder_lift_joint" in page and "joint_map.png" in page
    # and the capacity table: the given map step, the chosen settings with their validation figures
    assert "Capacity chosen from the data" in page and "given" in page and "harmonics" in page
    assert (tmp_path / "report" / "joint_map.png").stat().st_size > 5000


def test_bad_inputs_get_one_line_errors(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text(
        "shoulder_pan_joint,shoulder_lift_joint,elbow_joint,wrist_1_joint,wrist_2_joint,wrist_3_joint\n0,0,x,0,0,0\n"
    )
    result = cli("fk", "--robot", "ur10", "--joints", str(bad), "--out", str(tmp_path / "o.csv"))
    assert result.returncode == 2
    assert result.stderr.strip() == (
        f"hybrid-kinematics fk: error: {bad}: line 2, column 'elbow_joint': 'x' is not a number"
    )
    missing = tmp_path / "missing.csv"
    missing.write_text("shoulder_pan_joint,shoulder_lift_joint\n0,0\n")
    result = cli("fk", "--robot", "ur10", "--joints", str(missing), "--out", str(tmp_path / "o.csv"))
    assert "missing column(s) elbow_joint" in result.stderr and result.returncode == 2
    result = cli("train", "--bag", str(tmp_path / "nobag"), "--robot", "ur10", "--out", str(tmp_path / "m"))
    assert result.returncode == 2 and "does not exist" in result.stderr
    assert result.stderr.count("\n") == 1


def test_tracker_frame_position_only_workflow(tmp_path):
    """A reflector without orientation, seen by a tracker in its own frame: referencing, the parametric
    stage and the position net, then evaluation of a tracker-frame bag through the stored referencing."""
    import shutil

    import yaml

    from hybrid_kinematics_ros.kinematics.robot_config import CONFIG_DIR

    shutil.copy(CONFIG_DIR / "ur10.urdf", tmp_path / "ur10.urdf")
    cfg = yaml.safe_load((CONFIG_DIR / "ur10.yaml").read_text())
    cfg["tracker"]["base_to_tracker"] = {"xyz": [2.0, 0.5, -0.2], "rpy": [0.0, 0.01, 1.0]}
    cfg["tracker"]["flange_to_target"] = {"xyz": [0.0, 0.05, 0.1], "rpy": [0.0, 0.0, 0.0]}
    robot = tmp_path / "cell.yaml"
    robot.write_text(yaml.safe_dump(cfg))
    bag = tmp_path / "bag"
    sim = cli("simulate", "--robot", str(robot), "--samples", "1500", "--out", str(bag), "--position-only")
    assert sim.returncode == 0, sim.stderr
    model_dir = tmp_path / "model"
    result = cli(
        "train",
        "--bag",
        str(bag),
        "--robot",
        str(robot),
        "--out",
        str(model_dir),
        "--max-minutes",
        "0.1",
        "--arch-position",
        "mlp:32x2",
    )
    assert result.returncode == 0, result.stderr
    assert "referenced frame 'tracker'" in result.stderr and "parametric stage" in result.stderr
    manifest = json.loads((model_dir / "model.json").read_text())
    assert set(manifest["nets"]) == {"position"} and manifest["position_only"]
    assert [r["frame_id"] for r in manifest["referencing"]] == ["tracker"]
    assert "orientation is not corrected" in manifest["note"]
    # judged on a bag it never saw, in the tracker frame through the stored referencing
    test_bag = tmp_path / "test_bag"
    sim = cli(
        "simulate", "--robot", str(robot), "--samples", "300", "--out", str(test_bag), "--position-only", "--seed", "7"
    )
    assert sim.returncode == 0, sim.stderr
    result = cli("evaluate", "--model", str(model_dir), "--bag", str(test_bag))
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    # the stage is at the noise floor here, so the position net may rightly correct nothing: never worse than it
    assert report["hybrid"]["position_mm_mean"] <= 1.05 * report["parametric"]["position_mm_mean"] < 0.5
    # the URDF model, judged on the same bag, leaves the cell's robot errors: the stage removes nearly all
    assert report["analytic"]["position_mm_mean"] > 20 * report["parametric"]["position_mm_mean"]
    assert "orientation_deg_mean" not in report["hybrid"]
    report_dir = tmp_path / "report"
    result = cli("report", "--model", str(model_dir), "--bag", str(test_bag), "--out", str(report_dir))
    assert result.returncode == 0, result.stderr
    page = (report_dir / "index.html").read_text()
    assert "Method: least squares; frame 'tracker'" in page and "Not identifiable" in page
    assert "position-only pairs" in page and not (report_dir / "orientation_error_distribution.png").exists()


def test_train_runs_an_earlier_models_recipe_and_refuses_a_mix(tmp_path):
    bag = tmp_path / "bag"
    assert main(["simulate", "--robot", "ur10", "--samples", "600", "--out", str(bag), "--seed", "4"]) == 0
    given = ["--max-epochs", "3", "--arch-position", "mlp:16x2", "--arch-orientation", "mlp:16x2", "--members", "1"]
    stage = ["--elastic", "geometry", "--harmonics", "0", "--map-step", "0", "--no-approach", "--seed", "2"]
    stage += ["--orientation-length", "1.0", "--no-drop-outliers"]  # every capacity setting given: nothing to choose
    first = cli("train", "--bag", str(bag), "--robot", "ur10", "--out", str(tmp_path / "a"), *given, *stage)
    assert first.returncode == 0, first.stderr
    again = cli(
        "train", "--bag", str(bag), "--robot", "ur10", "--out", str(tmp_path / "b"), "--recipe", str(tmp_path / "a")
    )
    assert again.returncode == 0, again.stderr
    recipes = [json.loads((tmp_path / m / "model.json").read_text())["recipe"] for m in ("a", "b")]
    assert recipes[0] == recipes[1]
    assert recipes[0]["seed"] == 2 and recipes[0]["capacity"]["harmonics"] == 0 and not recipes[0]["drop_outliers"]
    assert recipes[0]["arch"] == {"position": "mlp:16x2", "orientation": "mlp:16x2"}

    mixed = cli(
        "train",
        "--bag",
        str(bag),
        "--robot",
        "ur10",
        "--out",
        str(tmp_path / "c"),
        "--recipe",
        str(tmp_path / "a"),
        "--harmonics",
        "3",
    )
    assert mixed.returncode == 2 and "--harmonics" in mixed.stderr
    assert not (tmp_path / "c").exists()
