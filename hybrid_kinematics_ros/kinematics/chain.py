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
import warnings
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import yourdfpy
from lxml import etree

from hybrid_kinematics_ros.kinematics.errors import KinematicsError
from hybrid_kinematics_ros.kinematics.fk_kernel import ChainOperands
from hybrid_kinematics_ros.kinematics.paths import resolve_path
from hybrid_kinematics_ros.kinematics.se3 import skew

ACTUATED = ("revolute", "continuous", "prismatic")
MAX_COM_DISTANCE_M = 3.0  # a link's centre of mass further than this from its frame is a unit mistake
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
    inertial_warnings: tuple[str, ...] = ()  # links whose implausible inertials were left out (see chain_from_urdf)
    # every link on the path: (k, F), its pose being joint k's frame after its motion times F (k = -1: the base)
    link_frames: dict[str, tuple[int, np.ndarray]] = field(default_factory=dict, repr=False, compare=False)

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

    @cached_property
    def kernel_operands(self) -> ChainOperands:
        """The arguments after ``q`` of :mod:`~hybrid_kinematics_ros.kinematics.fk_kernel`'s kernels, built once,
        contiguous (unpacked into each call: the kernels take plain arrays)."""
        return ChainOperands(
            generators=np.ascontiguousarray(self.generators, dtype=float),
            revolute=np.ascontiguousarray(self.revolute, dtype=bool),
            post=np.ascontiguousarray(self.post, dtype=float),
            axes=np.ascontiguousarray(self.axes, dtype=float),
        )

    @cached_property
    def single_operands(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
        """Constants of :func:`fk.fk_single`, built once: the generators as ``(n, 3, 16)`` (G0, G1, G2 of
        every joint, flattened), a row of ones ``(n,)``, the ``post`` transform followed by identities
        ``(m, 4, 4)`` that pad the n + 1 factors of the product to a power of two, and whether every joint
        is revolute."""
        n = self.dof
        flat = np.ascontiguousarray(self.generators.reshape(n, 3, 16))
        size = 1 << n.bit_length()  # the smallest power of two >= n + 1
        tail = np.concatenate([self.post[None], np.broadcast_to(np.eye(4), (size - n - 1, 4, 4))])
        for arr in (flat, tail):
            arr.setflags(write=False)
        return flat, np.ones(n), tail, bool(self.revolute.all())

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

    def first_difference(
        self, other: Chain, tol_m: float = 1e-5, tol_rad: float = 1e-5, tol_limit: float = 1e-3
    ) -> str | None:
        """The first way ``other`` is kinematically another robot than this chain, or None.

        Compares what the kinematics depends on, joint by joint from the base: joint names, types, axes,
        origins (fixed transforms between joints, fixed links collapsed) and limits, then the transform to
        the tip. Comments, attribute order, meshes, inertials, links off the chain and float formatting
        do not count. The default tolerances (10 µm, 2e-3°) lie far below a calibration's accuracy but far
        above the rounding of a URDF written by another tool; limits get ``tol_limit`` (rad or m), since
        tools round ±π.
        """
        if self.joint_names != other.joint_names:
            for k, (a, b) in enumerate(zip(self.joint_names, other.joint_names, strict=False)):
                if a != b:
                    return f"joint {k + 1} of the chain is '{a}', the given URDF has '{b}' there"
            return (
                f"the chain has {self.dof} joints ({', '.join(self.joint_names)}), the given URDF "
                f"{other.dof} ({', '.join(other.joint_names)})"
            )
        for k, name in enumerate(self.joint_names):
            kinds = [_joint_kind(c, k) for c in (self, other)]
            if kinds[0] != kinds[1]:
                return f"joint '{name}' is {kinds[0]}, {kinds[1]} in the given URDF"
            angle = float(np.arccos(np.clip(self.axes[k] @ other.axes[k], -1.0, 1.0)))
            if angle > tol_rad:
                return (
                    f"joint '{name}': axis {np.round(self.axes[k], 6).tolist()} differs from "
                    f"{np.round(other.axes[k], 6).tolist()} by {np.degrees(angle):.4f} deg"
                )
            what = _transform_difference(self.pre[k], other.pre[k], tol_m, tol_rad)
            if what:
                return f"joint '{name}': origin (from the previous joint) {what}"
            for side, a, b in (("lower", self.lower[k], other.lower[k]), ("upper", self.upper[k], other.upper[k])):
                if not (a == b or abs(a - b) <= tol_limit):
                    return f"joint '{name}': {side} limit {a:.6g} differs from {b:.6g} in the given URDF"
        untooled = self.post @ np.linalg.inv(self.tool), other.post @ np.linalg.inv(other.tool)
        what = _transform_difference(*untooled, tol_m, tol_rad)
        if what:
            return f"the transform from joint '{self.joint_names[-1]}' to '{self.tip_link}' {what}"
        return None

    def mid_limits(self) -> np.ndarray:
        lo = np.where(np.isfinite(self.lower), self.lower, -np.pi)
        hi = np.where(np.isfinite(self.upper), self.upper, np.pi)
        return 0.5 * (lo + hi)


class ImplausibleInertialWarning(UserWarning):
    """A link's inertial cannot be right (mass <= 0, or its centre of mass metres away); it is ignored."""


def _implausible_inertial(mass: float, com: np.ndarray) -> str | None:
    """Why a link's inertial is implausible, or None. A centre of mass given in millimetres lands hundreds of
    metres from the link, and its gravity torque would swamp the compliance fit. A mass of exactly 0 is how
    ROS URDFs write frame-only links (``tool0``, ``ee_link``, ``panda_link8``): it adds nothing and is not
    reported, or every real UR or Panda URDF would warn."""
    if mass == 0:
        return None
    if not mass > 0:
        return f"mass {mass:g} kg is not positive"
    distance = float(np.linalg.norm(com))
    if distance > MAX_COM_DISTANCE_M:
        return f"centre of mass {distance:.3g} m from its joint (more than {MAX_COM_DISTANCE_M:g} m; millimetres?)"
    return None


def _joint_kind(chain: Chain, k: int) -> str:
    if not chain.revolute[k]:
        return "prismatic"
    return "continuous" if chain.continuous[k] else "revolute"


def _transform_difference(a: np.ndarray, b: np.ndarray, tol_m: float, tol_rad: float) -> str | None:
    """How two 4x4 transforms differ (mm, deg), or None within the tolerances."""
    shift = float(np.linalg.norm(a[:3, 3] - b[:3, 3]))
    cos = 0.5 * (np.trace(a[:3, :3].T @ b[:3, :3]) - 1.0)
    turn = float(np.arccos(np.clip(cos, -1.0, 1.0)))
    if shift <= tol_m and turn <= tol_rad:
        return None
    return (
        f"differs by {shift * 1e3:.4f} mm and {np.degrees(turn):.4f} deg (xyz {np.round(a[:3, 3], 6).tolist()} "
        f"here, {np.round(b[:3, 3], 6).tolist()} in the given URDF)"
    )


def _skew4(axis: np.ndarray) -> np.ndarray:
    """The cross-product matrix of ``axis`` as a ``(4, 4)`` generator of rotation (no translation)."""
    k = np.zeros((4, 4))
    k[:3, :3] = skew(axis)
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
    links = {link.name: link for link in urdf.robot.links}
    for role, name in (("base_link", base_link), ("tip_link", tip_link)):
        if name not in links:
            raise KinematicsError(f"{role} '{name}' is not a link of the URDF (links: {', '.join(sorted(links))})")
    built = _ChainBuilder(links, base_link)
    for joint in _joint_path(urdf.robot.joints, base_link, tip_link):
        built.add(joint)
    chain = built.chain(tip_link, text)
    for message in chain.inertial_warnings:
        warnings.warn(message, ImplausibleInertialWarning, stacklevel=2)
    return chain


def _joint_path(joints: list, base_link: str, tip_link: str) -> list:
    """The URDF joints from ``base_link`` down to ``tip_link``, in order."""
    joint_to_child = {j.child: j for j in joints}
    path = []
    link = tip_link
    while link != base_link:
        joint = joint_to_child.get(link)
        if joint is None:
            raise KinematicsError(f"no kinematic path from '{base_link}' down to '{tip_link}' in the URDF")
        path.append(joint)
        link = joint.parent
    return path[::-1]


def _limits(joint: Any) -> tuple[float, float]:
    """A joint's (lower, upper) limits; a continuous joint, or a limit not given, is unbounded."""
    lim, endless = joint.limit, joint.type == "continuous"
    lo = lim.lower if (lim is not None and lim.lower is not None and not endless) else -np.inf
    hi = lim.upper if (lim is not None and lim.upper is not None and not endless) else np.inf
    if not lo <= hi:
        raise KinematicsError(f"joint '{joint.name}' has lower limit {lo} above upper limit {hi}")
    return lo, hi


class _ChainBuilder:
    """The chain's columns, joint by joint along the path: each actuated joint's frame, axis, type and limits;
    fixed joints folded into the transform to the next; each segment's mass and centre of mass (the links
    since the last actuated joint, in its frame); and where every link sits."""

    def __init__(self, links: dict[str, Any], base_link: str) -> None:
        self.links = links
        self.joints: list[dict[str, Any]] = []
        self.segments: list[tuple[float, np.ndarray]] = []  # (mass, centre of mass) of each closed segment
        self.implausible: list[str] = []
        self.fixed = np.eye(4)  # transform accumulated since the last actuated joint frame
        self.mass, self.moment = 0.0, np.zeros(3)  # of the segment since the last actuated joint, in its frame
        self.link_frames: dict[str, tuple[int, np.ndarray]] = {base_link: (-1, np.eye(4))}

    def add(self, joint: Any) -> None:
        origin = joint.origin if joint.origin is not None else np.eye(4)
        if joint.mimic is not None:
            raise KinematicsError(f"joint '{joint.name}' is a mimic joint; mimic joints are not supported in the chain")
        if joint.type == "fixed":
            self.fixed = self.fixed @ origin
            self._inertial(joint.child, self.fixed)
            self.link_frames[joint.child] = (len(self.joints) - 1, self.fixed.copy())
            return
        if joint.type not in ACTUATED:
            raise KinematicsError(
                f"joint '{joint.name}' is of type '{joint.type}'; only revolute, continuous, prismatic and fixed "
                "joints can be in a serial chain"
            )
        if self.joints:  # what sits before the first actuated joint moves with the base: no segment
            self._close_segment()
        self.mass, self.moment = 0.0, np.zeros(3)
        axis = np.asarray(joint.axis if joint.axis is not None else [1.0, 0.0, 0.0], dtype=float)
        if np.linalg.norm(axis) < 1e-12:
            raise KinematicsError(f"joint '{joint.name}' has a zero axis")
        lower, upper = _limits(joint)
        self.joints.append(
            {
                "name": joint.name,
                "pre": self.fixed @ origin,
                "axis": axis / np.linalg.norm(axis),
                "revolute": joint.type != "prismatic",
                "continuous": joint.type == "continuous",
                "lower": lower,
                "upper": upper,
            }
        )
        self.fixed = np.eye(4)
        self._inertial(joint.child, self.fixed)
        self.link_frames[joint.child] = (len(self.joints) - 1, np.eye(4))

    def _inertial(self, link_name: str, frame: np.ndarray) -> None:
        """The link's mass into the open segment, at its centre of mass in the segment's frame."""
        inertial = self.links[link_name].inertial
        if inertial is None or inertial.mass is None:
            return
        origin = inertial.origin if inertial.origin is not None else np.eye(4)
        problem = _implausible_inertial(float(inertial.mass), origin[:3, 3])
        if problem:
            self.implausible.append(f"link '{link_name}': {problem}; its mass is left out of the gravity torques")
        if problem or inertial.mass == 0:
            return
        self.mass += float(inertial.mass)
        self.moment += float(inertial.mass) * (frame @ origin)[:3, 3]

    def _close_segment(self) -> None:
        self.segments.append((self.mass, self.moment / self.mass if self.mass > 0 else np.zeros(3)))

    def chain(self, tip_link: str, text: str) -> Chain:
        base_link = next(iter(self.link_frames))
        if not self.joints:
            raise KinematicsError(f"the path from '{base_link}' to '{tip_link}' has no actuated joint")
        self._close_segment()

        def column(key: str, dtype: type = float) -> np.ndarray:
            return np.array([j[key] for j in self.joints], dtype=dtype)

        return Chain(
            base_link=base_link,
            tip_link=tip_link,
            joint_names=tuple(j["name"] for j in self.joints),
            pre=np.array([j["pre"] for j in self.joints]),
            axes=np.array([j["axis"] for j in self.joints]),
            post=self.fixed,
            revolute=column("revolute", bool),
            continuous=column("continuous", bool),
            lower=column("lower"),
            upper=column("upper"),
            segment_mass=np.array([m for m, _ in self.segments]),
            segment_com=np.array([c for _, c in self.segments]),
            urdf_sha256=hashlib.sha256(text.encode()).hexdigest(),
            urdf_text=text,
            link_frames=self.link_frames,
            inertial_warnings=tuple(self.implausible),
        )
