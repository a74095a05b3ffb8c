"""``hybrid-kinematics simulate`` through its real entry point."""

from __future__ import annotations

import json
import subprocess

import numpy as np

from hybrid_kinematics_ros.cli.main import main
from hybrid_kinematics_ros.io.pairs import read_pairs
from hybrid_kinematics_ros.kinematics import fk, se3
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config


def test_simulate_split_writes_three_readable_bags(tmp_path, capsys):
    out = tmp_path / "data"
    assert (
        main(
            [
                "simulate",
                "--robot",
                "rx160",
                "--samples",
                "1000",
                "--out",
                str(out),
                "--split",
                "0.8,0.1,0.1",
                "--no-noise",
            ]
        )
        == 0
    )
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["bags"] == {str(out / "train"): 800, str(out / "val"): 100, str(out / "test"): 100}
    cfg = load_robot_config("rx160")
    train = read_pairs(out / "train", cfg.chain.joint_names)
    assert len(train) == 800 and train.frame_id == "base_link"
    assert np.all(train.q >= cfg.chain.lower) and np.all(train.q <= cfg.chain.upper)
    pos, _ = se3.pose_errors(train.T, fk.fk(cfg.chain, train.q))
    assert 0.5 < pos.mean() < 5.0  # the truth differs from the nominal model by millimetres


def test_console_script_reports_bad_input_in_one_line(tmp_path):
    result = subprocess.run(
        [
            "hybrid-kinematics",
            "simulate",
            "--robot",
            str(tmp_path / "none.yaml"),
            "--samples",
            "5",
            "--out",
            str(tmp_path / "x"),
        ],
        capture_output=True,
        text=True,
        check=False,
    )
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0
    assert "none.yaml does not exist" in result.stderr
