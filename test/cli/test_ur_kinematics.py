"""``--ur-kinematics``: a UR kinematics file as the robot of fk and train, and a bad file as one error line."""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest

from hybrid_kinematics_ros.io.pairs import read_pairs, write_pairs
from hybrid_kinematics_ros.kinematics import se3
from hybrid_kinematics_ros.kinematics.robot_config import CONFIG_DIR
from hybrid_kinematics_ros.kinematics.ur_kinematics import UR_JOINTS
from test.cli.inprocess import cli

UR10 = CONFIG_DIR / "ur_kinematics" / "ur10_default.yaml"
HALF_TURN_Z = np.diag([-1.0, -1.0, 1.0, 1.0])  # ur_description's base_link from the embedded UR10's base


@pytest.fixture
def joints(tmp_path):
    path = tmp_path / "joints.csv"
    q = np.random.default_rng(0).uniform(-3.0, 3.0, (20, 6))
    path.write_text(",".join(UR_JOINTS) + "\n" + "\n".join(",".join(repr(float(v)) for v in row) for row in q) + "\n")
    return path


def fk_poses(tmp_path, joints, *robot: str) -> np.ndarray:
    out = tmp_path / "poses.csv"
    result = cli("fk", *robot, "--joints", joints, "--out", out, "--analytic")
    assert result.returncode == 0, result.stderr
    rows = np.loadtxt(out, delimiter=",", skiprows=1, ndmin=2)
    return se3.matrix_from_pose(rows[:, :3], rows[:, 3:7])


def test_fk_of_the_ur10_default_file_is_the_embedded_ur10_in_ur_descriptions_base(tmp_path, joints):
    embedded = fk_poses(tmp_path, joints, "--robot", "ur10")
    alone = fk_poses(tmp_path, joints, "--ur-kinematics", UR10)
    np.testing.assert_allclose(alone, HALF_TURN_Z @ embedded, atol=1e-7)
    # --robot ur10 with the file: the same chain, with that config's tool and working range
    np.testing.assert_allclose(fk_poses(tmp_path, joints, "--robot", "ur10", "--ur-kinematics", UR10), alone)


def test_a_bad_file_ends_the_command_with_one_line_naming_the_file_and_field(tmp_path, joints):
    bad = tmp_path / "my_robot_calibration.yaml"
    bad.write_text(UR10.read_text().replace("    z: 0.163941\n", ""))
    result = subprocess.run(
        ["hybrid-kinematics", "fk", "--ur-kinematics", str(bad), "--joints", str(joints), "--out", "x.csv"],
        capture_output=True,
        text=True,
        check=False,
        cwd=tmp_path,
    )
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and str(bad) in lines[0] and "'kinematics.wrist_1.z'" in lines[0], result.stderr
    assert not (tmp_path / "x.csv").exists()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--urdf", CONFIG_DIR / "ur10.urdf", "--ur-kinematics", UR10], "not with --urdf"),
        (["--ur-kinematics", "missing.yaml"], "UR kinematics file missing.yaml does not exist"),
        (["--robot", "rx160", "--ur-kinematics", UR10], "has no joint 'shoulder_pan_joint'"),
        ([], "give the robot: --robot, --urdf (with --base-link and --tip-link) or --ur-kinematics"),
    ],
)
def test_robot_arguments_that_do_not_go_together_exit_2(tmp_path, joints, args, message):
    result = cli("fk", *args, "--joints", joints, "--out", tmp_path / "poses.csv", "--analytic")
    assert result.returncode == 2 and message in result.stderr, result.stderr


def test_a_model_trained_on_the_file_keeps_its_urdf(tmp_path, joints):
    """train stores the URDF built from the file, so fk and evaluate with --model need the file no more."""
    simulated = tmp_path / "simulated"
    assert cli("simulate", "--robot", "ur10", "--samples", "300", "--out", simulated, "--seed", "5").returncode == 0
    pairs = read_pairs(simulated)  # poses in the embedded UR10's base_link: turn them into ur_description's
    write_pairs(tmp_path / "pairs", pairs.with_poses(HALF_TURN_Z @ pairs.T, "base_link"))
    model = tmp_path / "model"
    result = cli(
        *("train", "--bag", tmp_path / "pairs", "--ur-kinematics", UR10, "--out", model, "--no-parametric"),
        *("--arch-position", "mlp:16x1", "--arch-orientation", "mlp:16x1", "--members", "1"),
        *("--max-epochs", "2", "--max-minutes", "0.05"),
    )
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout.strip().splitlines()[-1])
    assert summary["test_analytic"]["position_mm_mean"] < 10.0  # the file's robot, in the pairs' frame
    assert "base_link_inertia" in (model / "robot.urdf").read_text()
    np.testing.assert_allclose(
        fk_poses(tmp_path, joints, "--model", model), fk_poses(tmp_path, joints, "--ur-kinematics", UR10), atol=1e-12
    )
    result = cli("evaluate", "--model", model, "--bag", tmp_path / "pairs", "--json", tmp_path / "e.json")
    assert result.returncode == 0, result.stderr
