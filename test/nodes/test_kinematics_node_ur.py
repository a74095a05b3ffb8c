"""The kinematics node's ``ur_kinematics`` parameter: the chain served without a model comes from the file."""

from __future__ import annotations

import numpy as np
import pytest
import rclpy
from rclpy.parameter import Parameter

from hybrid_kinematics_ros.kinematics import fk
from hybrid_kinematics_ros.kinematics.robot_config import CONFIG_DIR
from hybrid_kinematics_ros.kinematics.ur_kinematics import chain_from_ur_kinematics
from hybrid_kinematics_ros.nodes.kinematics_node import KinematicsNode
from hybrid_kinematics_ros.nodes.runtime import StartupError

pytestmark = pytest.mark.ros
UR10 = CONFIG_DIR / "ur_kinematics" / "ur10_default.yaml"


@pytest.fixture(scope="module")
def ros():
    rclpy.init()
    yield
    rclpy.shutdown()


def served_chain(**parameters):
    node = KinematicsNode("kinematics_ur", parameter_overrides=[Parameter(k, value=v) for k, v in parameters.items()])
    try:
        return node.model.chain
    finally:
        node.destroy_node()


@pytest.mark.parametrize(
    "template",
    [
        {},
        {
            "urdf_path": "package://hybrid_kinematics_ros/config/ur10.urdf",
            "base_link": "base_link",
            "tip_link": "tool0",
        },
    ],
)
def test_the_node_serves_the_files_chain(ros, template):
    """Alone (base_link to tool0 on the embedded UR10's inertials), or with config/kinematics.yaml's URDF and
    links as the template: the chain the core builds from the file."""
    chain = served_chain(ur_kinematics=str(UR10), **template)
    expected = chain_from_ur_kinematics(UR10)
    assert (chain.base_link, chain.tip_link) == ("base_link", "tool0")
    q = np.random.default_rng(0).uniform(-3.0, 3.0, (20, 6))
    np.testing.assert_allclose(fk.fk(chain, q), fk.fk(expected, q), atol=1e-12)
    assert chain.urdf_text == expected.urdf_text


def test_a_bad_file_stops_the_start_naming_the_field(ros, tmp_path):
    bad = tmp_path / "robot_calibration.yaml"
    bad.write_text(UR10.read_text().replace("  hash:", "  hush:"))
    with pytest.raises(StartupError, match=r"robot_calibration\.yaml: missing field 'kinematics\.hash'"):
        served_chain(ur_kinematics=str(bad))
