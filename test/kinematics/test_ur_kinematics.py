"""A UR kinematics file as the nominal robot: ur_description's layout, the file's round trip, and bad files."""

from __future__ import annotations

import warnings
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from hybrid_kinematics_ros.kinematics import fk
from hybrid_kinematics_ros.kinematics.chain import chain_from_urdf
from hybrid_kinematics_ros.kinematics.errors import KinematicsError
from hybrid_kinematics_ros.kinematics.robot_config import CONFIG_DIR, load_robot_config
from hybrid_kinematics_ros.kinematics.ur_kinematics import (
    ENTRIES,
    UR_JOINTS,
    TemplateInertialWarning,
    chain_from_ur_kinematics,
    format_ur_kinematics,
    parse_ur_kinematics,
    read_ur_kinematics,
    ur_kinematics_from_chain,
    ur_urdf,
    urdf_from_ur_kinematics,
)

UR_DIR = CONFIG_DIR / "ur_kinematics"
UR10 = UR_DIR / "ur10_default.yaml"
TEMPLATE = (CONFIG_DIR / "ur10.urdf").read_text()
HALF_TURN_Z = np.diag([-1.0, -1.0, 1.0, 1.0])  # base_link -> base_link_inertia in ur_description


def embedded_ur10():
    return chain_from_urdf(CONFIG_DIR / "ur10.urdf", "base_link", "tool0")


def random_joints(n: int = 200, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-2 * np.pi, 2 * np.pi, (n, 6))


def test_the_ur10_default_file_is_the_embedded_ur10_behind_ur_descriptions_base_turn():
    """ur_description's base_link is the embedded UR10's base turned by π about z; the rest, tool0 included
    (ur_description's flange and tool0 turns undo each other), is the same robot."""
    chain = chain_from_ur_kinematics(UR10)
    assert (chain.base_link, chain.tip_link, chain.joint_names) == ("base_link", "tool0", UR_JOINTS)
    q = random_joints()
    np.testing.assert_allclose(fk.fk(chain, q), HALF_TURN_Z @ fk.fk(embedded_ur10(), q), atol=1e-7)
    frames = {name: frame for name, (_, frame) in chain.link_frames.items()}
    np.testing.assert_allclose(frames["tool0"], np.eye(4), atol=1e-12)  # tool0 is wrist_3_link's frame
    flange = Rotation.from_matrix(frames["flange"][:3, :3])
    assert flange.apply([1.0, 0.0, 0.0]) == pytest.approx([0.0, 0.0, 1.0], abs=1e-12)  # flange x: tool z


def test_inertials_and_limits_come_from_the_template_in_the_same_link_frames():
    chain, template = chain_from_ur_kinematics(UR10), embedded_ur10()
    np.testing.assert_array_equal(chain.segment_mass, template.segment_mass)
    np.testing.assert_allclose(chain.segment_com, template.segment_com, atol=1e-12)
    np.testing.assert_array_equal(chain.lower, template.lower)
    np.testing.assert_array_equal(chain.upper, template.upper)
    assert chain.inertial_warnings == ()


def test_the_urdf_carries_the_files_numbers_and_ur_descriptions_names():
    kin = read_ur_kinematics(UR10)
    root = ET.fromstring(ur_urdf(UR10))
    joints = {joint.get("name"): joint for joint in root.iter("joint")}
    for name, origin in zip(UR_JOINTS, kin.origins, strict=True):
        element = joints[name].find("origin")
        assert tuple(float(v) for v in element.get("xyz").split()) == origin.xyz
        assert tuple(float(v) for v in element.get("rpy").split()) == origin.rpy
        assert joints[name].find("axis").get("xyz") == "0 0 1"
    links = {link.get("name") for link in root.iter("link")}
    assert {"base_link", "base_link_inertia", "shoulder_link", "wrist_3_link", "flange", "tool0", "base"} <= links
    assert kin.kinematics_hash in ur_urdf(UR10)  # the URDF says what it was built from


@pytest.mark.parametrize("model", ["ur10", "ur5e", "ur10e"])
def test_shipped_defaults_read_back_exactly_and_name_their_origin(model):
    path = UR_DIR / f"{model}_default.yaml"
    text = path.read_text()
    assert "Universal_Robots_ROS2_Description" in text and "BSD-3-Clause" in text
    kin = read_ur_kinematics(path)
    again = parse_ur_kinematics(kin.text("a comment"), "again")
    assert (again.origins, again.kinematics_hash) == (kin.origins, kin.kinematics_hash)
    assert (UR_DIR / "LICENSE").read_text().count("Redistribution and use in source and binary forms") == 1


def test_written_joint_origins_read_back_as_the_same_transforms():
    rng = np.random.default_rng(1)
    entries = {}
    for name in ENTRIES:
        t = np.eye(4)
        t[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
        t[:3, 3] = rng.normal(scale=0.3, size=3)
        entries[name] = t
    entries["forearm"][:3, 3] = [1e-5, -2e-11, 0.0]  # exponents that PyYAML must read as numbers
    text = format_ur_kinematics(entries, "calib_42", "exported\nby a test")
    assert text.startswith("# exported\n# by a test\nkinematics:\n")
    raw = yaml.safe_load(text)["kinematics"]
    assert all(isinstance(raw[name][key], float) for name in ENTRIES for key in raw[name])
    kin = parse_ur_kinematics(text)
    assert kin.kinematics_hash == "calib_42"
    for name, matrix in kin.matrices().items():
        np.testing.assert_allclose(matrix, entries[name], atol=1e-15)


def test_hashes_that_yaml_would_read_as_other_types_stay_strings():
    origins = read_ur_kinematics(UR10).matrices()
    for value in ("123", "true", "calib: x", "null"):
        assert parse_ur_kinematics(format_ur_kinematics(origins, value)).kinematics_hash == value


def test_a_calibrated_chain_exports_to_a_file_that_rebuilds_it():
    """The export path: a chain whose joint origins a calibration moved, written out and read back, serves the
    same FK; from ur_description's layout, and from the embedded UR10, whose base is base_link_inertia's."""
    rng = np.random.default_rng(2)
    for base, turn in ((chain_from_ur_kinematics(UR10), np.eye(4)), (embedded_ur10(), HALF_TURN_Z)):
        nudges = np.array([np.eye(4) for _ in range(6)])
        nudges[:, :3, 3] = rng.normal(scale=1e-3, size=(6, 3))
        nudges[:, :3, :3] = Rotation.from_rotvec(rng.normal(scale=1e-3, size=(6, 3))).as_matrix()
        calibrated = base.with_geometry(base.pre @ nudges, base.post)
        text = ur_kinematics_from_chain(calibrated, "calib_exported").text()
        rebuilt = chain_from_urdf(urdf_from_ur_kinematics(parse_ur_kinematics(text), TEMPLATE), "base_link", "tool0")
        q = random_joints(50, 3)
        np.testing.assert_allclose(fk.fk(rebuilt, q), turn @ fk.fk(calibrated, q), atol=1e-12)


def test_the_chain_of_another_robot_has_no_ur_kinematics():
    with pytest.raises(KinematicsError, match="not a UR's"):
        ur_kinematics_from_chain(load_robot_config("rx160").chain, "x")


def replaced(text: str, old: str, new: str) -> str:
    assert old in text
    return text.replace(old, new, 1)


GOOD = UR10.read_text()
BAD_FILES = [
    ("not: [valid", "not valid YAML"),
    ("shoulder: {x: 0}\n", "missing field 'kinematics'"),
    (replaced(GOOD, "  wrist_2:", "  wrist_two:"), "missing field 'kinematics.wrist_2'"),
    (replaced(GOOD, "    z: 0.163941\n", ""), "missing field 'kinematics.wrist_1.z'"),
    (replaced(GOOD, "z: 0.163941", "z: 16 cm"), "field 'kinematics.wrist_1.z': '16 cm' is not a number (m)"),
    (replaced(GOOD, "roll: 1.570796327", "roll: true"), "field 'kinematics.upper_arm.roll': True is not a number"),
    (replaced(GOOD, "x: -0.612", "x: .nan"), "field 'kinematics.forearm.x': nan is not finite"),
    (
        replaced(GOOD, "  forearm:\n", "  forearm: 3\n  forearm_old:\n"),
        "field 'kinematics.forearm': expected a mapping",
    ),
    (GOOD[: GOOD.index("  hash:")], "missing field 'kinematics.hash'"),
]


@pytest.mark.parametrize(("text", "message"), BAD_FILES)
def test_bad_files_name_the_file_and_the_field(tmp_path, text, message):
    path = tmp_path / "robot_calibration.yaml"
    path.write_text(text)
    with pytest.raises(KinematicsError) as caught:
        read_ur_kinematics(path)
    assert str(caught.value).startswith(f"{path}: ") and message in str(caught.value)


def test_yaml_cpp_exponents_without_a_point_are_numbers(tmp_path):
    path = tmp_path / "robot_calibration.yaml"
    path.write_text(replaced(GOOD, "z: 0.163941", "z: 1e-05"))
    assert read_ur_kinematics(path).origins[3].xyz[2] == 1e-05


def test_a_missing_file_is_named(tmp_path):
    with pytest.raises(KinematicsError, match=f"UR kinematics file {tmp_path / 'none.yaml'} does not exist"):
        read_ur_kinematics(tmp_path / "none.yaml")


def test_a_template_that_is_not_a_ur_in_ur_descriptions_layout_is_refused():
    with pytest.raises(KinematicsError, match="has no joint 'shoulder_pan_joint'"):
        chain_from_ur_kinematics(UR10, CONFIG_DIR / "rx160.urdf")
    # a UR URDF whose shoulder_lift frame is turned another way (older layouts): its inertials would sit elsewhere
    turned = replaced((CONFIG_DIR / "ur10.urdf").read_text(), 'rpy="1.57079633 0 0"', 'rpy="0 1.57079633 0"')
    with pytest.raises(KinematicsError, match=r"joint 'shoulder_lift_joint' turns its origin by 120\.0 deg"):
        chain_from_ur_kinematics(UR10, turned)


def test_a_template_of_another_ur_model_is_reported_with_the_inertials():
    with pytest.warns(TemplateInertialWarning, match="another UR model"):
        chain = chain_from_ur_kinematics(UR_DIR / "ur5e_default.yaml")
    assert any("another UR model" in note for note in chain.inertial_warnings)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert chain_from_ur_kinematics(UR_DIR / "ur10e_default.yaml").inertial_warnings == ()


def test_the_built_urdf_is_itself_a_template_and_keeps_the_configs_gravity(tmp_path):
    """A robot config with the file: its working range, tool and payload apply, and its gravity turns with the
    base from the embedded UR10's frame into ur_description's base_link (not for a ur_description template)."""
    (tmp_path / "ur_description.urdf").write_text(ur_urdf(UR10))
    for urdf, expected in ((CONFIG_DIR / "ur10.urdf", [-9.81, 0.0, 0.0]), ("ur_description.urdf", [9.81, 0.0, 0.0])):
        config = tmp_path / "wall.yaml"
        config.write_text(
            f"urdf: {urdf}\nbase_link: base_link\ntip_link: tool0\ngravity: [9.81, 0.0, 0.0]\n"
            "tool: {xyz: [0.0, 0.0, 0.1]}\npayload: {mass: 3.0}\njoint_limits: {lower: [-1, -2, -2, -3, -3, -3], "
            "upper: [1, 0, 2, 3, 3, 3]}\n"
        )
        loaded = load_robot_config(config, ur_kinematics=UR10)
        np.testing.assert_allclose(loaded.gravity, expected, atol=1e-12)
        np.testing.assert_array_equal(loaded.chain.lower, [-1, -2, -2, -3, -3, -3])
        assert loaded.payload_mass == 3.0 and loaded.chain.tool[2, 3] == 0.1
        q = random_joints(20, 4)
        plain = chain_from_ur_kinematics(UR10)
        np.testing.assert_allclose(fk.fk(loaded.chain, q), fk.fk(plain, q) @ loaded.chain.tool, atol=1e-12)


def _xacro_fk(entries: dict, q: np.ndarray) -> np.ndarray:
    """FK as ur_description's xacro composes it, written out by hand from the file's numbers: base_link to
    base_link_inertia (π about z), each entry ``Trans(x y z) · RPY(roll pitch yaw)`` then the joint about its z,
    then the flange (rpy 0 −π/2 −π/2) and tool0 (rpy π/2 0 π/2)."""

    def frame(xyz, rpy) -> np.ndarray:
        t = np.eye(4)
        t[:3, :3] = Rotation.from_euler("xyz", rpy).as_matrix()  # URDF rpy: fixed axes x, y, z
        t[:3, 3] = xyz
        return t

    out = np.broadcast_to(frame([0, 0, 0], [0, 0, np.pi]), (len(q), 4, 4))
    for k, name in enumerate(ENTRIES):
        e = entries[name]
        turn = np.tile(np.eye(4), (len(q), 1, 1))
        turn[:, :3, :3] = Rotation.from_euler("z", q[:, k, None]).as_matrix()
        out = out @ frame([e["x"], e["y"], e["z"]], [e["roll"], e["pitch"], e["yaw"]]) @ turn
    return out @ frame([0, 0, 0], [0, -np.pi / 2, -np.pi / 2]) @ frame([0, 0, 0], [np.pi / 2, 0, np.pi / 2])


def test_the_ur10e_file_and_a_perturbed_copy_build_the_robot_the_xacro_builds(tmp_path):
    raw = yaml.safe_load((UR_DIR / "ur10e_default.yaml").read_text())["kinematics"]
    rng = np.random.default_rng(4)
    perturbed = {name: {key: value + rng.normal(scale=1e-3) for key, value in raw[name].items()} for name in ENTRIES}
    q = random_joints(10_000, 5)
    for entries in (raw, perturbed):
        path = tmp_path / "ur10e.yaml"
        path.write_text(yaml.safe_dump({"kinematics": {**entries, "hash": "calib_test"}}))
        chain = chain_from_ur_kinematics(path)
        np.testing.assert_allclose(fk.fk(chain, q), _xacro_fk(entries, q), atol=1e-9)
