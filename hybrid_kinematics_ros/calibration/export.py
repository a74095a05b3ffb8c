"""The calibrated geometry as a URDF, for tools that only read URDFs (MoveIt, robot_state_publisher).

A URDF has joint origins and nothing else, so it carries the parametric stage's geometry-only fit (the
stage fits one beside the full model, so that the geometry absorbs what it can of the compliance): the
corrected joint origins, each joint's zero offset (a turn about its own axis, which commutes with the
joint's motion) and the flange correction (folded into the last fixed joint before the tip). Compliance, bending
and the nets cannot be expressed; :func:`export_urdf`'s caller should report how much accuracy is left.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
from scipy.spatial.transform import Rotation

from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.kinematics import se3
from hybrid_kinematics_ros.model.hybrid import HybridModel
from hybrid_kinematics_ros.model.parametric import model_from_manifest


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
