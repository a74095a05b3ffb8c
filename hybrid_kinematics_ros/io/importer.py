"""Metrology exports to calibration pairs: read a table of tracker measurements and joint readings by a spec.

The spec (``io/import_spec.py``) says how the table is laid out; this module reads the rows
(:func:`read_table`) and converts them into pairs in m, rad and the spec's frame (:func:`import_table`).

Failed measurements (an empty or NaN field, an all-zero measurement, a quaternion far from unit length,
reflector points that do not fit the tool's layout) are dropped and counted by reason. A malformed file (a
field that is not a number, a missing column, a wrong field count) raises :class:`DataError` naming the
file, the line and the column: it is a wrong spec or a broken export, and guessing would hide it.
"""

from __future__ import annotations

import calendar
import csv
import datetime as dt
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from hybrid_kinematics_ros.io.errors import DataError
from hybrid_kinematics_ros.io.import_spec import ImportSpec, RowFilter
from hybrid_kinematics_ros.io.pairs import Pairs, floor_summary
from hybrid_kinematics_ros.kinematics import se3


@dataclass
class ImportResult:
    """The pairs of one file, with what happened to its rows."""

    pairs: Pairs
    rows: int  # data rows in the file
    filtered: int  # rows the row filter left out (not failures)
    dropped: Counter  # failed measurements by reason

    def summary(self) -> dict[str, Any]:
        return {
            "rows": self.rows,
            "imported": len(self.pairs),
            "filtered_out": self.filtered,
            "dropped": dict(sorted(self.dropped.items())),
            "frame_id": self.pairs.frame_id,
            "position_only": self.pairs.position_only,
            "conditions": sorted(self.pairs.conditions),
            **({} if self.pairs.floor is None else {"tracker_floor": floor_summary(self.pairs.floor)}),
        }


# --------------------------------------------------------------------------------------------- reading


def _rows(path: Path, spec: ImportSpec) -> Iterator[tuple[int, list[str]]]:
    """(line number, fields) of every non-blank, non-comment line after the skipped preamble."""
    try:
        f = path.open(newline="", encoding=spec.encoding)
    except OSError as exc:
        raise DataError(f"{path}: cannot open it: {exc.strerror}") from None
    with f:
        lines = iter(f)
        number = 0
        try:
            for _ in range(spec.skip_lines):
                next(lines, None)
                number += 1
            if spec.separator == "whitespace":
                for line in lines:
                    number += 1
                    stripped = line.strip()
                    if stripped and not (spec.comment and stripped.startswith(spec.comment)):
                        yield number, stripped.split()
                return
            reader = csv.reader(lines, delimiter=spec.separator)
            for row in reader:
                line = number + reader.line_num
                text = spec.separator.join(row).strip()
                if text and not (spec.comment and text.startswith(spec.comment)):
                    yield line, row
        except UnicodeDecodeError as exc:
            raise DataError(f"{path}: line {number + 1}: not {spec.encoding} text ({exc.reason})") from None
        except csv.Error as exc:
            raise DataError(f"{path}: line {number + reader.line_num}: {exc}") from None


def _stamp_ns(text: str, spec: ImportSpec, where: str) -> int:
    if spec.stamp_format == "iso8601":
        try:
            parsed = dt.datetime.fromisoformat(text)
        except ValueError:
            raise DataError(f"{where}: '{text}' is not an ISO 8601 time") from None
    else:
        try:
            parsed = dt.datetime.strptime(text, spec.stamp_format)
        except ValueError:
            raise DataError(f"{where}: '{text}' does not match the stamp format '{spec.stamp_format}'") from None
    if parsed.tzinfo is None:  # an export without a zone: read as UTC, so stamps do not depend on the machine
        parsed = parsed.replace(tzinfo=dt.UTC)
    seconds = calendar.timegm(parsed.utctimetuple())
    return seconds * 1_000_000_000 + parsed.microsecond * 1000


def _matches(flt: RowFilter, text: str, decimal: str) -> bool:
    try:
        number = float(text.strip().replace(decimal, ".")) if text.strip() else float("nan")
    except ValueError:
        number = None
    if flt.equals is not None:
        if isinstance(flt.equals, int | float) and not isinstance(flt.equals, bool):
            if number is None or number != float(flt.equals):
                return False
        elif text.strip() != str(flt.equals):
            return False
    if flt.min is not None and (number is None or not number >= flt.min):
        return False
    return not (flt.max is not None and (number is None or not number <= flt.max))


def read_table(
    path: str | Path, spec: ImportSpec
) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray, np.ndarray, int, int]:
    """Parse the spec's columns of every kept row.

    Returns:
        the columns as floats (``nan`` where the field is empty or a NaN text), the empty-field mask
        ``(N, C + 1)`` (``spec.numeric_columns`` then the stamp), the stamps (ns, ``(N,)``), the file's data row
        index of each kept row, the number of data rows and the number the filter left out.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path} does not exist")
    rows = _rows(path, spec)
    layout = _Layout.of(path, spec, next(rows, None))
    values: list[list[float]] = []
    empty: list[list[bool]] = []
    stamps: list[int] = []
    row_index: list[int] = []
    total = filtered = 0
    for line, row in rows:
        row = layout.fields(row, line)
        total += 1
        if layout.filter_index is not None and not _matches(spec.row_filter, row[layout.filter_index], spec.decimal):
            filtered += 1
            continue
        parsed = [
            _number(row[i].strip(), spec, f"{path}: line {line}, column {i + 1} '{c}'") for c, i in layout.numeric
        ]
        numbers = [v for v, _ in parsed]
        stamp, blank_stamp = layout.stamp(row, numbers, f"{path}: line {line}")
        values.append(numbers)
        empty.append([blank for _, blank in parsed] + [blank_stamp])
        stamps.append(stamp)
        row_index.append(total - 1)
    rows_index = np.array(row_index, dtype=np.int64)
    if spec.stamp_column is None:
        # row i of the file (counting every data row, kept or not) is stamped start + i * period
        start_ns = round(spec.stamp_start_s * 1e9)
        stamp_arr = start_ns + rows_index * round(spec.stamp_period_s * 1e9)
    else:
        stamp_arr = np.array(stamps, dtype=np.int64)
    table = np.array(values, dtype=float).reshape(len(values), len(layout.numeric))
    columns = {c: table[:, k] for k, (c, _) in enumerate(layout.numeric)}
    mask = np.array(empty, dtype=bool).reshape(len(values), -1)
    return columns, mask, stamp_arr, rows_index, total, filtered


@dataclass(frozen=True)
class _Layout:
    """Where the spec's columns sit in a table: the header, each numeric column's index, the stamp's and the
    filter's."""

    path: Path
    spec: ImportSpec
    header: list[str]
    numeric: list[tuple[str, int]]
    stamp_index: int | None
    filter_index: int | None
    stamp_position: int | None  # the stamp's place among the numeric columns, when it is one of them

    @classmethod
    def of(cls, path: Path, spec: ImportSpec, first: tuple[int, list[str]] | None) -> _Layout:
        """From the header row ``first`` (line number, fields); every column the spec names must be in it."""
        if first is None:
            raise DataError(f"{path} has no header line")
        header_line, header = first
        header = [h.strip() for h in header]
        if spec.separator != "whitespace":
            while header and not header[-1]:  # a trailing separator
                header.pop()
        wanted = list(spec.numeric_columns)
        if spec.stamp_column and spec.stamp_column not in wanted:
            wanted.append(spec.stamp_column)
        if spec.row_filter:
            wanted.append(spec.row_filter.column)
        missing = [c for c in dict.fromkeys(wanted) if c not in header]
        numeric = list(spec.numeric_columns)
        if missing:
            raise DataError(
                f"{path}: line {header_line}: no column '{missing[0]}' in the header "
                f"({spec.separator if spec.separator != 'whitespace' else ' '}-separated: {', '.join(header)})"
            )
        return cls(
            path,
            spec,
            header,
            [(c, header.index(c)) for c in numeric],
            header.index(spec.stamp_column) if spec.stamp_column else None,
            header.index(spec.row_filter.column) if spec.row_filter else None,
            numeric.index(spec.stamp_column) if spec.stamp_column in numeric else None,
        )

    def fields(self, row: list[str], line: int) -> list[str]:
        """The row's fields, one per header column (empty trailing fields dropped)."""
        width = len(self.header)
        if len(row) > width and not any(f.strip() for f in row[width:]):
            row = row[:width]
        if len(row) != width:
            raise DataError(
                f"{self.path}: line {line}: {len(row)} fields, the header has {width} "
                f"(separator '{self.spec.separator}', decimal mark '{self.spec.decimal}')"
            )
        return row

    def stamp(self, row: list[str], parsed: list[float], where: str) -> tuple[int, bool]:
        """The row's stamp (ns; 0 where the rows' order stamps them, set later) and whether its field is empty."""
        spec, index = self.spec, self.stamp_index
        if index is None:
            return 0, False
        text = row[index].strip()
        if not text:
            return 0, True  # dropped by the caller: an empty stamp field is an empty field
        if spec._numeric_stamp:
            value = parsed[self.stamp_position]
            scale = {"seconds": 1e9, "milliseconds": 1e6, "nanoseconds": 1.0}[spec.stamp_format]
            return (round(value * scale) if np.isfinite(value) else 0), False
        return _stamp_ns(text, spec, f"{where}, column {index + 1} '{spec.stamp_column}'"), False


def _number(text: str, spec: ImportSpec, where: str) -> tuple[float, bool]:
    """One numeric field: its value (NaN for an empty field or a missing-value mark) and whether it is empty."""
    if not text:
        return np.nan, True
    if text.lower() in spec.na_values:
        return np.nan, False
    if not (spec.decimal == "," and "." in text):  # "1.5" with a decimal comma: a thousands mark or the wrong spec
        try:
            return float(text.replace(",", ".") if spec.decimal == "," else text), False
        except ValueError:
            pass
    raise DataError(f"{where}: '{text}' is not a number (decimal mark '{spec.decimal}')")


# --------------------------------------------------------------------------------------------- converting


def import_table(path: str | Path, spec: ImportSpec, model_joints: Sequence[str] | None = None) -> ImportResult:
    """Read one export file into pairs (m, rad, the spec's frame), dropping and counting failed measurements.

    Args:
        path: the CSV or TXT export.
        spec: how to read it.
        model_joints: the robot model's joint names. With joint columns given in model order and no
            ``joints.names`` they name the columns; otherwise the spec's names are checked against them and
            the joints are written in the model's order.

    Raises:
        DataError: a malformed file (naming the line and column), a spec that does not fit the model, or no
            usable row.
    """
    path = Path(path)
    names, order = _joint_names(spec, model_joints)
    columns, empty, stamps, _, total, filtered = read_table(path, spec)
    rows = _Rows(columns, len(stamps))
    rows.drop(np.any(empty, axis=1), "empty_field")
    rows.drop(~np.all(np.isfinite(rows.stack(spec.numeric_columns)), axis=1), "nan")
    rows.drop(np.all(rows.stack(spec.measured_columns) == 0.0, axis=1), "all_zero_measurement")
    q = rows.stack(spec.joint_columns)[:, order]
    if spec.joint_unit == "deg":
        q = np.radians(q)
    T, residual = _poses(spec, rows)
    # stamps are the pairs' identity: a second row with the same stamp cannot be told apart from the first
    _, first = np.unique(np.where(rows.keep, stamps, np.iinfo(np.int64).min), return_index=True)
    unique = np.zeros(rows.n, dtype=bool)
    unique[first] = True
    rows.drop(~unique, "duplicate_stamp")
    keep = rows.keep
    if not np.any(keep):
        raise DataError(f"{path}: no usable row among {total} (dropped {dict(rows.dropped)}, filtered out {filtered})")
    conditions = {name: columns[col][keep] * scale for name, (col, scale) in spec.conditions.items()}
    pairs = Pairs(
        q[keep],
        T[keep],
        stamps[keep],
        names,
        spec.frame_id,
        position_only=spec.orientation == "none",
        conditions=conditions,
        floor=_floor(spec, rows.stack, keep, residual),
    )
    return ImportResult(pairs, total, filtered, rows.dropped)


class _Rows:
    """An export's rows as they are read: their columns, which rows are kept, and how many were dropped why."""

    def __init__(self, columns: dict[str, np.ndarray], n: int) -> None:
        self.columns, self.n = columns, n
        self.keep = np.ones(n, dtype=bool)
        self.dropped: Counter = Counter()

    def drop(self, mask: np.ndarray, reason: str) -> None:
        """Drop the kept rows of ``mask``, counted under ``reason``."""
        mask = mask & self.keep
        if np.any(mask):
            self.dropped[reason] += int(mask.sum())
        self.keep &= ~mask

    def stack(self, cols: Sequence[str]) -> np.ndarray:
        """The columns ``cols`` side by side, ``(n, len(cols))``."""
        return np.stack([self.columns[c] for c in cols], axis=1) if cols else np.zeros((self.n, 0))


def _poses(spec: ImportSpec, rows: _Rows) -> tuple[np.ndarray, np.ndarray | None]:
    """The measured poses ``(n, 4, 4)`` (m), from a position and an orientation or from reflector points fitted
    rigidly, and the point fit's residuals (None without points). Rows whose points fit too poorly, or whose
    quaternion is not a unit one, are dropped."""
    T = np.tile(np.eye(4), (rows.n, 1, 1))
    residual = None
    if spec.points is not None:
        measured = np.stack([rows.stack(cols) for cols in spec.points.columns], axis=1) * spec.length_unit
        T, residual = se3.fit_rigid(spec.points.nominal, np.where(rows.keep[:, None, None], measured, 0.0))
        if spec.points.max_residual is not None:
            rows.drop(residual > spec.points.max_residual, "point_fit_residual")
    else:
        T[:, :3, 3] = rows.stack(spec.position_columns) * spec.length_unit
    if spec.orientation == "quaternion":
        quat = rows.stack(spec.orientation_columns)
        if spec.quaternion_order == "wxyz":
            quat = quat[:, [1, 2, 3, 0]]
        norm = np.linalg.norm(np.where(rows.keep[:, None], quat, 0.0), axis=1)
        rows.drop(np.abs(norm - 1.0) > spec.quaternion_tolerance, "non_unit_quaternion")
        quat = np.where(rows.keep[:, None], quat / np.where(norm > 0, norm, 1.0)[:, None], [0.0, 0.0, 0.0, 1.0])
        T[:, :3, :3] = Rotation.from_quat(quat).as_matrix()
    elif spec.orientation == "euler":
        angles = np.where(rows.keep[:, None], rows.stack(spec.orientation_columns), 0.0)
        rot = Rotation.from_euler(spec.euler_sequence, angles, degrees=spec.angle_unit == "deg")
        T[:, :3, :3] = rot.as_matrix()
    return T, residual


FLOOR_TRIALS = 4000  # simulated measurements: the floor to about 1 %


def _floor(
    spec: ImportSpec, stack: Callable[[Sequence[str]], np.ndarray], keep: np.ndarray, residual: np.ndarray | None
) -> tuple[float, float] | None:
    """The tracker's own floor (m, rad), where the export tells it: from the reflectors' scatter about their
    layout, or from its uncertainty columns (position only); None otherwise."""
    if residual is not None:
        return reflector_floor(spec.points.nominal, residual[keep])
    if spec.uncertainty_columns:
        sigma = stack(spec.uncertainty_columns)[keep] * spec.length_unit / spec.uncertainty_coverage
        return uncertainty_floor(np.broadcast_to(sigma, (len(sigma), 3))), float("nan")
    return None


def uncertainty_floor(sigma: np.ndarray) -> float:
    """The mean length (m) of position errors with standard deviations ``sigma (N, 3)`` (m, per axis), over the
    rows, by simulation: at least :data:`FLOOR_TRIALS` draws in all."""
    repeats = -(-FLOOR_TRIALS // len(sigma))
    draws = np.random.default_rng(0).normal(0.0, 1.0, (len(sigma), repeats, 3))
    return float(np.mean(np.linalg.norm(sigma[:, None, :] * draws, axis=2)))


def reflector_floor(layout: np.ndarray, residual: np.ndarray) -> tuple[float, float]:
    """One measurement's mean position (m) and orientation (rad) error at the tool's origin from the reflectors'
    own scatter. Each row's rigid fit of the ``layout (k, 3)`` leaves ``residual`` (rms over its points), whose
    square has ``(3k − 6) / k · σ²`` as expectation for a per-coordinate noise ``σ``; that noise is then sent
    through the same fit, by simulation, to the pose it gives."""
    k = len(layout)
    sigma = float(np.sqrt(np.mean(residual**2) * k / (3 * k - 6)))
    noisy = layout + np.random.default_rng(0).normal(0.0, sigma, (FLOOR_TRIALS, k, 3))
    fitted, _ = se3.fit_rigid(layout, noisy)
    position = np.linalg.norm(fitted[:, :3, 3], axis=1)
    return float(np.mean(position)), float(np.mean(se3.rotation_angle(fitted[:, :3, :3])))


def _joint_names(spec: ImportSpec, model: Sequence[str] | None) -> tuple[tuple[str, ...], list[int]]:
    """The joint names to write and the column order that gives them."""
    count = len(spec.joint_columns)
    if spec.joint_names is None:
        if model is None:
            raise DataError(
                f"import spec {spec.source}: joints.columns are in model order but nothing names the model's "
                "joints: give joints.names (or columns by joint name), or --robot"
            )
        if len(model) != count:
            raise DataError(
                f"import spec {spec.source}: joints.columns has {count} columns, the robot has {len(model)} "
                f"joints ({', '.join(model)})"
            )
        return tuple(model), list(range(count))
    if model is None:
        return spec.joint_names, list(range(count))
    if set(spec.joint_names) != set(model) or len(spec.joint_names) != len(model):
        unknown = sorted(set(spec.joint_names) - set(model))
        missing = sorted(set(model) - set(spec.joint_names))
        raise DataError(
            f"import spec {spec.source}: joints name {list(spec.joint_names)}; unknown {unknown}, missing "
            f"{missing} (the robot has {list(model)})"
        )
    return tuple(model), [spec.joint_names.index(j) for j in model]
