"""Denavit-Hartenberg tables of a serial chain, for controllers that take their geometry in that form.

The table comes from the joint axes as lines in space at q = 0 and the common normals between consecutive
axes; a ``base`` transform (chain base link to DH frame 0) and a ``tool`` transform (last DH frame to the
chain's tip) carry what no DH row can, so that ``base · A_1(q_1) ··· A_n(q_n) · tool`` is the chain's
:func:`~hybrid_kinematics_ros.kinematics.fk.fk` exactly.

Conventions (joints numbered from 1, as in DH texts):

* ``standard`` (distal): ``A_i = Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``; frame i lies on joint i+1's axis.
* ``modified`` (proximal, Craig): ``A_i = Rx(alpha_{i-1}) Tx(a_{i-1}) Rz(theta_i) Tz(d_i)``; frame i lies on
  joint i's axis. Row i holds ``a_{i-1}`` and ``alpha_{i-1}`` in its ``a`` and ``alpha``.

Both use the same common normals, so theta and d agree between them and only a and alpha shift by a row;
``base`` and ``tool`` are the same too. In both, ``a_i``, ``alpha_i`` and ``x_i`` belong to the common normal
from joint i's axis to joint i+1's (the names the notes use), and ``d_i`` is the offset along joint i's axis.

The choices where the geometry leaves freedom:

* Frame 0 lies on joint 1's axis at the foot of the perpendicular from the base link's origin, its x axis the
  base link's x (else y) projected across the axis: a base whose z is joint 1's axis gives ``base = I``.
* The last frame lies on joint n's axis at the foot of the perpendicular from the tip's origin, its x axis the
  tip's x (else y) projected across the axis: a flange on the last axis gives ``tool = I``.
* Each common normal's direction is the one within 84° of the previous x axis (a theta offset within ±84°,
  a may then be negative: the published UR tables' a_2 = -0.612); near ±90°, the one that makes alpha lie
  in (0, π), or for parallel axes a > 0. A small calibration tilt thus flips no sign, except where it turns
  parallel axes into skew ones (see the notes).
* Parallel axes have no unique common normal: the one through the point where the previous normal meets
  the first axis is taken, so ``d_k = 0``; a note names the joints.
* A prismatic joint's axis line is the one through its joint frame's origin (only its direction moves the
  tip); the joint variable adds to d and theta is fixed.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from hybrid_kinematics_ros.kinematics import fk
from hybrid_kinematics_ros.kinematics.chain import Chain
from hybrid_kinematics_ros.kinematics.errors import KinematicsError

Convention = Literal["standard", "modified"]
CONVENTIONS: tuple[str, ...] = ("standard", "modified")
PARALLEL_TOL = 1e-10  # |u × v| below which two axes count as parallel (an error of this times the lever, m)
COINCIDENT_TOL_M = 1e-12  # parallel axes closer than this share one line
NEARLY_PARALLEL_RAD = 1e-2  # axes this close to parallel have a remote, ill-conditioned common normal
SIGN_BAND = 0.1  # |cos theta| below which a normal's direction follows alpha (or a), not the previous x axis
NOISE = 1e-14  # parameters (m, rad) below this are rounding noise of exact zeros and are written as 0
IDENTITY_TOL = 1e-12  # a base or tool closer than this to the identity needs no note
HEADER = {
    "standard": (
        "standard (distal) convention: A_i = Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i); frame i on joint i+1's axis"
    ),
    "modified": (
        "modified (proximal, Craig) convention: A_i = Rx(alpha_{i-1}) Tx(a_{i-1}) Rz(theta_i) Tz(d_i); "
        "row i holds a_{i-1} and alpha_{i-1}; frame i on joint i's axis"
    ),
}


@dataclass(frozen=True)
class DHRow:
    """One joint's DH parameters. Lengths in m, angles in rad.

    A revolute joint's variable adds to ``theta`` (its zero offset); a prismatic joint's adds to ``d``,
    and ``theta`` is fixed. In the modified convention ``a`` and ``alpha`` are ``a_{i-1}``, ``alpha_{i-1}``.
    """

    a: float
    alpha: float
    d: float
    theta: float
    revolute: bool = True


@dataclass(frozen=True, eq=False)
class DHTable:
    """A DH table with the base and tool transforms that make it the chain's forward kinematics.

    Attributes:
        convention: ``"standard"`` or ``"modified"`` (see the module docstring).
        rows: one :class:`DHRow` per joint, from the base.
        base: ``(4, 4)`` from the chain's base link to DH frame 0.
        tool: ``(4, 4)`` from the last DH frame to the chain's tip.
        notes: where the chain's geometry has no unique or exact DH form.
        base_link, tip_link: the chain's link names, for the text form.
    """

    convention: Convention
    rows: tuple[DHRow, ...]
    base: np.ndarray
    tool: np.ndarray
    notes: tuple[str, ...] = ()
    base_link: str = ""
    tip_link: str = ""

    def __post_init__(self) -> None:
        _check_convention(self.convention)
        for name in ("base", "tool"):
            arr = np.array(getattr(self, name), dtype=float)
            if arr.shape != (4, 4):
                raise KinematicsError(f"DH table: {name} must be a 4x4 transform, got shape {arr.shape}")
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        object.__setattr__(self, "rows", tuple(self.rows))
        object.__setattr__(self, "notes", tuple(self.notes))

    @property
    def dof(self) -> int:
        return len(self.rows)

    def column(self, name: str) -> np.ndarray:
        """One parameter of every row as an ``(n,)`` array: ``a``, ``alpha``, ``d``, ``theta`` or ``revolute``."""
        return np.array([getattr(row, name) for row in self.rows])


@dataclass(frozen=True)
class _Normal:
    """A common normal from one line to the next: unit direction ``x``, its ``foot`` on the first line and the
    signed length ``a`` along ``x`` to the second line; ``kind`` says how the two lines lie."""

    x: np.ndarray
    foot: np.ndarray
    a: float
    kind: Literal["skew", "parallel", "coincident"]
    angle: float  # between the two lines' directions, rad
    shift: float = 0.0  # from where the previous normal meets the first line to ``foot``, m


def _clean(x: float) -> float:
    """``x`` as a float, with rounding noise (below :data:`NOISE`) written as an exact 0 rather than ±1e-17."""
    return 0.0 if abs(x) < NOISE else float(x)


def _check_convention(convention: str) -> None:
    if convention not in CONVENTIONS:
        raise KinematicsError(f"unknown DH convention '{convention}'; choose one of {', '.join(CONVENTIONS)}")


def _angle_about(a: np.ndarray, b: np.ndarray, axis: np.ndarray) -> float:
    """The signed angle that turns ``a`` into ``b`` about ``axis`` (all three unit, a and b across the axis)."""
    return float(np.arctan2(np.cross(a, b) @ axis, a @ b))


def _across(frame: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """The frame's x axis projected across ``axis`` and normalised (its y axis if x lies along ``axis``)."""
    for column in (frame[:3, 0], frame[:3, 1]):
        v = column - (column @ axis) * axis
        norm = np.linalg.norm(v)
        if norm > 1e-6:
            return v / norm
    raise AssertionError("two orthonormal columns cannot both lie along one axis")


def _foot(point: np.ndarray, origin: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """The foot on the line ``origin + t · direction`` of the perpendicular from ``point``."""
    return origin + ((point - origin) @ direction) * direction


def _common_normal(
    p: np.ndarray, u: np.ndarray, q: np.ndarray, v: np.ndarray, start: np.ndarray, x_prev: np.ndarray
) -> _Normal:
    """The common normal from line ``(p, u)`` to line ``(q, v)``.

    ``start`` is the point of the first line where the previous normal meets it and ``x_prev`` that normal's
    direction: parallel lines take the normal through ``start`` (d = 0), coincident ones ``x_prev`` itself,
    and the direction's sign follows ``x_prev`` (see the module docstring).
    """
    cross = np.cross(u, v)
    sin = float(np.linalg.norm(cross))
    angle = float(np.arctan2(sin, abs(u @ v)))
    if sin < PARALLEL_TOL:
        offset = q - start
        offset = offset - (offset @ v) * v  # from start across to the second line
        length = float(np.linalg.norm(offset))
        if length < COINCIDENT_TOL_M:
            return _Normal(x_prev.copy(), start, 0.0, "coincident", angle)
        x = offset / length
        x = x - (x @ u) * u  # exactly across the first line, though v may differ from u by rounding
        x /= np.linalg.norm(x)
        a, kind, foot = float((q - start) @ x), "parallel", start
    else:
        x = cross / sin
        foot = p + (np.cross(q - p, v) @ cross) / sin**2 * u
        a, kind = float((q - p) @ x), "skew"
    c = float(x @ x_prev)
    # near ±90° from x_prev, x stays as built: along u × v (alpha in (0, π)) or, parallel, towards the second line
    sign = np.sign(c) if abs(c) >= SIGN_BAND else 1.0
    return _Normal(sign * x, foot, sign * a, kind, angle)


def _axis_lines(chain: Chain) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points ``(n, 3)`` and unit directions ``(n, 3)`` of the joint axes and the tip pose, at q = 0, in the
    base link's frame."""
    frames = fk.joint_frames(chain, np.zeros((1, chain.dof)))[0]
    points = frames[:-1, :3, 3]
    directions = np.einsum("kij,kj->ki", frames[:-1, :3, :3], chain.axes)
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return points, directions, frames[-1]


def _normals(chain: Chain) -> tuple[list[_Normal], np.ndarray, np.ndarray]:
    """The n + 1 normals (base to axis 1, axis k to k+1, axis n to the tip, each's ``foot`` on the axis before it
    and ``a`` its length; the base's ``foot`` is frame 0's origin on axis 1), the axis directions ``(n, 3)`` and
    the tip pose, at q = 0."""
    points, u, tip = _axis_lines(chain)
    origin0 = _foot(np.zeros(3), points[0], u[0])
    normals = [_Normal(_across(np.eye(4), u[0]), origin0, 0.0, "skew", 0.0)]
    start = origin0
    for k in range(chain.dof - 1):
        normal = _common_normal(points[k], u[k], points[k + 1], u[k + 1], start, normals[-1].x)
        normal = replace(normal, shift=float(np.linalg.norm(normal.foot - start)))
        normals.append(normal)
        start = normal.foot + normal.a * normal.x  # where it meets axis k+1
    end = _foot(tip[:3, 3], points[-1], u[-1])
    normals.append(_Normal(_across(tip, u[-1]), end, 0.0, "skew", 0.0))
    return normals, u, tip


def _rows(chain: Chain, normals: list[_Normal], u: np.ndarray, convention: str) -> tuple[DHRow, ...]:
    """The DH rows from the normals and the axis directions ``u``: theta and d from the normals on either side of
    each axis, a and alpha from the normal after the axis (standard) or before it (modified)."""
    n = chain.dof
    rows = []
    for k in range(n):
        before, after = normals[k], normals[k + 1]
        start = before.foot + before.a * before.x  # where the normal before axis k meets it
        theta = _angle_about(before.x, after.x, u[k])
        d = float((after.foot - start) @ u[k])
        if convention == "standard":
            a, alpha = (after.a, _angle_about(u[k], u[k + 1], after.x)) if k < n - 1 else (0.0, 0.0)
        else:
            a, alpha = (before.a, _angle_about(u[k - 1], u[k], before.x)) if k > 0 else (0.0, 0.0)
        values = {name: _clean(x) for name, x in (("a", a), ("alpha", alpha), ("d", d), ("theta", theta))}
        rows.append(DHRow(**values, revolute=bool(chain.revolute[k])))
    return tuple(rows)


def _frame(origin: np.ndarray, z: np.ndarray, x: np.ndarray) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = np.column_stack((x, np.cross(z, x), z))
    t[:3, 3] = origin
    return t


def _joint(chain: Chain, k: int) -> str:
    return f"{k + 1} ({chain.joint_names[k]})"


def _pair_notes(chain: Chain, normals: list[_Normal]) -> list[str]:
    """Notes on consecutive axes whose common normal is not unique or not well conditioned."""
    notes = []
    for k, normal in enumerate(normals[1:-1]):
        pair = f"joints {_joint(chain, k)} and {_joint(chain, k + 1)}"
        if normal.kind == "coincident":
            notes.append(
                f"{pair} share one axis line: x_{k + 1} continues x_{k}, a_{k + 1} = 0 and d_{k + 1} = 0 are a "
                "convention here; only the sum of the two joints' motions is determined by the geometry"
            )
        elif normal.kind == "parallel":
            notes.append(
                f"{pair} are parallel: d_{k + 1} is a convention here (0: their common normal meets joint "
                f"{k + 1}'s axis where the previous one does); a controller's table may place it elsewhere, and "
                "a small calibration tilt makes it ill-conditioned"
            )
        elif normal.angle < NEARLY_PARALLEL_RAD:
            notes.append(
                f"{pair} are nearly parallel ({np.degrees(normal.angle):.3g} deg apart): their common normal is "
                f"unique but {normal.shift:.3g} m along joint {k + 1}'s axis, so d_{k + 1} and the d further down "
                "that takes its offset back are exact here yet ill-conditioned (a small tilt moves them by metres); "
                "a controller's table with these axes parallel cannot hold this geometry"
            )
    return notes


def _pose_text(t: np.ndarray) -> str:
    xyz, rpy = xyz_rpy(t)
    return f"xyz {(np.round(xyz, 6) + 0.0).tolist()} m, rpy {(np.round(rpy, 6) + 0.0).tolist()} rad"  # no -0.0


def _notes(chain: Chain, normals: list[_Normal], base: np.ndarray, tool: np.ndarray) -> tuple[str, ...]:
    """Every note of the table: axis pairs, prismatic joints' axis lines, a base and a tool no row can hold."""
    notes = _pair_notes(chain, normals)
    for k in np.flatnonzero(~chain.revolute):
        notes.append(
            f"joint {_joint(chain, k)} is prismatic: only its direction moves the tip, so its axis line is placed "
            "through its joint frame's origin, which fixes the common normals to it; its variable adds to d"
        )
    if not np.allclose(base, np.eye(4), rtol=0.0, atol=IDENTITY_TOL):
        notes.append(
            f"base: DH frame 0 lies on joint 1's axis, {_pose_text(base)} from '{chain.base_link}'; no DH row "
            "holds this, so the controller needs it as its base frame"
        )
    if not np.allclose(tool, np.eye(4), rtol=0.0, atol=IDENTITY_TOL):
        notes.append(
            f"tool: '{chain.tip_link}' is {_pose_text(tool)} from the last DH frame; no DH row holds this, so the "
            "controller needs it as its tool frame"
        )
    return tuple(notes)


def dh_table(chain: Chain, convention: Convention = "standard") -> DHTable:
    """The chain's DH table in ``convention`` with the base and tool transforms that make :func:`dh_fk` equal
    :func:`~hybrid_kinematics_ros.kinematics.fk.fk`, and notes where the geometry has no unique or exact DH form.

    The tool is taken from the table's own product at q = 0, so rounding in the rows does not show at the tip
    there. Elsewhere the table is exact to float64 rounding of its largest d: nearly parallel axes put their
    common normal about ``link length / tilt`` away (600 m for a 1 mrad tilt of the UR10's upper arm, where a
    d holds 1e-13 m; 6000 km for 0.1 µrad, where it holds only 1e-9 m).
    """
    _check_convention(convention)
    normals, u, tip = _normals(chain)
    rows = _rows(chain, normals, u, convention)
    base = _frame(normals[0].foot, u[0], normals[0].x)
    table = DHTable(convention, rows, base, np.eye(4), base_link=chain.base_link, tip_link=chain.tip_link)
    tool = np.linalg.solve(dh_fk(table, np.zeros(chain.dof))[0], tip)
    tool[3] = (0.0, 0.0, 0.0, 1.0)
    for t in (base, tool):
        t[np.abs(t) < NOISE] = 0.0  # rounding noise of exact zeros, so that a plain base or tool reads as one
    return DHTable(
        convention,
        rows,
        base,
        tool,
        _notes(chain, normals, base, tool),
        base_link=chain.base_link,
        tip_link=chain.tip_link,
    )


def dh_transforms(
    convention: Convention, a: np.ndarray, alpha: np.ndarray, d: np.ndarray, theta: np.ndarray
) -> np.ndarray:
    """The link transforms ``A (..., 4, 4)`` of broadcast DH parameters in ``convention``."""
    _check_convention(convention)
    a, alpha, d, theta = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (a, alpha, d, theta)))
    ct, st, ca, sa = np.cos(theta), np.sin(theta), np.cos(alpha), np.sin(alpha)
    out = np.zeros((*a.shape, 4, 4))
    out[..., 3, 3] = 1.0
    if convention == "standard":  # Rz(theta) Tz(d) Tx(a) Rx(alpha)
        out[..., 0, :] = np.stack((ct, -st * ca, st * sa, a * ct), axis=-1)
        out[..., 1, :] = np.stack((st, ct * ca, -ct * sa, a * st), axis=-1)
        out[..., 2, 1], out[..., 2, 2], out[..., 2, 3] = sa, ca, d
    else:  # Rx(alpha) Tx(a) Rz(theta) Tz(d)
        out[..., 0, 0], out[..., 0, 1], out[..., 0, 3] = ct, -st, a
        out[..., 1, :] = np.stack((st * ca, ct * ca, -sa, -d * sa), axis=-1)
        out[..., 2, :] = np.stack((st * sa, ct * sa, ca, d * ca), axis=-1)
    return out


def dh_fk(table: DHTable, q: np.ndarray) -> np.ndarray:
    """Tip poses ``(N, 4, 4)`` in the base link's frame from the table: ``base · A_1(q_1) ··· A_n(q_n) · tool``
    for joints ``(N, n)`` (a 1-D ``q`` is a batch of one)."""
    q = np.asarray(q, dtype=float)
    if q.ndim == 1:
        q = q[None, :]
    if q.ndim != 2 or q.shape[1] != table.dof:
        raise KinematicsError(
            f"expected joints of shape (N, {table.dof}) for a {table.dof}-row DH table, got {q.shape}"
        )
    revolute = table.column("revolute").astype(bool)
    theta = table.column("theta") + np.where(revolute, q, 0.0)
    d = table.column("d") + np.where(revolute, 0.0, q)
    factors = dh_transforms(table.convention, table.column("a"), table.column("alpha"), d, theta)
    out = np.broadcast_to(table.base, (len(q), 4, 4))
    for k in range(table.dof):
        out = out @ factors[:, k]
    return out @ table.tool


def xyz_rpy(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A transform's translation (m) and URDF roll, pitch, yaw (rad, fixed axes x, y, z)."""
    with warnings.catch_warnings():  # at pitch ±π/2 scipy warns of gimbal lock; the angles still give the rotation
        warnings.simplefilter("ignore", UserWarning)
        rpy = Rotation.from_matrix(t[:3, :3]).as_euler("xyz")
    return np.array(t[:3, 3], dtype=float), rpy


def _pose_entry(t: np.ndarray) -> dict[str, list[float]]:
    xyz, rpy = xyz_rpy(t)
    return {"xyz_m": [_clean(x) for x in xyz], "rpy_rad": [_clean(x) for x in rpy]}


def format_dh(table: DHTable, chain_joint_names: tuple[str, ...] | list[str]) -> str:
    """The table as YAML for people and programs: one entry per joint with the units in its keys, the base and
    tool as xyz (m) and URDF rpy (rad), the notes as a list; a header comment states the convention and how
    the pieces compose. Floats are written in full (``repr``), so reading them back loses nothing."""
    names = tuple(chain_joint_names)
    if len(names) != table.dof:
        raise KinematicsError(f"{len(names)} joint names for a {table.dof}-row DH table")
    data = {
        "convention": table.convention,
        "base_link": table.base_link,
        "tip_link": table.tip_link,
        "joints": [
            {
                "name": name,
                "type": "revolute" if row.revolute else "prismatic",
                "a_m": float(row.a),
                "alpha_rad": float(row.alpha),
                "d_m": float(row.d),
                "theta_offset_rad": float(row.theta),
            }
            for name, row in zip(names, table.rows, strict=True)
        ],
        "base": _pose_entry(table.base),
        "tool": _pose_entry(table.tool),
    }
    header = (
        f"# Denavit-Hartenberg table, {HEADER[table.convention]}.\n"
        f"# T({table.base_link or 'base'} -> {table.tip_link or 'tip'}) = base · A_1(q_1) ··· A_n(q_n) · tool. "
        "A revolute joint's q adds to theta_offset_rad, a prismatic one's to d_m.\n"
        "# base: from the base link to DH frame 0; tool: from the last DH frame to the tip (xyz in m, rpy in rad: "
        "URDF fixed-axis roll, pitch, yaw).\n# Give them to the controller as its base and tool frames.\n"
    )
    rows = yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=1000, allow_unicode=True)
    notes = yaml.safe_dump({"notes": list(table.notes)}, default_flow_style=False, width=1000, allow_unicode=True)
    return header + rows + notes
