"""URDF parsing: every joint type, odd axes and origins, inertials, and clear errors."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from hybrid_kinematics_ros.kinematics import fk
from hybrid_kinematics_ros.kinematics.chain import chain_from_urdf
from hybrid_kinematics_ros.kinematics.errors import KinematicsError
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config

MIXED = """<?xml version="1.0"?>
<robot name="mixed">
  <link name="world"/>
  <link name="base"><inertial><origin xyz="0 0 0.1"/><mass value="3"/>
    <inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <link name="a"><inertial><origin xyz="0.1 0 0"/><mass value="2"/>
    <inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <link name="a_cover"><inertial><origin xyz="0 0.2 0"/><mass value="1"/>
    <inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <link name="b"/>
  <link name="c"/>
  <link name="tip"/>
  <link name="side"/>
  <joint name="mount" type="fixed"><parent link="world"/><child link="base"/>
    <origin xyz="0.1 -0.2 0.3" rpy="0.3 -0.2 0.9"/></joint>
  <joint name="j1" type="revolute"><parent link="base"/><child link="a"/>
    <origin xyz="0 0 0.4" rpy="0.1 0.2 0.3"/><axis xyz="0.3 -0.5 0.8"/>
    <limit lower="-1.5" upper="2.0" effort="1" velocity="1"/></joint>
  <joint name="cover" type="fixed"><parent link="a"/><child link="a_cover"/>
    <origin xyz="0.05 0 0" rpy="0 0 1.5707963267948966"/></joint>
  <joint name="j2" type="prismatic"><parent link="a_cover"/><child link="b"/>
    <origin xyz="0.2 0.1 0" rpy="-0.4 0 0.2"/><axis xyz="0 1 1"/>
    <limit lower="-0.1" upper="0.3" effort="1" velocity="1"/></joint>
  <joint name="j3" type="continuous"><parent link="b"/><child link="c"/>
    <origin xyz="0 0.3 0.1" rpy="1.2 0.4 -0.7"/><axis xyz="1 0 0"/></joint>
  <joint name="flange" type="fixed"><parent link="c"/><child link="tip"/>
    <origin xyz="0.05 0.02 0.12" rpy="0 3.0 0"/></joint>
  <joint name="branch" type="revolute"><parent link="a"/><child link="side"/>
    <axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
</robot>
"""


def test_mixed_joint_types_match_pinocchio(tmp_path):
    path = tmp_path / "mixed.urdf"
    path.write_text(MIXED)
    chain = chain_from_urdf(path, "world", "tip")
    assert chain.joint_names == ("j1", "j2", "j3")
    assert list(chain.revolute) == [True, False, True]
    assert list(chain.continuous) == [False, False, True]
    np.testing.assert_array_equal(chain.lower[:2], [-1.5, -0.1])
    assert np.isinf(chain.lower[2]) and np.isinf(chain.upper[2])
    # joint 1 moves link a and, through a fixed joint, a_cover: 3 kg with the combined centre of mass
    assert chain.segment_mass[0] == pytest.approx(3.0)
    cover_com = np.array([0.05, 0.0, 0.0]) + np.array([-0.2, 0.0, 0.0])  # 0.2 along y, turned by 90 deg
    np.testing.assert_allclose(chain.segment_com[0], (2 * np.array([0.1, 0, 0]) + cover_com) / 3, atol=1e-12)

    model = pin.buildModelFromUrdf(str(path))
    data = model.createData()
    frame = model.getFrameId("tip")
    rng = np.random.default_rng(0)
    q = np.column_stack([rng.uniform(-1.5, 2, 200), rng.uniform(-0.1, 0.3, 200), rng.uniform(-6, 6, 200)])
    t, j = fk.fk_and_jacobian(chain, q)
    for i in range(len(q)):
        qp = np.zeros(model.nq)
        # pinocchio orders joints depth-first; continuous joints take (cos, sin)
        idx = {name: model.joints[model.getJointId(name)].idx_q for name in ("j1", "j2", "j3", "branch")}
        qp[idx["j1"]], qp[idx["j2"]] = q[i, 0], q[i, 1]
        qp[idx["j3"]], qp[idx["j3"] + 1] = np.cos(q[i, 2]), np.sin(q[i, 2])
        pin.forwardKinematics(model, data, qp)
        pin.updateFramePlacements(model, data)
        np.testing.assert_allclose(t[i], data.oMf[frame].homogeneous, atol=1e-12)
        np.testing.assert_allclose(fk.fk_single(chain, q[i]), t[i], atol=1e-14, rtol=0)
        t_single, j_single = fk.fk_and_jacobian_single(chain, q[i])  # the compiled path, prismatic joint too
        np.testing.assert_allclose(t_single, t[i], atol=1e-14, rtol=0)
        np.testing.assert_allclose(j_single, j[i], atol=1e-13, rtol=0)
        jp = pin.computeFrameJacobian(model, data, qp, frame, pin.LOCAL_WORLD_ALIGNED)
        vcols = [model.joints[model.getJointId(n)].idx_v for n in ("j1", "j2", "j3")]
        np.testing.assert_allclose(j[i], jp[:, vcols], atol=1e-12)


@pytest.mark.parametrize(
    ("edit", "base", "tip", "message"),
    [
        (None, "world", "nowhere", "tip_link 'nowhere' is not a link"),
        (None, "tip", "world", "no kinematic path from 'tip' down to 'world'"),
        (None, "c", "tip", "has no actuated joint"),
        (('type="continuous"', 'type="floating"'), "world", "tip", "joint 'j3' is of type 'floating'"),
        (('<axis xyz="1 0 0"/>', '<axis xyz="1 0 0"/><mimic joint="j1"/>'), "world", "tip", "mimic"),
        (('<link name="tip"/>', '<link name="tip">'), "world", "tip", "cannot parse URDF"),
    ],
)
def test_unusable_urdf_gets_a_clear_error(tmp_path, edit, base, tip, message):
    text = MIXED if edit is None else MIXED.replace(*edit)
    path = tmp_path / "bad.urdf"
    path.write_text(text)
    with pytest.raises(KinematicsError, match=message):
        chain_from_urdf(path, base, tip)


def test_missing_file_and_text_input(tmp_path):
    with pytest.raises(KinematicsError, match="does not exist"):
        chain_from_urdf(tmp_path / "none.urdf", "a", "b")
    from_text = chain_from_urdf(MIXED, "world", "tip")
    assert from_text.joint_names == ("j1", "j2", "j3")
    assert len(from_text.urdf_sha256) == 64


def test_chain_is_frozen():
    chain = chain_from_urdf(MIXED, "world", "tip")
    with pytest.raises(ValueError, match="read-only"):
        chain.pre[0, 0, 0] = 2.0
    with pytest.raises(AttributeError):
        chain.base_link = "x"


def test_robot_config_limits_and_tool(tmp_path):
    cfg = load_robot_config("ur10")
    assert cfg.chain.dof == 6
    assert cfg.chain.upper[1] == 0.0  # working range from the YAML, inside the URDF limits
    text = (
        cfg.path.read_text()
        .replace("urdf: ur10.urdf", f"urdf: {cfg.urdf_path}")
        .replace("xyz: [0.0, 0.0, 0.0], rpy", "xyz: [0.0, 0.0, 0.1], rpy")
    )
    (tmp_path / "tool.yaml").write_text(text)
    with_tool = load_robot_config(tmp_path / "tool.yaml")
    q = np.zeros((1, 6))
    diff = fk.fk(with_tool.chain, q)[0] @ np.linalg.inv(fk.fk(cfg.chain, q)[0])
    assert np.linalg.norm(diff[:3, 3]) == pytest.approx(0.1)
    (tmp_path / "bad.yaml").write_text("urdf: ur10.urdf\nbase_link: base_link\n")
    with pytest.raises(KinematicsError, match="missing field 'tip_link'"):
        load_robot_config(tmp_path / "bad.yaml")


@pytest.mark.parametrize("joints", range(1, 7))
def test_single_fk_agrees_with_the_batch_for_every_chain_length(joints):
    """fk_single multiplies the factors as a tree padded with identities to a power of two: each length
    pads differently (1 joint: none; 4 joints: three)."""
    chain = chain_from_urdf(load_robot_config("ur10").chain.urdf_text, "base_link", f"link_{joints}")
    assert chain.dof == joints
    q = np.random.default_rng(joints).uniform(-np.pi, np.pi, (50, joints))
    batch = fk.fk(chain, q)
    for i in range(len(q)):
        np.testing.assert_allclose(fk.fk_single(chain, q[i]), batch[i], atol=1e-14, rtol=0)
