"""URDF to a frozen serial chain, parsed once and evaluated in batches.

The chain collapses fixed joints into constant transforms, so that forward kinematics is
``T = A_0(q_0) · A_1(q_1) ··· A_{n-1}(q_{n-1}) · post`` with ``A_k(q) = pre_k · M_k(q)``, where ``M_k``
is the motion of joint k about (or along) its unit axis. Rodrigues' formula makes each factor linear
in a few constants: ``A_k(q) = G0_k + a_k(q) G1_k + b_k(q) G2_k`` with ``a = sin q, b = 1 - cos q`` for
revolute joints and ``a = q, b = 0`` for prismatic ones. The generators ``G`` are precomputed here.
"""

from __future__ import annotations

import hashlib
import io
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import yourdfpy
from lxml import etree

from hybrid_kinematics_ros.kinematics.errors import KinematicsError
from hybrid_kinematics_ros.kinematics.paths import resolve_path

ACTUATED = ("revolute", "continuous", "prismatic")
LEADING_JUNK = "\ufeff \t\r\n"  # what may precede a URDF's first tag


@dataclass(frozen=True, eq=False)
class Chain:
    """A serial chain between two links. Arrays are read-only; lengths in m, angles in rad.

    Attributes:
        pre: ``(n, 4, 4)`` fixed transform from the previous joint frame to joint k's frame.
        axes: ``(n, 3)`` unit joint axes in their own joint frames.
        post: ``(4, 4)`` fixed transform from the last joint frame to the tip (tool offset included).
        revolute: ``(n,)`` True for revolute and continuous joints.
        continuous: ``(n,)`` True for continuous joints (no limits, angles wrap).
        lower, upper: ``(n,)`` joint limits; ``±inf`` for continuous joints.
        segment_mass: ``(n,)`` mass of the rigid body each joint moves directly (links up to the next joint).
        segment_com: ``(n, 3)`` its centre of mass in joint k's frame (after the joint's motion).
        urdf_sha256: hash of the URDF text, so a trained model can refuse another robot.
    """

    base_link: str
    tip_link: str
    joint_names: tuple[str, ...]
    pre: np.ndarray
    axes: np.ndarray
    post: np.ndarray
    revolute: np.ndarray
    continuous: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    segment_mass: np.ndarray
    segment_com: np.ndarray
    urdf_sha256: str = ""
    urdf_text: str = field(default="", repr=False)
    tool: np.ndarray = field(default_factory=lambda: np.eye(4))  # the part of ``post`` added by a robot config

    def __post_init__(self) -> None:
        for name in (
            "pre",
            "axes",
            "post",
            "tool",
            "revolute",
            "continuous",
            "lower",
            "upper",
            "segment_mass",
            "segment_com",
        ):
            arr = np.array(getattr(self, name))
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        generators = _generators(self.pre, self.axes, self.revolute)
        generators.setflags(write=False)
        object.__setattr__(self, "generators", generators)

    generators: np.ndarray = field(init=False, repr=False)  # (n, 3, 4, 4): G0, G1, G2 per joint

    @property
    def dof(self) -> int:
        return len(self.joint_names)

    def with_tool(self, tool: np.ndarray) -> Chain:
        """The same chain with a fixed tool transform appended after the tip."""
        tool = np.asarray(tool, dtype=float)
        return replace(self, post=self.post @ tool, tool=self.tool @ tool)

    def with_limits(self, lower: np.ndarray, upper: np.ndarray) -> Chain:
        return replace(self, lower=np.asarray(lower, dtype=float), upper=np.asarray(upper, dtype=float))

    def with_geometry(self, pre: np.ndarray, post: np.ndarray) -> Chain:
        """The same chain with other fixed transforms: how the virtual cell perturbs the geometry."""
        return replace(self, pre=np.asarray(pre, dtype=float), post=np.asarray(post, dtype=float))

    def coefficients(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(a, b)`` of each joint for joints ``q (..., n)``; see the module docstring."""
        a = np.where(self.revolute, np.sin(q), q)
        b = np.where(self.revolute, 1.0 - np.cos(q), 0.0)
        return a, b

    def mid_limits(self) -> np.ndarray:
        lo = np.where(np.isfinite(self.lower), self.lower, -np.pi)
        hi = np.where(np.isfinite(self.upper), self.upper, np.pi)
        return 0.5 * (lo + hi)


def _skew4(axis: np.ndarray) -> np.ndarray:
    x, y, z = axis
    k = np.zeros((4, 4))
    k[:3, :3] = [[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]]
    return k


def _generators(pre: np.ndarray, axes: np.ndarray, revolute: np.ndarray) -> np.ndarray:
    out = np.zeros((len(axes), 3, 4, 4))
    for k, (p, axis, rev) in enumerate(zip(pre, axes, revolute, strict=True)):
        out[k, 0] = p
        if rev:
            kk = _skew4(axis)
            out[k, 1] = p @ kk
            out[k, 2] = p @ kk @ kk
        else:
            d = np.zeros((4, 4))
            d[:3, 3] = axis
            out[k, 1] = p @ d
    return out


def load_urdf(source: str | Path) -> tuple[yourdfpy.URDF, str]:
    """Parse a URDF from a path (``package://`` too) or from XML text; returns the model and the text."""
    text = str(source)
    if not text.lstrip(LEADING_JUNK).startswith("<"):
        path = resolve_path(source)
        if not path.is_file():
            raise KinematicsError(f"URDF file {source} does not exist" + (f" ({path})" if str(path) != text else ""))
        text = path.read_text(encoding="utf-8-sig")
    where = source if len(str(source)) < 200 else "text"
    # ROS's parser (tinyxml2) skips a byte-order mark and blank lines before the XML declaration; lxml does not.
    xml = text.lstrip(LEADING_JUNK).encode()
    try:
        # yourdfpy silently recovers from malformed XML; a URDF must parse strictly.
        etree.fromstring(xml)
        urdf = yourdfpy.URDF.load(io.BytesIO(xml), build_scene_graph=False, load_meshes=False)
    except Exception as exc:  # lxml and yourdfpy raise a variety of errors
        raise KinematicsError(f"cannot parse URDF ({where}): {exc}") from exc
    return urdf, text


def chain_from_urdf(source: str | Path, base_link: str, tip_link: str) -> Chain:
    """Build the serial chain from ``base_link`` to ``tip_link`` of a URDF (a path or XML text)."""
    urdf, text = load_urdf(source)
    robot = urdf.robot
    links = {link.name: link for link in robot.links}
    for role, name in (("base_link", base_link), ("tip_link", tip_link)):
        if name not in links:
            raise KinematicsError(f"{role} '{name}' is not a link of the URDF (links: {', '.join(sorted(links))})")
    joint_to_child = {j.child: j for j in robot.joints}

    path = []
    link = tip_link
    while link != base_link:
        joint = joint_to_child.get(link)
        if joint is None:
            raise KinematicsError(f"no kinematic path from '{base_link}' down to '{tip_link}' in the URDF")
        path.append(joint)
        link = joint.parent
    path.reverse()

    names, pre, axes, revolute, continuous, lower, upper = [], [], [], [], [], [], []
    seg_mass, seg_com = [], []
    fixed = np.eye(4)  # transform accumulated since the last actuated joint frame
    mass, moment = 0.0, np.zeros(3)  # of the segment since the last actuated joint, in its frame

    def add_inertial(link_name: str, frame: np.ndarray) -> None:
        nonlocal mass, moment
        inertial = links[link_name].inertial
        if inertial is None or not inertial.mass:
            return
        origin = inertial.origin if inertial.origin is not None else np.eye(4)
        mass += float(inertial.mass)
        moment += float(inertial.mass) * (frame @ origin)[:3, 3]

    for joint in path:
        origin = joint.origin if joint.origin is not None else np.eye(4)
        if joint.mimic is not None:
            raise KinematicsError(f"joint '{joint.name}' is a mimic joint; mimic joints are not supported in the chain")
        if joint.type == "fixed":
            fixed = fixed @ origin
            add_inertial(joint.child, fixed)
            continue
        if joint.type not in ACTUATED:
            raise KinematicsError(
                f"joint '{joint.name}' is of type '{joint.type}'; only revolute, continuous, prismatic and fixed "
                "joints can be in a serial chain"
            )
        if names:
            seg_mass.append(mass)
            seg_com.append(moment / mass if mass > 0 else np.zeros(3))
        mass, moment = 0.0, np.zeros(3)
        axis = np.asarray(joint.axis if joint.axis is not None else [1.0, 0.0, 0.0], dtype=float)
        if np.linalg.norm(axis) < 1e-12:
            raise KinematicsError(f"joint '{joint.name}' has a zero axis")
        names.append(joint.name)
        pre.append(fixed @ origin)
        axes.append(axis / np.linalg.norm(axis))
        revolute.append(joint.type != "prismatic")
        is_cont = joint.type == "continuous"
        continuous.append(is_cont)
        lim = joint.limit
        lo = lim.lower if (lim is not None and lim.lower is not None and not is_cont) else -np.inf
        hi = lim.upper if (lim is not None and lim.upper is not None and not is_cont) else np.inf
        if not lo <= hi:
            raise KinematicsError(f"joint '{joint.name}' has lower limit {lo} above upper limit {hi}")
        lower.append(lo)
        upper.append(hi)
        fixed = np.eye(4)
        add_inertial(joint.child, fixed)
    if not names:
        raise KinematicsError(f"the path from '{base_link}' to '{tip_link}' has no actuated joint")
    seg_mass.append(mass)
    seg_com.append(moment / mass if mass > 0 else np.zeros(3))

    return Chain(
        base_link=base_link,
        tip_link=tip_link,
        joint_names=tuple(names),
        pre=np.array(pre),
        axes=np.array(axes),
        post=fixed,
        revolute=np.array(revolute, dtype=bool),
        continuous=np.array(continuous, dtype=bool),
        lower=np.array(lower, dtype=float),
        upper=np.array(upper, dtype=float),
        segment_mass=np.array(seg_mass),
        segment_com=np.array(seg_com),
        urdf_sha256=hashlib.sha256(text.encode()).hexdigest(),
        urdf_text=text,
    )
