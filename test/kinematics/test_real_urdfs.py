"""URDFs as other tools write them: the same robot in other words is the same chain; a moved joint is not.
What ROS's parser loads, ours loads; implausible inertials are reported and left out of gravity."""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest

from hybrid_kinematics_ros.kinematics.chain import ImplausibleInertialWarning, chain_from_urdf
from hybrid_kinematics_ros.kinematics.elastic import ElasticChain
from hybrid_kinematics_ros.kinematics.fk import fk
from hybrid_kinematics_ros.kinematics.robot_config import CONFIG_DIR

UR10 = (CONFIG_DIR / "ur10.urdf").read_text()
MESH = (
    '<visual><origin xyz="0 0 0" rpy="0 0 0"/><geometry><mesh filename="package://ur_description/meshes/ur10/'
    'visual/shoulder.dae" scale="0.001 0.001 0.001"/></geometry></visual><collision><geometry><mesh '
    'filename="package://ur_description/meshes/ur10/collision/shoulder.stl"/></geometry></collision>'
)
EXTRA = """
  <link name="world"/>
  <joint name="world_joint" type="fixed">
    <parent link="world"/><child link="base_link"/><origin xyz="1 2 3" rpy="0 0 1"/>
  </joint>
  <link name="camera"/>
  <joint name="camera_mount" type="fixed">
    <parent link="link_3"/><child link="camera"/><origin xyz="0.1 0 0.2"/>
  </joint>
</robot>"""


def restated(text: str) -> str:
    """The UR10 as xacro or another exporter might write it: same kinematics, other bytes."""
    # the flange split into two fixed joints through an extra link
    text = text.replace(
        '<child link="tool0"/>\n    <origin xyz="0 0 0" rpy="0 0 0"/>',
        '<child link="flange_link"/>\n    <origin xyz="0 0 0.05" rpy="0 0 0"/>',
    )
    text = text.replace(
        "</robot>",
        '  <link name="flange_link"/>\n  <joint name="flange_tool" type="fixed"><parent link="flange_link"/>'
        '<child link="tool0"/><origin xyz="0 0 -0.05"/></joint>' + EXTRA,
    )
    text = text.replace('<?xml version="1.0"?>', '\n  \n<?xml version="1.0" encoding="utf-8"?>')
    text = text.replace("</link>", "</link>\n  <!-- written by another tool -->")
    # attributes in the other order, numbers printed with more digits
    text = re.sub(r'<origin xyz="([^"]*)" rpy="([^"]*)"/>', r'<origin rpy="\2" xyz="\1"/>', text)
    text = text.replace('xyz="-0.612 0 0"', 'xyz="-0.6120000000001 0.0 0.0"')
    text = text.replace("6.28318531", "6.283185307179586").replace('rpy="1.57079633 0 0"', 'rpy="1.5707963267949 0 0"')
    text = text.replace('<link name="link_1">', f'<link name="link_1">{MESH}')
    return "\ufeff" + text


def test_the_same_robot_in_other_words_is_the_same_chain(tmp_path):
    original = chain_from_urdf(UR10, "base_link", "tool0")
    text = restated(UR10)
    assert text != UR10 and "mesh" in text and "camera" in text
    path = tmp_path / "robot_description.urdf"
    path.write_text(text, encoding="utf-8")
    for source in (text, path):
        other = chain_from_urdf(source, "base_link", "tool0")
        assert original.first_difference(other) is None
        q = np.random.default_rng(0).uniform(-3, 3, (20, 6))
        np.testing.assert_allclose(fk(other, q), fk(original, q), atol=1e-7)  # rpy digits: nm


@pytest.mark.parametrize("joint", ["shoulder_pan_joint", "elbow_joint", "wrist_3_joint"])
def test_a_joint_origin_moved_by_a_tenth_of_a_millimetre_is_named(joint):
    original = chain_from_urdf(UR10, "base_link", "tool0")
    block = re.search(rf'<joint name="{joint}".*?<origin xyz="([^"]*)"', UR10, re.S)
    xyz = np.array(block.group(1).split(), dtype=float) + np.array([0.0, 1e-4, 0.0])
    moved = UR10[: block.start(1)] + " ".join(repr(float(v)) for v in xyz) + UR10[block.end(1) :]
    difference = original.first_difference(chain_from_urdf(restated(moved), "base_link", "tool0"))
    assert difference is not None and f"joint '{joint}'" in difference and "0.1000 mm" in difference


def test_other_differences_are_named():
    original = chain_from_urdf(UR10, "base_link", "tool0")

    def diff(old: str, new: str, count: int = 1) -> str | None:
        return original.first_difference(chain_from_urdf(UR10.replace(old, new, count), "base_link", "tool0"))

    assert "'shoulder_lift_joint'" in diff('<joint name="shoulder_lift_joint"', '<joint name="shoulder"')
    pan = '<joint name="shoulder_pan_joint" type='
    assert "'shoulder_pan_joint'" in diff(pan + '"revolute"', pan + '"continuous"')
    assert "'shoulder_pan_joint': upper limit" in diff('upper="6.28318531"', 'upper="3.14"')
    assert "'shoulder_pan_joint': axis" in diff('<axis xyz="0 0 1"/>', '<axis xyz="0 0.01 1"/>')
    flange = '<child link="tool0"/>\n    <origin xyz="0 0 0'
    assert "'tool0'" in diff(flange + '"', flange + '.001"')


def test_ros_parser_leniency_bom_and_blank_lines(tmp_path):
    for prefix in ("\n", "   \n\n", "\ufeff", "\ufeff\n  "):
        path = tmp_path / "r.urdf"
        path.write_bytes((prefix + UR10).encode("utf-8"))
        assert chain_from_urdf(path, "base_link", "tool0").dof == 6
        assert chain_from_urdf(prefix + UR10, "base_link", "tool0").dof == 6


def inertial_of(link: str, xyz: str, mass: str) -> str:
    block = re.search(rf'<link name="{link}">.*?</link>', UR10, re.S)
    edited = re.sub(r'<origin xyz="[^"]*"', f'<origin xyz="{xyz}"', block.group(0), count=1)
    edited = re.sub(r'<mass value="[^"]*"', f'<mass value="{mass}"', edited)
    return UR10[: block.start()] + edited + UR10[block.end() :]


def without_inertial(link: str) -> str:
    block = re.search(rf'<link name="{link}">.*?</link>', UR10, re.S)
    return UR10[: block.start()] + f'<link name="{link}"/>' + UR10[block.end() :]


@pytest.mark.parametrize(
    ("xyz", "mass", "reason"),
    [("-332.3 0 68", "4.27", "centre of mass 339 m"), ("-0.3323 0 0.068", "-4.27", "mass -4.27 kg")],
)
def test_implausible_inertials_are_named_and_left_out_of_gravity(xyz, mass, reason):
    with pytest.warns(ImplausibleInertialWarning, match=f"link 'link_3': {reason}"):
        chain = chain_from_urdf(inertial_of("link_3", xyz, mass), "base_link", "tool0")
    assert len(chain.inertial_warnings) == 1 and "link_3" in chain.inertial_warnings[0]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # neither the reference nor the shipped URDF warns
        reference = chain_from_urdf(without_inertial("link_3"), "base_link", "tool0")
        shipped = chain_from_urdf(UR10, "base_link", "tool0")
    assert shipped.inertial_warnings == ()
    q = np.random.default_rng(1).uniform(-3, 3, (10, 6))
    torques = ElasticChain.rigid(chain, 2.0).gravity_torques(q)
    np.testing.assert_allclose(torques, ElasticChain.rigid(reference, 2.0).gravity_torques(q), atol=1e-9)
    assert np.abs(torques - ElasticChain.rigid(shipped, 2.0).gravity_torques(q)).max() > 1.0  # link_3 weighs 42 N


def test_a_model_accepts_its_robot_restated_and_refuses_a_moved_joint(trained):
    from hybrid_kinematics_ros.io.errors import DataError
    from hybrid_kinematics_ros.model.hybrid import HybridModel

    path, model = trained[0], trained[1]
    loaded = HybridModel.load(path, expect_urdf=restated(UR10))
    q = np.random.default_rng(2).uniform(model.trained_lower, model.trained_upper, (5, 6))
    np.testing.assert_allclose(loaded.fk(q), model.fk(q), atol=1e-12)
    block = re.search(r'<joint name="wrist_1_joint".*?<origin xyz="([^"]*)"', UR10, re.S)
    moved = UR10[: block.start(1)] + "-0.5723 0.0001 0.163941" + UR10[block.end(1) :]
    with pytest.raises(DataError, match=r"trained for another URDF: joint 'wrist_1_joint': origin .* 0\.1000 mm"):
        HybridModel.load(path, expect_urdf=moved)


def test_the_cli_prints_the_inertial_warning_as_one_line(tmp_path, capsys):
    from hybrid_kinematics_ros.cli.main import main

    urdf = tmp_path / "mm.urdf"
    urdf.write_text(inertial_of("link_3", "-332.3 0 68", "4.27"))
    joints = tmp_path / "q.csv"
    joints.write_text(
        "shoulder_pan_joint,shoulder_lift_joint,elbow_joint,wrist_1_joint,wrist_2_joint,wrist_3_joint\n0,0,0,0,0,0\n"
    )
    argv = ["fk", "--urdf", str(urdf), "--base-link", "base_link", "--tip-link", "tool0"]
    assert main([*argv, "--joints", str(joints), "--out", str(tmp_path / "p.csv")]) == 0
    err = capsys.readouterr().err.splitlines()
    assert err == [
        "hybrid-kinematics fk: warning: link 'link_3': centre of mass 339 m from its joint (more than 3 m; "
        "millimetres?); its mass is left out of the gravity torques"
    ]
