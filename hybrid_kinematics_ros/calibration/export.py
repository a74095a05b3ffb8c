"""The calibrated geometry in the files users keep: a URDF (MoveIt, robot_state_publisher), a UR kinematics
file (ur_robot_driver's ``kinematics_params_file``) or a DH table (controllers that take one).

A URDF has joint origins and nothing else, so it carries the parametric stage's geometry-only fit (the
stage fits one beside the full model, so that the geometry absorbs what it can of the compliance): the
corrected joint origins, each joint's zero offset (a turn about its own axis, which commutes with the
joint's motion) and the flange correction (folded into the last fixed joint before the tip). Compliance, bending
and the nets cannot be expressed; :func:`export_urdf`'s caller should report how much accuracy is left.
"""

from __future__ import annotations

import hashlib
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.calibration.evaluate import error_stats, pose_errors_of, target_errors
from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.kinematics import fk, se3
from hybrid_kinematics_ros.kinematics.chain import Chain, chain_from_urdf
from hybrid_kinematics_ros.kinematics.dh import dh_table, format_dh
from hybrid_kinematics_ros.kinematics.ur_kinematics import ENTRIES, UR_JOINTS, format_ur_kinematics
from hybrid_kinematics_ros.model.hybrid import HybridModel
from hybrid_kinematics_ros.model.parametric import model_from_manifest
from hybrid_kinematics_ros.model.referencing import to_base_frame


def _origin(joint: ET.Element) -> np.ndarray:
    t = np.eye(4)
    origin = joint.find("origin")
    if origin is not None:
        t[:3, 3] = [float(v) for v in origin.get("xyz", "0 0 0").split()]
        t[:3, :3] = Rotation.from_euler("xyz", [float(v) for v in origin.get("rpy", "0 0 0").split()]).as_matrix()
    return t


def _set_origin(joint: ET.Element, t: np.ndarray) -> None:
    origin = joint.find("origin")
    if origin is None:
        origin = ET.SubElement(joint, "origin")
    origin.set("xyz", " ".join(f"{v:.12g}" for v in t[:3, 3]))
    origin.set("rpy", " ".join(f"{v:.12g}" for v in Rotation.from_matrix(t[:3, :3]).as_euler("xyz")))


def export_urdf(model: HybridModel) -> str:
    """The model's URDF with the parametric stage's geometry in its joint origins.

    Raises:
        CalibrationError: no parametric stage, or no fixed joint after the last joint to hold the flange
            correction.
    """
    if not model.has_parametric:
        raise CalibrationError("the model has no parametric stage: retrain with --parametric to export a URDF")
    chain = model.chain
    calibrated = model_from_manifest(chain, model.manifest["parametric"], rigid=True)
    root = ET.fromstring(chain.urdf_text)
    by_child = {j.find("child").get("link"): j for j in root.iter("joint")}
    path, link = [], chain.tip_link
    while link != chain.base_link:
        path.append(by_child[link])
        link = path[-1].find("parent").get("link")
    path.reverse()
    fixed = np.eye(4)
    k = 0
    last_fixed = None
    for joint in path:
        if joint.get("type") == "fixed":
            fixed = fixed @ _origin(joint)
            last_fixed = joint
            continue
        new = se3.inverse(fixed) @ calibrated.chain.pre[k]
        zero = calibrated.zero_offset[k]
        turn = np.eye(4)
        if chain.revolute[k]:
            turn[:3, :3] = Rotation.from_rotvec(zero * chain.axes[k]).as_matrix()
        else:
            turn[:3, 3] = zero * chain.axes[k]
        _set_origin(joint, new @ turn)
        fixed, last_fixed, k = np.eye(4), None, k + 1
    flange = se3.inverse(chain.post) @ calibrated.chain.post  # the correction after the last joint
    if not np.allclose(flange, np.eye(4), atol=1e-12):
        if last_fixed is None:
            raise CalibrationError(
                f"the URDF has no fixed joint between the last joint and '{chain.tip_link}' to hold the flange "
                "correction; add a flange link"
            )
        tool = chain.tool
        _set_origin(last_fixed, _origin(last_fixed) @ tool @ flange @ se3.inverse(tool))
    root.set("name", f"{root.get('name', 'robot')}_calibrated")
    comment = ET.Comment(
        " Joint origins calibrated by hybrid_kinematics_ros (geometry and zero offsets only; "
        f"compliance and the residual nets are not in this file). Model: {model.path} "
    )
    root.insert(0, comment)
    return ET.tostring(root, encoding="unicode", xml_declaration=True)


FORMATS = ("urdf", "ur-kinematics", "dh")
LEFT_BEHIND = "the compliance, bending, cyclic joint errors, backlash and the residual nets"


@dataclass(frozen=True)
class Exported:
    """A calibration in a file users keep: its text, the geometry it describes (a chain from the model's base
    link to its tip, to judge it by), and what of the model it cannot carry."""

    text: str
    chain: Chain
    left: tuple[str, ...]
    tip_correction: np.ndarray = field(default_factory=lambda: np.eye(4))  # what to append at the tip (a TCP)


def export(model: HybridModel, form: str, convention: str = "standard") -> Exported:
    """The model's calibrated geometry in ``form`` (one of :data:`FORMATS`); ``convention`` for DH tables."""
    if form not in FORMATS:
        raise CalibrationError(f"unknown export format '{form}'; choose one of {', '.join(FORMATS)}")
    urdf = export_urdf(model)
    chain = _chain_of(model, urdf)
    if form == "urdf":
        return Exported(urdf, chain, (LEFT_BEHIND,))
    if form == "dh":
        table = dh_table(chain, convention)
        return Exported(format_dh(table, chain.joint_names), chain, (LEFT_BEHIND, *table.notes))
    return _ur_kinematics(model, urdf)


def _chain_of(model: HybridModel, urdf: str) -> Chain:
    return chain_from_urdf(urdf, model.chain.base_link, model.chain.tip_link).with_tool(model.chain.tool)


def _ur_kinematics(model: HybridModel, urdf: str) -> Exported:
    """The six joint origins as a UR kinematics file. Its hash is new, so that the UR driver warns that the
    file no longer matches the controller's own calibration. The xacro fixes the flange, so the flange
    correction's part along wrist 3's axis (a shift along it and a turn about it, which commute with the joint)
    moves into wrist 3's origin; the rest has no entry and is named in what the file leaves behind."""
    root = ET.fromstring(urdf)
    joints = {j.get("name"): j for j in root.iter("joint")}
    missing = [name for name in UR_JOINTS if name not in joints]
    if missing or model.chain.joint_names != UR_JOINTS:
        raise CalibrationError(
            f"the model's joints are {', '.join(model.chain.joint_names)}, not a UR's ({', '.join(UR_JOINTS)}): "
            "a UR kinematics file cannot describe it; export --format urdf or dh"
        )
    chain = model.chain
    flange = se3.inverse(chain.post) @ model_from_manifest(chain, model.manifest["parametric"], rigid=True).chain.post
    along, across = split_along_axis(chain.post @ flange @ se3.inverse(chain.post), chain.axes[-1])
    wrist_3 = joints[UR_JOINTS[-1]]
    _set_origin(wrist_3, _origin(wrist_3) @ along)
    origins = [_origin(joints[name]) for name in UR_JOINTS]
    digest = hashlib.sha256(np.round(np.array(origins), 12).tobytes()).hexdigest()[:16]
    text = format_ur_kinematics(
        dict(zip(ENTRIES, origins, strict=True)),
        f"calib_hkr_{digest}",
        f"Calibrated by hybrid_kinematics_ros from model {model.path}: joint origins with the zero offsets "
        "and the flange correction along wrist 3's axis folded in. The hash is new, so ur_robot_driver warns "
        "that this file is not the controller's own calibration. Not in this file: the flange correction "
        "across wrist 3's axis, " + LEFT_BEHIND + ".",
    )
    nominal = {j.get("name"): j for j in ET.fromstring(chain.urdf_text).iter("joint")}
    for joint in root.iter("joint"):  # the fixed joints after the wrist back at the nominal URDF's
        if joint.get("type") == "fixed" and joint.get("name") in nominal and joint.get("name") not in UR_JOINTS:
            _set_origin(joint, _origin(nominal[joint.get("name")]))
    tip = se3.inverse(chain.post) @ across @ chain.post  # in the tip's frame, as a TCP is given
    xyz = " ".join(f"{v:.4f}" for v in tip[:3, 3] * 1e3)
    rpy = " ".join(f"{v:.5f}" for v in np.degrees(Rotation.from_matrix(tip[:3, :3]).as_euler("xyz")))
    left = (
        f"the flange correction across wrist 3's axis: xyz {xyz} mm, rpy {rpy} deg in {chain.tip_link}'s frame "
        "(append it to the TCP or to the end effector's fixed joint)",
        LEFT_BEHIND,
    )
    return Exported(text, _chain_of(model, ET.tostring(root, encoding="unicode")), left, tip)


def split_along_axis(correction: np.ndarray, axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``correction = along @ across``: ``along`` a shift along the unit ``axis`` and a turn about it (it
    commutes with a joint about ``axis``), ``across`` what is left, with no shift along the axis and a rotation
    about an axis perpendicular to it (swing-twist)."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    x, y, z, w = Rotation.from_matrix(correction[:3, :3]).as_quat()
    twist = np.array([*(np.dot([x, y, z], axis) * axis), w])
    along = np.eye(4)
    along[:3, :3] = (
        Rotation.from_quat(twist / np.linalg.norm(twist)).as_matrix() if np.linalg.norm(twist) else np.eye(3)
    )
    along[:3, 3] = np.dot(correction[:3, 3], axis) * axis
    return along, se3.inverse(along) @ correction


def held_out_errors(model: HybridModel, exported: Exported, stations: Sequence[Pairs]) -> dict[str, dict]:
    """Error statistics at the target on held-out ``stations``: the URDF model with its own referencing
    (``nominal``), the exported geometry, the stage and the full model (``hybrid``), the last three with the
    model's referencing."""
    errors: dict[str, list] = {}
    for pairs in stations:
        for name, values in pose_errors_of(model, pairs).items():
            errors.setdefault({"analytic": "nominal"}.get(name, name), []).append(values)
        base = to_base_frame([pairs], model.chain, model.referencings)
        errors.setdefault("exported", []).append(target_errors(base, fk.fk(exported.chain, base.q)))
    return {
        name: error_stats(*(np.concatenate([p[k] for p in parts]) for k in (0, 1))) for name, parts in errors.items()
    }
