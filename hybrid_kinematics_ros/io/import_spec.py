"""The import spec: how to read one tracker export table, checked from a YAML file or the command line.

A calibration engineer gets a CSV or TXT export from the tracker software (SpatialAnalyzer, PolyWorks, the
tracker's own tools) with the controller's joint readings in the same rows, not a ROS topic. An
:class:`ImportSpec` says how to read such a table: separator and decimal mark, which columns hold the joints
and the measured pose in which units, how the orientation is given, the tracker station's frame, the stamps
and the extra columns to carry along as condition channels (see ``io/pairs.py``). It comes from a small YAML
file (``config/import/*.yaml``, ``extends`` resolved by :func:`load_spec_dict`) or from the command line;
both are plain dicts checked by :func:`spec_from_dict`, so every mistake is reported with the key that holds
it. Reading a table by a spec is ``io/importer.py``.
"""

from __future__ import annotations

import datetime as dt
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from hybrid_kinematics_ros.io.errors import DataError
from hybrid_kinematics_ros.io.pairs import CONDITION_TYPES
from hybrid_kinematics_ros.kinematics.paths import config_dir

ORIENTATIONS = ("quaternion", "euler", "none", "points")
LENGTH_UNITS = {"mm": 1e-3, "m": 1.0}
ANGLE_UNITS = ("rad", "deg")
STAMP_FORMATS = ("seconds", "milliseconds", "nanoseconds", "iso8601")  # or a strftime pattern with '%'
NA_VALUES = ("nan", "-nan", "+nan", "na", "n/a", "#n/a", "null", "none")
SECTIONS = ("extends", "format", "frame_id", "joints", "position", "orientation", "stamp", "conditions", "filter")


@dataclass(frozen=True)
class Points:
    """Reflector points on the tool: measured columns (k x 3) and their nominal layout (k, 3) in m."""

    columns: tuple[tuple[str, str, str], ...]
    nominal: np.ndarray
    max_residual: float | None  # m, RMS of the fit; above it the row is dropped


@dataclass(frozen=True)
class RowFilter:
    """Keep only the rows whose ``column`` equals ``equals`` (text or number) and/or lies in [min, max]."""

    column: str
    equals: str | float | None = None
    min: float | None = None
    max: float | None = None


@dataclass(frozen=True)
class ImportSpec:
    """How to read one export table. Units are the file's; the importer converts to m and rad."""

    source: str  # where the spec came from, for messages
    frame_id: str
    joint_columns: tuple[str, ...]
    joint_names: tuple[str, ...] | None  # None: the robot model's, in the columns' order
    joint_unit: str = "rad"
    position_columns: tuple[str, ...] = ()
    length_unit: float = 1e-3  # metres per file unit of the positions (and of the reflector points)
    orientation: str = "none"
    orientation_columns: tuple[str, ...] = ()
    quaternion_order: str = "wxyz"
    quaternion_tolerance: float = 1e-3
    euler_sequence: str = "XYZ"  # scipy's: upper case intrinsic, lower case extrinsic
    angle_unit: str = "deg"
    points: Points | None = None
    # the tracker's uncertainty of each position: one column (the same for every axis) or one per axis, in the
    # positions' unit, and the coverage factor it is given at (2: twice the standard deviation)
    uncertainty_columns: tuple[str, ...] = ()
    uncertainty_coverage: float = 1.0
    separator: str = ","  # "whitespace": runs of spaces and tabs
    decimal: str = "."
    skip_lines: int = 0
    comment: str | None = None
    encoding: str = "utf-8-sig"
    na_values: tuple[str, ...] = NA_VALUES
    stamp_column: str | None = None
    stamp_format: str = "seconds"
    stamp_period_s: float | None = None
    stamp_start_s: float = 0.0
    conditions: dict[str, tuple[str, float]] = field(default_factory=dict)  # name -> (column, scale)
    row_filter: RowFilter | None = None

    @property
    def measured_columns(self) -> tuple[str, ...]:
        """The tracker's columns: when all of them are zero the tracker did not measure."""
        if self.points is not None:
            return tuple(c for cols in self.points.columns for c in cols)
        return self.position_columns + self.orientation_columns

    @property
    def numeric_columns(self) -> tuple[str, ...]:
        cond = tuple(col for col, _ in self.conditions.values())
        stamp = (self.stamp_column,) if self.stamp_column and self._numeric_stamp else ()
        measured = self.measured_columns + self.uncertainty_columns
        return tuple(dict.fromkeys(self.joint_columns + measured + cond + stamp))

    @property
    def _numeric_stamp(self) -> bool:
        return self.stamp_format in ("seconds", "milliseconds", "nanoseconds")


def resolve_spec(spec: str | Path) -> Path:
    """A spec file, or the name of a shipped one (``config/import/<name>.yaml``, in the installed share
    directory after a plain ``colcon build``: see :mod:`kinematics.paths`)."""
    path = Path(spec)
    if path.is_file():
        return path
    shipped_dir = config_dir() / "import"
    shipped = shipped_dir / f"{spec}.yaml"
    if shipped.is_file():
        return shipped
    names = ", ".join(sorted(p.stem for p in shipped_dir.glob("*.yaml")))
    raise DataError(f"import spec {spec} does not exist (shipped specs: {names})")


def load_spec_dict(spec: str | Path, _seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    """The spec file as a dict, with ``extends: <spec>`` resolved: a section given here replaces the whole
    section of the spec it extends (so a stamp column there and a stamp period here do not mix)."""
    path = resolve_spec(spec).resolve()
    if path in _seen:
        raise DataError(f"import spec {path}: 'extends' loops back to itself")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise DataError(f"import spec {path}: cannot read it: {' '.join(str(exc).split())}") from exc
    if not isinstance(data, dict):
        raise DataError(f"import spec {path}: expected a mapping of sections, got {type(data).__name__}")
    parent = data.pop("extends", None)
    if parent is None:
        return data
    base = Path(str(parent))
    if not base.is_absolute() and (path.parent / base).is_file():
        base = path.parent / base
    merged = load_spec_dict(base if base.is_file() else str(parent), (*_seen, path))
    merged.update(data)
    return merged


class _Section:
    """Typed access to one spec section; every error names the key (``orientation.unit``) and the spec."""

    def __init__(self, data: Any, key: str, source: str) -> None:
        if data is None:
            data = {}
        if not isinstance(data, Mapping):
            raise DataError(f"import spec {source}: '{key}' must be a mapping, got {data!r}")
        self.data, self.key, self.source = dict(data), key, source

    def error(self, name: str, message: str) -> DataError:
        return DataError(f"import spec {self.source}: {self.key}.{name} {message}")

    def known(self, *names: str) -> None:
        unknown = sorted(set(self.data) - set(names))
        if unknown:
            raise self.error(unknown[0], f"is not a known key (known in '{self.key}': {', '.join(names)})")

    def get(self, name: str, default: Any = None) -> Any:
        return self.data.get(name, default)

    def require(self, name: str) -> Any:
        if self.data.get(name) is None:
            raise self.error(name, "is required")
        return self.data[name]

    def choice(self, name: str, choices: Sequence[str], default: str | None = None) -> str:
        value = self.data.get(name, default)
        if value is None:
            raise self.error(name, f"is required (one of {', '.join(choices)})")
        if str(value) not in choices:
            raise self.error(name, f"'{value}' is not one of {', '.join(choices)}")
        return str(value)

    def number(self, name: str, default: float | None = None, positive: bool = False) -> float | None:
        value = self.data.get(name, default)
        if value is None:
            return None
        try:
            out = float(value)
        except (TypeError, ValueError):
            raise self.error(name, f"'{value}' is not a number") from None
        if not np.isfinite(out) or (positive and out <= 0):
            raise self.error(name, f"'{value}' must be a {'positive' if positive else 'finite'} number")
        return out

    def columns(self, name: str, count: int | None = None, value: Any = None) -> tuple[str, ...]:
        value = self.data.get(name) if value is None else value
        if isinstance(value, str):
            value = [v.strip() for v in value.split(",")]
        if not isinstance(value, list | tuple) or not value or not all(isinstance(v, str) and v for v in value):
            raise self.error(name, f"must be a list of column names, got {value!r}")
        if count is not None and len(value) != count:
            raise self.error(name, f"needs {count} columns, got {len(value)}: {list(value)}")
        return tuple(value)


def spec_from_dict(data: Mapping[str, Any], source: str = "<flags>") -> ImportSpec:
    """Check a spec dict (the YAML layout, see ``config/import/ipa_robot_accuracy_a.yaml``) and build the spec.

    Raises:
        DataError: naming the spec and the key of the first unknown key, missing or bad value.
    """
    unknown = sorted(set(data) - set(SECTIONS))
    if unknown:
        raise DataError(f"import spec {source}: '{unknown[0]}' is not a known section ({', '.join(SECTIONS)})")
    out: dict[str, Any] = {"source": source}
    sections = (
        _format_section,
        _frame_section,
        _joints_section,
        _pose_section,
        _stamp_section,
        _conditions_section,
        _filter_section,
    )
    for section in sections:  # in this order, so that the first mistake is the one reported
        out |= section(data, source)
    return ImportSpec(**out)


def _format_section(data: Mapping[str, Any], source: str) -> dict[str, Any]:
    """The fields of separator, decimal mark, lines to skip, comments, encoding and missing-value marks."""
    out: dict[str, Any] = {}
    fmt = _Section(data.get("format"), "format", source)
    fmt.known("separator", "decimal", "skip_lines", "comment", "encoding", "na_values")
    out["separator"] = str(fmt.get("separator", ","))
    out["decimal"] = fmt.choice("decimal", (".", ","), ".")
    if out["separator"] == out["decimal"]:
        raise fmt.error("decimal", f"'{out['decimal']}' is also the separator")
    if out["separator"] != "whitespace" and len(out["separator"]) != 1:
        raise fmt.error("separator", f"'{out['separator']}' must be one character or 'whitespace'")
    skip = fmt.number("skip_lines", 0)
    if skip < 0 or skip != int(skip):
        raise fmt.error("skip_lines", f"'{fmt.get('skip_lines')}' must be a whole number >= 0")
    out["skip_lines"] = int(skip)
    out["comment"] = fmt.get("comment")
    out["encoding"] = str(fmt.get("encoding", "utf-8-sig"))
    if fmt.get("na_values") is not None:
        out["na_values"] = tuple(str(v).lower() for v in fmt.columns("na_values"))
    return out


def _frame_section(data: Mapping[str, Any], source: str) -> dict[str, Any]:
    """The fields of the tracker station's frame."""
    out: dict[str, Any] = {}
    frame = data.get("frame_id")
    if not isinstance(frame, str) or not frame:
        raise DataError(f"import spec {source}: frame_id is required (the tracker station's frame), got {frame!r}")
    out["frame_id"] = frame
    return out


def _joints_section(data: Mapping[str, Any], source: str) -> dict[str, Any]:
    """The fields of the joint columns, by name or in the model's order, and their unit."""
    out: dict[str, Any] = {}
    joints = _Section(data.get("joints"), "joints", source)
    joints.known("columns", "names", "unit")
    cols = joints.require("columns")
    if isinstance(cols, Mapping):  # by name: model joint -> column
        out["joint_names"] = tuple(str(k) for k in cols)
        out["joint_columns"] = joints.columns("columns", value=[str(v) for v in cols.values()])
        if joints.get("names") is not None:
            raise joints.error("names", "conflicts with columns given by joint name")
    else:
        out["joint_columns"] = joints.columns("columns")
        names = joints.get("names")
        out["joint_names"] = None if names is None else joints.columns("names", len(out["joint_columns"]))
    out["joint_unit"] = joints.choice("unit", ANGLE_UNITS)
    return out


def _pose_section(data: Mapping[str, Any], source: str) -> dict[str, Any]:
    """The fields of the measured position and orientation (or the reflector points that give both)."""
    out: dict[str, Any] = {}
    orient = _Section(data.get("orientation"), "orientation", source)
    kind = orient.choice("kind", ORIENTATIONS)
    out["orientation"] = kind
    position = _Section(data.get("position"), "position", source)
    if kind == "points":
        orient.known("kind", "points", "unit", "max_residual")
        if data.get("position") is not None:
            raise DataError(f"import spec {source}: position: the reflector points give the position; remove it")
        scale = LENGTH_UNITS[orient.choice("unit", tuple(LENGTH_UNITS))]
        out["length_unit"] = scale
        out["points"] = _points(orient, scale)
    else:
        position.known("columns", "unit", "uncertainty", "coverage")
        out["position_columns"] = position.columns("columns", 3, position.require("columns"))
        out["length_unit"] = LENGTH_UNITS[position.choice("unit", tuple(LENGTH_UNITS))]
        if position.get("uncertainty") is not None:
            out["uncertainty_columns"] = position.columns("uncertainty")
            if len(out["uncertainty_columns"]) not in (1, 3):
                raise position.error("uncertainty", "needs one column (every axis) or three (x, y, z)")
            out["uncertainty_coverage"] = position.number("coverage", 1.0, positive=True)
        if kind == "quaternion":
            orient.known("kind", "columns", "order", "tolerance")
            out["orientation_columns"] = orient.columns("columns", 4, orient.require("columns"))
            out["quaternion_order"] = orient.choice("order", ("wxyz", "xyzw"))
            out["quaternion_tolerance"] = orient.number("tolerance", 1e-3, positive=True)
        elif kind == "euler":
            orient.known("kind", "columns", "sequence", "convention", "unit")
            out["orientation_columns"] = orient.columns("columns", 3, orient.require("columns"))
            seq = str(orient.require("sequence"))
            if not re.fullmatch(r"[xyzXYZ]{3}", seq) or seq[0].lower() == seq[1].lower() or seq[1] == seq[2]:
                raise orient.error("sequence", f"'{seq}' is not an Euler sequence such as XYZ or ZYZ")
            convention = orient.choice("convention", ("intrinsic", "extrinsic"))
            out["euler_sequence"] = seq.upper() if convention == "intrinsic" else seq.lower()
            out["angle_unit"] = orient.choice("unit", ANGLE_UNITS)
        else:
            orient.known("kind")
    return out


def _stamp_section(data: Mapping[str, Any], source: str) -> dict[str, Any]:
    """The fields of the measurement times: a column and its format, or the row order and a period."""
    out: dict[str, Any] = {}
    stamp = _Section(data.get("stamp"), "stamp", source)
    stamp.known("column", "format", "period_s", "start")
    if stamp.get("column") is not None and stamp.get("period_s") is not None:
        raise stamp.error("period_s", "conflicts with stamp.column: give one (a period stamps rows by their index)")
    if stamp.get("column") is not None:
        out["stamp_column"] = str(stamp.get("column"))
        fmt_value = str(stamp.get("format", "seconds"))
        if fmt_value not in STAMP_FORMATS and "%" not in fmt_value:
            raise stamp.error("format", f"'{fmt_value}' is not one of {', '.join(STAMP_FORMATS)} or a strftime pattern")
        out["stamp_format"] = fmt_value
    else:  # the rows' order is the measurement order: row i is stamped start + i * period
        out["stamp_period_s"] = stamp.number("period_s", 1.0, positive=True)
        out["stamp_start_s"] = _start_seconds(stamp)
    return out


def _conditions_section(data: Mapping[str, Any], source: str) -> dict[str, Any]:
    """The fields of the condition channels carried along."""
    out: dict[str, Any] = {}
    cond = data.get("conditions") or {}
    if not isinstance(cond, Mapping):
        raise DataError(f"import spec {source}: conditions must map a condition name to a column, got {cond!r}")
    conditions: dict[str, tuple[str, float]] = {}
    for name, value in cond.items():
        if name not in CONDITION_TYPES:
            raise DataError(
                f"import spec {source}: conditions.{name} is not a known condition ({', '.join(CONDITION_TYPES)})"
            )
        entry = _Section(value if isinstance(value, Mapping) else {"column": value}, f"conditions.{name}", source)
        entry.known("column", "scale")
        conditions[name] = (str(entry.require("column")), entry.number("scale", 1.0))
    out["conditions"] = conditions
    return out


def _filter_section(data: Mapping[str, Any], source: str) -> dict[str, Any]:
    """The fields of the rows kept."""
    out: dict[str, Any] = {}
    if data.get("filter") is not None:
        flt = _Section(data.get("filter"), "filter", source)
        flt.known("column", "equals", "min", "max")
        if all(flt.get(k) is None for k in ("equals", "min", "max")):
            raise flt.error("equals", "or filter.min / filter.max is required")
        out["row_filter"] = RowFilter(
            str(flt.require("column")), flt.get("equals"), flt.number("min"), flt.number("max")
        )
    return out


def _points(orient: _Section, scale: float) -> Points:
    entries = orient.require("points")
    if not isinstance(entries, list) or len(entries) < 3:
        raise orient.error("points", f"needs three or more reflector points, got {entries!r}")
    columns, nominal = [], []
    for i, entry in enumerate(entries):
        point = _Section(entry, f"orientation.points[{i}]", orient.source)
        point.known("columns", "nominal")
        columns.append(point.columns("columns", 3, point.require("columns")))
        try:
            xyz = np.asarray(point.require("nominal"), dtype=float).reshape(3)
        except (TypeError, ValueError):
            raise point.error("nominal", f"must be [x, y, z], got {point.get('nominal')!r}") from None
        nominal.append(xyz * scale)
    layout = np.array(nominal)
    singular = np.linalg.svd(layout - layout.mean(axis=0), compute_uv=False)
    if singular[1] <= 1e-9 * max(singular[0], 1e-12):
        raise orient.error("points", "nominal layout is collinear: it cannot give an orientation")
    max_residual = orient.number("max_residual", None, positive=True)
    return Points(tuple(columns), layout, None if max_residual is None else max_residual * scale)


def _start_seconds(stamp: _Section) -> float:
    value = stamp.get("start", 0.0)
    if isinstance(value, dt.datetime | dt.date):  # YAML reads an unquoted timestamp as a datetime
        value = value.isoformat()
    if isinstance(value, str):
        try:
            return float(value)  # seconds, e.g. from the command line
        except ValueError:
            pass
        try:
            parsed = dt.datetime.fromisoformat(value)
        except ValueError:
            raise stamp.error("start", f"'{value}' is neither seconds nor an ISO 8601 time") from None
        if parsed.tzinfo is None:
            parsed = parsed.replace(tzinfo=dt.UTC)
        return parsed.timestamp()
    return stamp.number("start", 0.0)
