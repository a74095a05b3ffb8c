"""DH tables from a chain: the table's forward kinematics is the chain's, the UR10's is the published one, and
the notes say where the geometry has no unique or exact DH form."""

from __future__ import annotations

from dataclasses import replace
from functools import cache

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from hybrid_kinematics_ros.kinematics import fk
from hybrid_kinematics_ros.kinematics.chain import Chain
from hybrid_kinematics_ros.kinematics.dh import DHRow, DHTable, dh_fk, dh_table, dh_transforms, format_dh
from hybrid_kinematics_ros.kinematics.errors import KinematicsError
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.kinematics.se3 import rotation_angle

ROBOTS = ("ur10", "rx160", "kr16")
CONVENTIONS = ("standard", "modified")
TOL = 1e-9  # m and rad
HALF_PI = np.pi / 2
URDF_ROUNDING = 1e-6  # the URDF writes π/2 as 1.57079633: d_4, d_5 move by its 3e-9 rad times the lever


@cache
def robot(name: str) -> Chain:
    return load_robot_config(name).chain


def transform(rotvec: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    t[:3, 3] = xyz
    return t


def rz(angle: float) -> np.ndarray:
    return transform(np.array([0.0, 0.0, angle]), np.zeros(3))


def random_q(chain: Chain, rng: np.random.Generator, count: int = 200) -> np.ndarray:
    return rng.uniform(-np.pi, np.pi, size=(count, chain.dof))


def errors(t_a: np.ndarray, t_b: np.ndarray) -> tuple[float, float]:
    """The largest position (m) and rotation (rad) difference between two batches of poses."""
    position = np.linalg.norm(t_a[:, :3, 3] - t_b[:, :3, 3], axis=-1)
    turn = rotation_angle(np.swapaxes(t_b[:, :3, :3], -1, -2) @ t_a[:, :3, :3])
    return float(position.max()), float(turn.max())


def assert_reproduces_fk(table: DHTable, chain: Chain, seed: int = 0) -> None:
    q = random_q(chain, np.random.default_rng(seed))
    position, turn = errors(dh_fk(table, q), fk.fk(chain, q))
    assert position < TOL and turn < TOL, (position, turn)


def calibrated(chain: Chain, seed: int, rotation_rad: float = 1e-3, translation_m: float = 3e-4) -> Chain:
    """The chain with every joint origin turned and shifted a little, like a calibration's: ``replace`` runs
    ``__post_init__`` again, which rebuilds the FK generators from the new ``pre``."""
    rng = np.random.default_rng(seed)
    small = [transform(rng.normal(0, rotation_rad, 3), rng.normal(0, translation_m, 3)) for _ in range(chain.dof)]
    return replace(chain, pre=chain.pre @ np.array(small))


def test_dh_transforms_are_the_textbook_products():
    a, alpha, d, theta = 0.3, -0.7, 0.2, 1.1
    rx = transform(np.array([alpha, 0.0, 0.0]), np.zeros(3))
    tx = transform(np.zeros(3), np.array([a, 0.0, 0.0]))
    tz = transform(np.zeros(3), np.array([0.0, 0.0, d]))
    np.testing.assert_allclose(dh_transforms("standard", a, alpha, d, theta), rz(theta) @ tz @ tx @ rx, atol=1e-15)
    np.testing.assert_allclose(dh_transforms("modified", a, alpha, d, theta), rx @ tx @ rz(theta) @ tz, atol=1e-15)


@pytest.mark.parametrize("convention", CONVENTIONS)
@pytest.mark.parametrize("name", ROBOTS)
def test_the_table_reproduces_the_chains_fk(name, convention):
    chain = robot(name)
    table = dh_table(chain, convention)
    assert table.convention == convention and table.dof == chain.dof
    assert_reproduces_fk(table, chain)


def test_the_ur10_standard_table_is_the_published_one():
    table = dh_table(robot("ur10"), "standard")
    np.testing.assert_allclose(table.column("a"), [0, -0.612, -0.5723, 0, 0, 0], atol=URDF_ROUNDING)
    np.testing.assert_allclose(table.column("d"), [0.1273, 0, 0, 0.163941, 0.1157, 0.0922], atol=URDF_ROUNDING)
    np.testing.assert_allclose(table.column("alpha"), [HALF_PI, 0, 0, HALF_PI, -HALF_PI, 0], atol=URDF_ROUNDING)
    np.testing.assert_allclose(table.column("theta"), np.zeros(6), atol=URDF_ROUNDING)
    assert table.column("revolute").all()
    np.testing.assert_allclose(table.base, np.eye(4), atol=TOL)  # base_link's z is joint 1's axis
    np.testing.assert_allclose(table.tool, np.eye(4), atol=TOL)  # tool0 is the flange on joint 6's axis


def test_the_ur10_modified_table_shifts_a_and_alpha_by_one_row():
    table = dh_table(robot("ur10"), "modified")
    np.testing.assert_allclose(table.column("a"), [0, 0, -0.612, -0.5723, 0, 0], atol=URDF_ROUNDING)
    np.testing.assert_allclose(table.column("alpha"), [0, HALF_PI, 0, 0, HALF_PI, -HALF_PI], atol=URDF_ROUNDING)
    np.testing.assert_allclose(table.column("d"), [0.1273, 0, 0, 0.163941, 0.1157, 0.0922], atol=URDF_ROUNDING)
    np.testing.assert_allclose(table.column("theta"), np.zeros(6), atol=URDF_ROUNDING)
    np.testing.assert_allclose(table.base, np.eye(4), atol=TOL)
    np.testing.assert_allclose(table.tool, np.eye(4), atol=TOL)


def test_the_rx160_standard_table_is_the_published_one():
    """Stäubli's RX160 table: joint 2's zero is the arm upright, a theta offset of -π/2 that joint 3 undoes."""
    table = dh_table(robot("rx160"), "standard")
    np.testing.assert_allclose(table.column("a"), [0.15, 0.825, 0, 0, 0, 0], atol=TOL)
    np.testing.assert_allclose(table.column("d"), [0.55, 0, 0, 0.625, 0, 0.11], atol=URDF_ROUNDING)
    np.testing.assert_allclose(table.column("alpha"), [-HALF_PI, 0, HALF_PI, -HALF_PI, HALF_PI, 0], atol=URDF_ROUNDING)
    np.testing.assert_allclose(table.column("theta"), [0, -HALF_PI, HALF_PI, 0, 0, 0], atol=URDF_ROUNDING)
    np.testing.assert_allclose(table.base, np.eye(4), atol=TOL)
    np.testing.assert_allclose(table.tool, np.eye(4), atol=TOL)


def test_a_small_tilt_flips_no_sign_at_a_right_angle():
    """The RX160's theta_3 = π/2 lies where the previous x axis cannot choose the normal's direction: a tilted
    joint 4 keeps theta_3 and alpha_3 near +π/2 rather than jumping to -π/2 with the tilt's sign."""
    nominal = robot("rx160")
    rng = np.random.default_rng(3)
    for _ in range(10):
        pre = nominal.pre.copy()
        pre[3] = pre[3] @ transform(rng.normal(0, 1e-3, 3), np.zeros(3))
        chain = replace(nominal, pre=pre)
        table = dh_table(chain, "standard")
        assert table.rows[2].theta == pytest.approx(HALF_PI, abs=0.01)
        assert table.rows[2].alpha == pytest.approx(HALF_PI, abs=0.01)
        assert_reproduces_fk(table, chain)


def test_a_wrong_sign_or_convention_misses_the_fk_by_centimetres():
    """What the FK comparison above catches: the same rows read in the other convention, or one alpha of the
    other sign, land centimetres away (the tool, fitted at q = 0, cannot hide it at other joints)."""
    chain = robot("ur10")
    q = random_q(chain, np.random.default_rng(1))
    table = dh_table(chain, "standard")
    swapped = replace(table, convention="modified")
    rows = list(table.rows)
    rows[4] = replace(rows[4], alpha=-rows[4].alpha)
    flipped = replace(table, rows=tuple(rows))
    for wrong in (swapped, flipped):
        assert errors(dh_fk(wrong, q), fk.fk(chain, q))[0] > 0.01


@pytest.mark.parametrize("name, pairs", [("ur10", [(2, 3), (3, 4)]), ("rx160", [(2, 3)]), ("kr16", [(2, 3)])])
def test_parallel_axes_are_named_in_the_notes(name, pairs):
    chain = robot(name)
    for convention in CONVENTIONS:
        table = dh_table(chain, convention)
        assert len(table.notes) == len(pairs), table.notes  # nothing else: base and tool are the identity
        for note, (j, k) in zip(table.notes, pairs, strict=True):
            assert note.startswith(f"joints {j} ({chain.joint_names[j - 1]}) and {k} ({chain.joint_names[k - 1]}) ")
            assert "are parallel" in note and f"d_{j} is a convention" in note


@pytest.mark.parametrize("convention", CONVENTIONS)
def test_parallel_axes_take_the_normal_through_the_previous_one(convention):
    """The UR10's joints 2, 3 and 4 are parallel: d_2 = d_3 = 0, and joint 4's offset lies in d_4 alone."""
    table = dh_table(robot("ur10"), convention)
    assert table.rows[1].d == 0.0 and table.rows[2].d == 0.0
    assert table.rows[3].d == pytest.approx(0.163941, abs=URDF_ROUNDING)


@pytest.mark.parametrize("tilt", [1e-3, 1e-5])
@pytest.mark.parametrize("convention", CONVENTIONS)
@pytest.mark.parametrize("name", ROBOTS)
def test_a_calibrated_chain_is_reproduced_exactly(name, convention, tilt):
    """Joint origins turned by ~tilt rad (a calibration's 0.05 deg is 1e-3): the nominally parallel axes' common
    normal moves up to 0.6 / tilt m away, and the table still holds the geometry to 1e-9."""
    for seed in range(3):
        chain = calibrated(robot(name), seed, rotation_rad=tilt)
        table = dh_table(chain, convention)
        assert_reproduces_fk(table, chain, seed)
        assert not any("are parallel:" in note for note in table.notes)  # tilted: no longer exactly parallel
        assert any("joints 2 (" in note and "nearly parallel" in note for note in table.notes)


def test_a_calibration_tilt_makes_parallel_axes_ill_conditioned():
    """What the note warns of: a 1 mrad tilt of the UR10's joint 3 towards joint 2 makes the two axes meet
    612 m away, where their common normal now lies: d_2 carries that distance, and d_4 takes it back (joints 3
    and 4 stay parallel, so d_3 = 0)."""
    nominal = robot("ur10")
    pre = nominal.pre.copy()
    pre[2] = pre[2] @ transform(np.array([0.0, 1e-3, 0.0]), np.zeros(3))
    chain = replace(nominal, pre=pre)
    table = dh_table(chain, "standard")
    assert abs(table.rows[1].d) == pytest.approx(612.0, rel=1e-3)
    assert table.rows[2].d == 0.0
    assert table.rows[1].d + table.rows[3].d == pytest.approx(0.163941, abs=1e-3)
    assert table.rows[1].a == pytest.approx(0.0, abs=TOL)  # the axes meet: the 0.612 m link length is gone
    assert "0.0573 deg apart" in table.notes[0] and "612 m along joint 2's axis" in table.notes[0]
    assert_reproduces_fk(table, chain)


@pytest.mark.parametrize("convention", CONVENTIONS)
def test_a_joint_zero_turned_about_its_axis_is_a_theta_offset(convention):
    nominal = robot("ur10")
    before = dh_table(nominal, convention)
    delta = 0.3
    pre = nominal.pre.copy()
    pre[1] = pre[1] @ rz(delta)  # the arm after joint 2 turned by delta at q = 0: a robot with another zero
    turned = replace(nominal, pre=pre)
    table = dh_table(turned, convention)
    assert_reproduces_fk(table, turned)
    assert table.rows[1].theta == pytest.approx(delta, abs=TOL)
    others = [0, 2, 3, 4, 5]
    for name in ("a", "alpha", "d", "theta"):
        np.testing.assert_allclose(table.column(name)[others], before.column(name)[others], atol=TOL)
    for name in ("a", "alpha", "d"):
        assert getattr(table.rows[1], name) == pytest.approx(getattr(before.rows[1], name), abs=TOL)
    # the same robot, its joint 2 frame relabelled: the turn undone in the next origin leaves the table as it was
    pre[2] = rz(-delta) @ pre[2]
    relabelled = dh_table(replace(nominal, pre=pre), convention)
    for name in ("a", "alpha", "d", "theta"):
        np.testing.assert_allclose(relabelled.column(name), before.column(name), atol=TOL)


@pytest.mark.parametrize("convention", CONVENTIONS)
def test_a_prismatic_joint_moves_d(convention):
    nominal = robot("kr16")
    revolute = nominal.revolute.copy()
    revolute[2] = False  # joint 3 slides along its axis
    chain = replace(nominal, revolute=revolute, continuous=np.zeros(nominal.dof, bool))
    table = dh_table(chain, convention)
    assert not table.rows[2].revolute and table.column("revolute").sum() == 5
    assert_reproduces_fk(table, chain)
    assert any(note.startswith("joint 3 (joint_3) is prismatic") for note in table.notes)
    # sliding joint 3 by 0.1 m moves the tip by 0.1 m, and does not turn it
    q = np.zeros((2, chain.dof))
    q[1, 2] = 0.1
    tips = dh_fk(table, q)
    assert np.linalg.norm(tips[1, :3, 3] - tips[0, :3, 3]) == pytest.approx(0.1, abs=TOL)
    np.testing.assert_allclose(tips[1, :3, :3], tips[0, :3, :3], atol=TOL)


@pytest.mark.parametrize("convention", CONVENTIONS)
def test_a_general_base_and_tool_come_as_transforms_with_notes(convention):
    nominal = robot("rx160")
    mount = transform(np.array([0.2, -0.3, 0.5]), np.array([0.4, -0.1, 0.05]))
    pre = nominal.pre.copy()
    pre[0] = mount @ pre[0]
    chain = replace(nominal, pre=pre).with_tool(transform(np.array([0.1, 0.6, -0.2]), np.array([0.01, 0.02, 0.15])))
    table = dh_table(chain, convention)
    assert_reproduces_fk(table, chain)
    axis = mount[:3, :3] @ nominal.axes[0]
    np.testing.assert_allclose(table.base[:3, 2], axis, atol=TOL)  # DH frame 0's z is joint 1's axis
    offset = table.base[:3, 3] - mount[:3, 3]
    np.testing.assert_allclose(np.cross(offset, axis), 0.0, atol=TOL)  # and its origin lies on that axis
    assert any(note.startswith("base:") and "'base_link'" in note for note in table.notes)
    assert any(note.startswith("tool: 'tool0'") for note in table.notes)


def test_coaxial_joints_are_noted():
    nominal = robot("ur10")
    pre = nominal.pre.copy()
    pre[1] = transform(np.zeros(3), np.array([0.0, 0.0, 0.2]))  # joint 2 on joint 1's axis
    chain = replace(nominal, pre=pre)
    for convention in CONVENTIONS:
        table = dh_table(chain, convention)
        assert_reproduces_fk(table, chain)
        assert any(note.startswith("joints 1 (") and "share one axis line" in note for note in table.notes)


def table_from_text(text: str) -> tuple[DHTable, list[str]]:
    """A table read back from :func:`format_dh`'s YAML as a controller would, with the joint names."""
    data = yaml.safe_load(text)

    def pose(entry: dict) -> np.ndarray:
        t = np.eye(4)
        t[:3, :3] = Rotation.from_euler("xyz", entry["rpy_rad"]).as_matrix()
        t[:3, 3] = entry["xyz_m"]
        return t

    rows = tuple(
        DHRow(j["a_m"], j["alpha_rad"], j["d_m"], j["theta_offset_rad"], j["type"] == "revolute")
        for j in data["joints"]
    )
    table = DHTable(data["convention"], rows, pose(data["base"]), pose(data["tool"]), tuple(data["notes"]))
    return table, [j["name"] for j in data["joints"]]


@pytest.mark.parametrize("convention", CONVENTIONS)
def test_the_text_reads_back_to_the_same_fk(convention):
    nominal = robot("ur10")
    pre = nominal.pre.copy()
    pre[0] = transform(np.array([0.1, -0.2, 0.3]), np.array([0.5, 0.2, 0.1])) @ pre[0]
    chain = calibrated(replace(nominal, pre=pre), 5).with_tool(transform(np.array([0, 0.4, 0]), [0, 0, 0.1]))
    table = dh_table(chain, convention)
    text = format_dh(table, chain.joint_names)
    assert text.startswith("# Denavit-Hartenberg table, " + convention)
    read, names = table_from_text(text)
    assert names == list(chain.joint_names)
    assert read.notes == table.notes and len(read.notes) >= 4  # 2 nearly parallel pairs, base, tool
    assert_reproduces_fk(read, chain)


def test_the_ur10_text_has_units_in_its_keys():
    chain = robot("ur10")
    data = yaml.safe_load(format_dh(dh_table(chain, "standard"), chain.joint_names))
    assert data["convention"] == "standard" and (data["base_link"], data["tip_link"]) == ("base_link", "tool0")
    assert set(data["joints"][0]) == {"name", "type", "a_m", "alpha_rad", "d_m", "theta_offset_rad"}
    assert data["joints"][1]["a_m"] == pytest.approx(-0.612)
    assert data["base"] == {"xyz_m": [0.0, 0.0, 0.0], "rpy_rad": [0.0, 0.0, 0.0]}
    assert data["tool"] == {"xyz_m": [0.0, 0.0, 0.0], "rpy_rad": [0.0, 0.0, 0.0]}
    assert len(data["notes"]) == 2


def test_wrong_inputs_are_refused():
    chain = robot("ur10")
    with pytest.raises(KinematicsError, match="unknown DH convention 'craig'"):
        dh_table(chain, "craig")
    table = dh_table(chain)
    with pytest.raises(KinematicsError, match="expected joints of shape"):
        dh_fk(table, np.zeros((3, 5)))
    with pytest.raises(KinematicsError, match="5 joint names"):
        format_dh(table, chain.joint_names[:5])
