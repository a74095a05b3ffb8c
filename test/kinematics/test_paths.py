"""package:// paths, the way ROS users write them, and where the package's own files are."""

from __future__ import annotations

from pathlib import Path

import pytest

from hybrid_kinematics_ros.kinematics.chain import chain_from_urdf
from hybrid_kinematics_ros.kinematics.errors import KinematicsError
from hybrid_kinematics_ros.kinematics.paths import config_dir, resolve_path
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config


def test_package_paths_resolve_to_the_package_files():
    expected = config_dir() / "ur10.urdf"
    assert resolve_path("package://hybrid_kinematics_ros/config/ur10.urdf") == expected
    # argparse's type=Path collapses the double slash
    assert resolve_path(Path("package://hybrid_kinematics_ros/config/ur10.urdf")) == expected
    assert resolve_path(f"file://{expected}") == expected
    assert resolve_path("ur10.urdf", relative_to=config_dir()) == expected
    chain = chain_from_urdf("package://hybrid_kinematics_ros/config/ur10.urdf", "base_link", "tool0")
    assert chain.joint_names == load_robot_config("ur10").chain.joint_names


def test_robot_config_and_its_urdf_entry_take_package_paths(tmp_path):
    cfg = tmp_path / "cell.yaml"
    cfg.write_text("urdf: package://hybrid_kinematics_ros/config/rx160.urdf\nbase_link: base_link\ntip_link: tool0\n")
    loaded = load_robot_config(cfg)
    assert loaded.urdf_path == (config_dir() / "rx160.urdf").resolve()
    assert load_robot_config("package://hybrid_kinematics_ros/config/ur10.yaml").name == "ur10"


def test_unknown_package_and_missing_file_are_named():
    with pytest.raises(KinematicsError, match="no_such_pkg"):
        resolve_path("package://no_such_pkg/robot.urdf")
    with pytest.raises(KinematicsError, match="config/nope"):
        chain_from_urdf("package://hybrid_kinematics_ros/config/nope.urdf", "base_link", "tool0")
