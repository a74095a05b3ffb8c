"""A UR kinematics file as the nominal robot, and a calibrated geometry back into one.

Universal Robots users keep their robot's factory calibration in the YAML file ``ur_calibration`` extracts
from the controller (ur_description ships each model's defaults as ``default_kinematics.yaml``)::

    kinematics:
      shoulder: {x: 0, y: 0, z: 0.1273, roll: 0, pitch: 0, yaw: 0}
      upper_arm: ...
      forearm: ...
      wrist_1: ...
      wrist_2: ...
      wrist_3: ...
      hash: calib_12345

Each entry is a joint's origin in its parent link (m; roll, pitch, yaw as URDF ``rpy``: fixed axes x, y, z).
ur_description's xacro builds the robot from it as

    base_link -> base_link_inertia (fixed, rpy 0 0 π) -> shoulder_pan_joint (``shoulder``) -> shoulder_link
    -> shoulder_lift_joint (``upper_arm``) -> upper_arm_link -> elbow_joint (``forearm``) -> forearm_link
    -> wrist_1_joint (``wrist_1``) -> wrist_1_link -> wrist_2_joint (``wrist_2``) -> wrist_2_link
    -> wrist_3_joint (``wrist_3``) -> wrist_3_link -> flange (fixed, rpy 0 -π/2 -π/2) -> tool0 (fixed, rpy π/2 0 π/2)

with every joint turning about its z axis, and :func:`urdf_from_ur_kinematics` writes the same URDF. The
file carries no masses or limits: those come from a template URDF of a UR (the embedded ``config/ur10.urdf``
unless a robot config names another), whose link frames are ur_description's, so that each link's inertial
keeps its place. ``base_link`` is REP-103 aligned and turned by π about z from the controller's base frame,
which is why ``base_link_inertia`` exists; ``tool0`` coincides with ``wrist_3_link``.
"""

from __future__ import annotations

import copy
import json
import math
import re
import textwrap
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from hybrid_kinematics_ros.kinematics.chain import LEADING_JUNK, Chain, ImplausibleInertialWarning, chain_from_urdf
from hybrid_kinematics_ros.kinematics.errors import KinematicsError
from hybrid_kinematics_ros.kinematics.paths import config_dir, resolve_path

ENTRIES = ("shoulder", "upper_arm", "forearm", "wrist_1", "wrist_2", "wrist_3")
FIELDS = ("x", "y", "z", "roll", "pitch", "yaw")
UR_JOINTS = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)
UR_LINKS = ("shoulder_link", "upper_arm_link", "forearm_link", "wrist_1_link", "wrist_2_link", "wrist_3_link")
BASE_LINK = "base_link"
TIP_LINK = "tool0"
DEFAULT_TEMPLATE = "ur10.urdf"  # in config/: the embedded UR10, whose link frames are ur_description's
# The joint origins' rotations every UR model shares (ur_description's default files); a template's link frames
# are ur_description's when its joint origins turn the same way, within FRAME_TOLERANCE_RAD.
QUARTER = math.pi / 2
NOMINAL_RPY = ((0, 0, 0), (QUARTER, 0, 0), (0, 0, 0), (0, 0, 0), (QUARTER, 0, 0), (-QUARTER, 0, 0))
FRAME_TOLERANCE_RAD = 0.1  # far above a calibration's corrections, far below the quarter turns of other layouts
SIZE_TOLERANCE = 0.1  # a template more than 10 % longer or shorter than the file is another UR model
# the fixed joints around the six, as ur_description's xacro writes them: (name, parent, child, rpy)
BASE_JOINT = ("base_link-base_link_inertia", BASE_LINK, "base_link_inertia", (0.0, 0.0, math.pi))
TIP_JOINTS = (
    ("wrist_3-flange", "wrist_3_link", "flange", (0.0, -math.pi / 2, -math.pi / 2)),
    ("flange-tool0", "flange", TIP_LINK, (math.pi / 2, 0.0, math.pi / 2)),
)
OFF_CHAIN_JOINTS = (  # frames ur_description offers beside the chain: the controller's base, the F/T sensor's frame
    ("base_link-base_fixed_joint", BASE_LINK, "base", (0.0, 0.0, math.pi)),
    ("wrist_3_link-ft_frame", "wrist_3_link", "ft_frame", (math.pi, 0.0, 0.0)),
)
ROUNDING = 1e-14  # m or rad: what UROrigin.of_matrix rounds to zero
_PLAIN_HASH = re.compile(r"^[A-Za-z_][A-Za-z0-9_.-]*$")


class TemplateInertialWarning(ImplausibleInertialWarning):
    """The template URDF is a UR of another size than the kinematics file: its masses, centres of mass and
    limits are another model's, so the parametric stage's joint torques are approximate."""


@dataclass(frozen=True)
class UROrigin:
    """One entry of a UR kinematics file: a joint's origin in its parent link (m; URDF rpy, rad)."""

    xyz: tuple[float, float, float]
    rpy: tuple[float, float, float]

    @property
    def matrix(self) -> np.ndarray:
        """The 4x4 transform from the parent link to the joint's frame."""
        t = np.eye(4)
        t[:3, :3] = Rotation.from_euler("xyz", self.rpy).as_matrix()
        t[:3, 3] = self.xyz
        return t

    @classmethod
    def of_matrix(cls, t: np.ndarray) -> UROrigin:
        """The entry of a 4x4 transform (rpy in URDF's convention, each in [-π, π])."""
        t = np.asarray(t, dtype=float)
        if t.shape != (4, 4) or not np.all(np.isfinite(t)):
            raise KinematicsError(f"a UR kinematics entry needs a finite 4x4 transform, got shape {t.shape}")
        rpy = Rotation.from_matrix(t[:3, :3]).as_euler("xyz")
        return cls(_clean(t[:3, 3]), _clean(rpy))


@dataclass(frozen=True)
class URKinematics:
    """A UR kinematics file: the six joint origins in :data:`ENTRIES` order, and the hash that names the
    calibration (ur_robot_driver compares it with the controller's)."""

    origins: tuple[UROrigin, ...]
    kinematics_hash: str
    source: str = ""  # where it was read from, for messages

    def __post_init__(self) -> None:
        if len(self.origins) != len(ENTRIES):
            raise KinematicsError(f"a UR kinematics file has {len(ENTRIES)} entries, got {len(self.origins)}")

    def matrices(self) -> dict[str, np.ndarray]:
        """Entry name -> its 4x4 joint origin."""
        return {name: origin.matrix for name, origin in zip(ENTRIES, self.origins, strict=True)}

    def text(self, comment: str = "") -> str:
        """The file, with each entry's numbers as they are (a round trip through :func:`parse_ur_kinematics`
        gives them back exactly)."""
        return _format(self.origins, self.kinematics_hash, comment)


def _clean(values: np.ndarray) -> tuple[float, float, float]:
    """Three floats without the rounding dust of a matrix's decomposition (below 1e-14) or negative zeros,
    which a file would show as ``2.220446049250313e-16`` and ``-0.0``."""
    return tuple(0.0 if abs(v) < ROUNDING else float(v) for v in values)


# ------------------------------------------------------------------------------------------------- reading
def read_ur_kinematics(path: str | Path) -> URKinematics:
    """Read and check a UR kinematics file (a path or ``package://pkg/path``).

    Raises:
        KinematicsError: the file is missing, not YAML, or lacks or misstates a field; the message names the
            file and the field.
    """
    resolved = resolve_path(path)
    if not resolved.is_file():
        where = "" if str(resolved) == str(path) else f" ({resolved})"
        raise KinematicsError(f"UR kinematics file {path}{where} does not exist")
    return parse_ur_kinematics(resolved.read_text(encoding="utf-8-sig"), str(path))


def parse_ur_kinematics(text: str, where: str = "UR kinematics") -> URKinematics:
    """The kinematics of a UR kinematics file's text; ``where`` names it in errors."""
    try:
        raw = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise KinematicsError(f"{where}: not valid YAML: {exc}") from exc
    if not isinstance(raw, dict) or not isinstance(raw.get("kinematics"), dict):
        raise KinematicsError(f"{where}: missing field 'kinematics' (a mapping of the six joint origins and 'hash')")
    section = raw["kinematics"]
    origins = tuple(_origin(section, name, where) for name in ENTRIES)
    if "hash" not in section:
        raise KinematicsError(f"{where}: missing field 'kinematics.hash' (ur_description's xacro needs it)")
    value = section["hash"]
    if isinstance(value, dict | list) or value is None or not str(value).strip():
        raise KinematicsError(f"{where}: field 'kinematics.hash': expected a name such as calib_123, got {value!r}")
    return URKinematics(origins, str(value), where)


def _origin(section: dict[str, Any], name: str, where: str) -> UROrigin:
    entry = section.get(name)
    if entry is None:
        raise KinematicsError(f"{where}: missing field 'kinematics.{name}'")
    if not isinstance(entry, dict):
        raise KinematicsError(f"{where}: field 'kinematics.{name}': expected a mapping of {', '.join(FIELDS)}")
    values = [_number(entry, name, key, where) for key in FIELDS]
    return UROrigin(tuple(values[:3]), tuple(values[3:]))


def _number(entry: dict[str, Any], name: str, key: str, where: str) -> float:
    field = f"kinematics.{name}.{key}"
    if key not in entry:
        raise KinematicsError(f"{where}: missing field '{field}'")
    value = entry[key]
    unit = "m" if key in "xyz" else "rad"
    try:
        if isinstance(value, bool):  # YAML's yes/no/true are not lengths
            raise TypeError
        number = float(value)  # yaml-cpp writes 1e-05, which PyYAML reads as a string
    except (TypeError, ValueError):
        raise KinematicsError(f"{where}: field '{field}': {value!r} is not a number ({unit})") from None
    if not math.isfinite(number):
        raise KinematicsError(f"{where}: field '{field}': {value!r} is not finite ({unit})")
    return number


# ------------------------------------------------------------------------------------------------- writing
def format_ur_kinematics(entries: Mapping[str, np.ndarray], kinematics_hash: str, comment: str = "") -> str:
    """A UR kinematics file of six joint origins.

    Args:
        entries: each of :data:`ENTRIES` to its 4x4 joint origin (m), as the joint's ``<origin>`` in its parent
            link; rotations are written as URDF rpy.
        kinematics_hash: the calibration's name (``kinematics.hash``).
        comment: written above the data as ``#`` lines (wrapped at 100 columns).

    Raises:
        KinematicsError: an entry is missing or is not a finite 4x4 transform.
    """
    missing = [name for name in ENTRIES if name not in entries]
    if missing:
        raise KinematicsError(
            f"a UR kinematics file needs the entries {', '.join(ENTRIES)}; missing {', '.join(missing)}"
        )
    return _format(tuple(UROrigin.of_matrix(entries[name]) for name in ENTRIES), kinematics_hash, comment)


def _format(origins: tuple[UROrigin, ...], kinematics_hash: str, comment: str) -> str:
    lines = [
        f"# {line}".rstrip() for paragraph in comment.splitlines() for line in textwrap.wrap(paragraph, 98) or [""]
    ]
    lines.append("kinematics:")
    for name, origin in zip(ENTRIES, origins, strict=True):
        lines.append(f"  {name}:")
        for key, value in zip(FIELDS, (*origin.xyz, *origin.rpy), strict=True):
            lines.append(f"    {key}: {_yaml_float(value)}")
    lines.append(f"  hash: {_yaml_string(kinematics_hash)}")
    return "\n".join(lines) + "\n"


def _yaml_float(value: float) -> str:
    """``repr`` of a float, with a decimal point before any exponent: PyYAML (and so xacro) reads ``1e-05`` as a
    string, ``1.0e-05`` as a number."""
    if not math.isfinite(value):
        raise KinematicsError(f"a UR kinematics file holds finite numbers, got {value}")
    text = repr(float(value) + 0.0)
    mantissa, _, exponent = text.partition("e")
    if exponent and "." not in mantissa:
        text = f"{mantissa}.0e{exponent}"
    return text


def _yaml_string(value: str) -> str:
    """A hash as a plain YAML scalar where it reads back as that string, else double-quoted."""
    if "\n" in value or not value.strip():
        raise KinematicsError(f"a UR kinematics hash is one non-empty line, got {value!r}")
    if _PLAIN_HASH.match(value) and yaml.safe_load(f"h: {value}")["h"] == value:
        return value
    return json.dumps(value)


def ur_kinematics_from_chain(chain: Chain, kinematics_hash: str) -> URKinematics:
    """The six joint origins of a UR chain (its ``pre``, which a calibration may have moved) as a UR kinematics
    file's entries. Fixed joints before a joint (``base_link_inertia``'s turn) are taken out, so a chain from
    a ur_description URDF and one from the embedded UR10 give the same file; what follows the last joint (the
    flange, a tool) has no entry, ur_description fixing it.

    Raises:
        KinematicsError: the chain's joints are not a UR's.
    """
    if chain.joint_names != UR_JOINTS:
        raise KinematicsError(
            f"the chain's joints are {', '.join(chain.joint_names)}, not a UR's ({', '.join(UR_JOINTS)})"
        )
    origins = [UROrigin.of_matrix(np.linalg.inv(parent_frame(chain, k)) @ chain.pre[k]) for k in range(chain.dof)]
    return URKinematics(tuple(origins), kinematics_hash)


def parent_frame(chain: Chain, k: int) -> np.ndarray:
    """The 4x4 frame of the link joint ``k`` hangs from, in joint k-1's frame after its motion (the base frame for
    k = 0): the fixed joints between the two, which ``chain.pre[k]`` includes before the joint's own origin."""
    before = [frame for index, frame in chain.link_frames.values() if index == k - 1]
    return before[-1] if before else np.eye(4)


# --------------------------------------------------------------------------------------------- URDF building
def urdf_from_ur_kinematics(kin: URKinematics, template_urdf_text: str, template_name: str = "") -> str:
    """The URDF ur_description's xacro builds from ``kin``, with the template's inertials and limits.

    Links and joints carry ur_description's names; each joint's origin is its entry's numbers as the file writes
    them, its axis z. Each moving link takes the inertial of the template's link that the same joint moves, and
    each joint the template's type (revolute or continuous) and ``<limit>``. ``template_name`` names the template
    in errors.

    Raises:
        KinematicsError: the template does not parse, lacks a UR joint, or its link frames are not
            ur_description's (its inertials would sit in other frames).
    """
    what = f"template URDF {template_name}".rstrip()
    template = _parse_template(template_urdf_text, what)
    joints = _template_joints(template, what)
    links = {link.get("name"): link for link in template.iter("link")}
    robot = ET.Element("robot", name=template.get("name") or "ur")
    # no paths: the same file on the same template gives the same text wherever it is built
    note = (
        f" Built by hybrid_kinematics_ros from a UR kinematics file (hash {kin.kinematics_hash}) as ur_description's "
        f"xacro builds it; inertials and limits from the template URDF '{robot.get('name')}'. "
    )
    robot.append(ET.Comment(note.replace("--", "- -")))  # "--" may not appear in an XML comment
    ET.SubElement(robot, "link", name=BASE_LINK)
    _fixed(robot, *BASE_JOINT)
    parents = (BASE_JOINT[2], *UR_LINKS[:-1])
    for k, (joint, origin) in enumerate(zip(joints, kin.origins, strict=True)):
        _moving(robot, k, parents[k], origin, joint, links.get(joint.find("child").get("link")))
    for fixed in (*TIP_JOINTS, *OFF_CHAIN_JOINTS):
        _fixed(robot, *fixed)
    ET.indent(robot, "  ")
    return '<?xml version="1.0"?>\n' + ET.tostring(robot, encoding="unicode") + "\n"


def _moving(
    robot: ET.Element, k: int, parent: str, origin: UROrigin, template_joint: ET.Element, moved: ET.Element | None
) -> None:
    """UR joint ``k`` and the link it moves: the file's origin, the template's type and limits, and the inertial
    of ``moved``, the template's link that the joint moves."""
    link = ET.SubElement(robot, "link", name=UR_LINKS[k])
    if moved is not None and moved.find("inertial") is not None:
        link.append(copy.deepcopy(moved.find("inertial")))
    joint = ET.SubElement(robot, "joint", name=UR_JOINTS[k], type=template_joint.get("type"))
    ET.SubElement(joint, "parent", link=parent)
    ET.SubElement(joint, "child", link=UR_LINKS[k])
    ET.SubElement(joint, "origin", xyz=_numbers(origin.xyz), rpy=_numbers(origin.rpy))
    ET.SubElement(joint, "axis", xyz="0 0 1")
    if template_joint.find("limit") is not None:
        joint.append(copy.deepcopy(template_joint.find("limit")))


def _fixed(robot: ET.Element, name: str, parent: str, child: str, rpy: tuple[float, float, float]) -> None:
    ET.SubElement(robot, "link", name=child)
    joint = ET.SubElement(robot, "joint", name=name, type="fixed")
    ET.SubElement(joint, "parent", link=parent)
    ET.SubElement(joint, "child", link=child)
    ET.SubElement(joint, "origin", xyz="0 0 0", rpy=_numbers(rpy))


def _numbers(values: tuple[float, ...]) -> str:
    return " ".join(repr(float(v) + 0.0) for v in values)


def _parse_template(text: str, what: str) -> ET.Element:
    try:
        root = ET.fromstring(text.lstrip(LEADING_JUNK).encode())
    except ET.ParseError as exc:
        raise KinematicsError(f"{what}: cannot parse: {exc}") from exc
    if root.tag != "robot":
        raise KinematicsError(f"{what}: the root element is <{root.tag}>, not <robot>")
    return root


def _template_joints(template: ET.Element, what: str) -> list[ET.Element]:
    """The template's six UR joints, checked to place their links where ur_description does."""
    joints = {joint.get("name"): joint for joint in template.iter("joint")}
    found = []
    for name, rpy in zip(UR_JOINTS, NOMINAL_RPY, strict=True):
        joint = joints.get(name)
        if joint is None:
            raise KinematicsError(
                f"{what} has no joint '{name}': a UR kinematics file needs a UR's URDF as the template "
                f"(joints {', '.join(UR_JOINTS)})"
            )
        if joint.get("type") not in ("revolute", "continuous") or joint.find("child") is None:
            raise KinematicsError(f"{what}: joint '{name}' is {joint.get('type')}, not a UR's revolute joint")
        problem = _frame_problem(joint, rpy)
        if problem:
            raise KinematicsError(
                f"{what}: joint '{name}' {problem}, so its links' frames are not ur_description's and their "
                "inertials would sit elsewhere; give a UR's URDF in ur_description's layout (xacro's output, or "
                "the embedded config/ur10.urdf)"
            )
        found.append(joint)
    return found


def _joint_origin(joint: ET.Element) -> np.ndarray:
    """A URDF joint's ``<origin>`` as a 4x4 (ValueError for an attribute that is not three numbers)."""
    origin = joint.find("origin")
    xyz, rpy = ("0 0 0", "0 0 0") if origin is None else (origin.get("xyz", "0 0 0"), origin.get("rpy", "0 0 0"))
    return UROrigin(_three(xyz), _three(rpy)).matrix


def _three(text: str) -> tuple[float, float, float]:
    values = tuple(float(v) for v in text.split())
    if len(values) != 3:
        raise ValueError(f"'{text}' is not three numbers")
    return values


def _frame_problem(joint: ET.Element, rpy: tuple[float, float, float]) -> str | None:
    """How a template joint turns its child link's frame away from ur_description's, or None."""
    axis = joint.find("axis")
    try:
        rotation = _joint_origin(joint)[:3, :3]
        direction = np.array(_three("1 0 0" if axis is None else axis.get("xyz", "1 0 0")))
    except ValueError as exc:
        return f"has an origin or axis that is not three numbers ({exc})"
    angle = float((Rotation.from_matrix(rotation).inv() * Rotation.from_euler("xyz", rpy)).magnitude())
    if angle > FRAME_TOLERANCE_RAD:
        return f"turns its origin by {np.degrees(angle):.1f} deg from ur_description's"
    length = float(np.linalg.norm(direction))
    if length == 0 or np.arccos(np.clip(direction[2] / length, -1.0, 1.0)) > FRAME_TOLERANCE_RAD:
        return f"turns about {direction.tolist()}, not its z axis"
    return None


def size_note(kin: URKinematics, template_urdf_text: str, template_name: str = "") -> str | None:
    """Why the template's inertials may not fit the file's robot, or None: the distance from the shoulder to the
    wrist at zero joint angles differs by more than :data:`SIZE_TOLERANCE` (a UR5e file on the UR10 template)."""
    what = f"template URDF {template_name}".rstrip()
    joints = _template_joints(_parse_template(template_urdf_text, what), what)
    ours = _reach([origin.matrix for origin in kin.origins])
    theirs = _reach([_joint_origin(joint) for joint in joints])
    if abs(ours - theirs) <= SIZE_TOLERANCE * theirs:
        return None
    return (
        f"the {what} is a UR {theirs:.3f} m from shoulder to wrist at zero joint angles, the kinematics file "
        f"{kin.source} one of {ours:.3f} m (another UR model?): its masses and limits are the template's, so the "
        "stage's joint torques are approximate; give a robot config whose URDF is your model's"
    )


def _reach(origins: list[np.ndarray]) -> float:
    """The distance from the first joint's frame to the last's at zero joint angles (m)."""
    t = np.eye(4)
    for origin in origins[1:]:
        t = t @ origin
    return float(np.linalg.norm(t[:3, 3]))


# ----------------------------------------------------------------------------------------------- from files
def template_text(template: str | Path | None = None) -> tuple[str, str]:
    """A template URDF's text and its name for messages: ``template`` as a path (``package://`` too) or as URDF
    text, or the embedded UR10's when None."""
    if template is None:
        path = config_dir() / DEFAULT_TEMPLATE
        return path.read_text(encoding="utf-8-sig"), str(path)
    text = str(template)
    if text.lstrip(LEADING_JUNK).startswith("<"):
        return text, "(text)"
    path = resolve_path(template)
    if not path.is_file():
        raise KinematicsError(f"template URDF {template} does not exist")
    return path.read_text(encoding="utf-8-sig"), text


def ur_urdf(kinematics: str | Path, template: str | Path | None = None) -> str:
    """The URDF of a UR kinematics file (a path), on ``template``'s inertials and limits (see
    :func:`template_text`)."""
    text, name = template_text(template)
    return urdf_from_ur_kinematics(read_ur_kinematics(kinematics), text, name)


def chain_from_ur_kinematics(
    kinematics: str | Path,
    template: str | Path | None = None,
    base_link: str = BASE_LINK,
    tip_link: str = TIP_LINK,
) -> Chain:
    """The chain of a UR kinematics file (a path), built as ur_description builds it, between two of its links.

    The chain's ``urdf_text`` is the built URDF, so a model trained on it stores it and loads without the file.
    A template of another UR model (see :func:`size_note`) is reported in ``inertial_warnings`` and as a
    :class:`TemplateInertialWarning`: the joint torques then come from another model's masses.
    """
    kin = read_ur_kinematics(kinematics)
    text, name = template_text(template)
    chain = chain_from_urdf(urdf_from_ur_kinematics(kin, text, name), base_link, tip_link)
    note = size_note(kin, text, name)
    if note is None:
        return chain
    warnings.warn(note, TemplateInertialWarning, stacklevel=2)
    return replace(chain, inertial_warnings=(*chain.inertial_warnings, note))
