"""``import``: a metrology export (CSV/TXT: tracker measurements and joint readings) to a calibration-pairs bag.

The table is read by an import spec (YAML, see ``config/import/``); every flag below sets or overrides one
key of it, so a spec can also be given by flags alone.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

from hybrid_kinematics_ros.cli.common import add_robot_args, chain_from_args, robot_given
from hybrid_kinematics_ros.io.errors import DataError
from hybrid_kinematics_ros.io.import_spec import ORIENTATIONS, load_spec_dict, spec_from_dict
from hybrid_kinematics_ros.io.importer import import_table
from hybrid_kinematics_ros.io.pairs import CONDITION_TYPES, write_pairs


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "import",
        help="turn a tracker export (CSV/TXT with joint readings) into calibration pairs",
        description=__doc__.splitlines()[0],
    )
    p.add_argument("--csv", required=True, type=Path, help="the export file (CSV or TXT)")
    p.add_argument("--out", required=True, type=Path, help="pairs bag to write")
    p.add_argument("--spec", help="import spec: a YAML file or a shipped name (e.g. ipa_robot_accuracy_a)")
    add_robot_args(p, required=False)
    p.add_argument("--frame-id", help="the tracker station's frame (overrides the spec's)")
    g = p.add_argument_group("file format")
    g.add_argument("--separator", help="field separator, one character or 'whitespace' (default ',')")
    g.add_argument("--decimal", choices=(".", ","), help="decimal mark (default '.')")
    g.add_argument("--skip-lines", type=int, help="lines before the header to skip")
    g = p.add_argument_group("joints")
    g.add_argument("--joints", help="joint columns: COL,COL,... in model order, or JOINT=COL,... by joint name")
    g.add_argument("--joint-names", help="the model's joint names for columns given in model order")
    g.add_argument("--joint-unit", choices=("rad", "deg"))
    g = p.add_argument_group("measured pose")
    g.add_argument("--position", help="position columns X,Y,Z")
    g.add_argument("--position-unit", choices=("mm", "m"))
    g.add_argument(
        "--position-uncertainty",
        metavar="U or UX,UY,UZ",
        help="the tracker's uncertainty of each position: one column (every axis) or three, in the positions' unit",
    )
    g.add_argument(
        "--uncertainty-coverage", type=float, help="the coverage factor the uncertainty is given at (default 1)"
    )
    g.add_argument("--orientation", choices=ORIENTATIONS, help="how the orientation is given")
    g.add_argument("--quaternion", help="quaternion columns, in --quaternion-order")
    g.add_argument("--quaternion-order", choices=("wxyz", "xyzw"))
    g.add_argument("--euler", help="Euler angle columns A,B,C")
    g.add_argument("--euler-sequence", help="axis sequence, e.g. XYZ or ZYX")
    g.add_argument("--euler-convention", choices=("intrinsic", "extrinsic"))
    g.add_argument("--angle-unit", choices=("rad", "deg"), help="unit of the Euler angles")
    g.add_argument(
        "--point",
        action="append",
        metavar="X,Y,Z=NX,NY,NZ",
        help="a reflector point: its columns and its nominal position on the tool (repeat, three or more)",
    )
    g.add_argument("--point-unit", choices=("mm", "m"), help="unit of the reflector points and their layout")
    g.add_argument("--max-point-residual", type=float, help="drop rows whose points fit worse (RMS, point unit)")
    g = p.add_argument_group("stamps, conditions, rows")
    g.add_argument("--stamp-column", help="column of the measurement time")
    g.add_argument("--stamp-format", help="seconds, milliseconds, nanoseconds, iso8601 or a strftime pattern")
    g.add_argument("--stamp-period", type=float, metavar="S", help="no usable stamp column: row i at start + i*S")
    g.add_argument("--stamp-start", help="stamp of the first row with --stamp-period (seconds or ISO 8601)")
    g.add_argument(
        "--condition",
        action="append",
        metavar="NAME=COL",
        help=f"carry a column along as a condition channel ({', '.join(CONDITION_TYPES)}); repeat",
    )
    g.add_argument("--filter", metavar="COL=VALUE", help="import only the rows whose column has this value")
    p.set_defaults(run=run)


def _pair(text: str, flag: str) -> tuple[str, str]:
    key, sep, value = text.partition("=")
    if not sep or not key.strip() or not value.strip():
        raise DataError(f"{flag} '{text}': expected NAME=VALUE")
    return key.strip(), value.strip()


# flags of the spec's position section: flag -> key
POSITION_FLAGS = {
    "position": "columns",
    "position_unit": "unit",
    "position_uncertainty": "uncertainty",
    "uncertainty_coverage": "coverage",
}


def spec_dict_from_args(args: argparse.Namespace) -> dict[str, Any]:
    """The spec file's dict (or an empty one) with every given flag written over its key."""
    data: dict[str, Any] = load_spec_dict(args.spec) if args.spec else {}
    for flag, key in (("separator", "separator"), ("decimal", "decimal"), ("skip_lines", "skip_lines")):
        if getattr(args, flag) is not None:
            _section(data, "format")[key] = getattr(args, flag)
    if args.frame_id:
        data["frame_id"] = args.frame_id
    _joint_flags(args, data)
    for flag, key in POSITION_FLAGS.items():
        if getattr(args, flag) is not None:
            _section(data, "position")[key] = getattr(args, flag)
    _orientation_flags(args, data)
    _stamp_flags(args, data)
    for text in args.condition or ():
        name, column = _pair(text, "--condition")
        _section(data, "conditions")[name] = column
    if args.filter:
        column, value = _pair(args.filter, "--filter")
        try:
            equals: str | float = float(value)
        except ValueError:
            equals = value
        data["filter"] = {"column": column, "equals": equals}
    return data


def _section(data: dict[str, Any], name: str) -> dict[str, Any]:
    """``data[name]`` as a dict of its own (a new, empty one where the spec has none), for flags to write to."""
    value = data.get(name)
    data[name] = dict(value) if isinstance(value, dict) else {}
    return data[name]


def _joint_flags(args: argparse.Namespace, data: dict[str, Any]) -> None:
    """``--joints`` (columns, or ``name=column`` pairs), ``--joint-names`` and ``--joint-unit`` into ``data``."""
    if args.joints:
        items = [c.strip() for c in args.joints.split(",")]
        joints = _section(data, "joints")
        if all("=" in c for c in items):
            joints["columns"] = dict(_pair(c, "--joints") for c in items)
            joints.pop("names", None)
        else:
            joints["columns"] = items
    if args.joint_names:
        _section(data, "joints")["names"] = [c.strip() for c in args.joint_names.split(",")]
    if args.joint_unit:
        _section(data, "joints")["unit"] = args.joint_unit


def _orientation_flags(args: argparse.Namespace, data: dict[str, Any]) -> None:
    """The orientation's flags into ``data``: its kind (another kind drops the spec's keys), columns, units and
    the reflector points (``--point COLUMNS=X,Y,Z``)."""
    orient = data.get("orientation") if isinstance(data.get("orientation"), dict) else {}
    if args.orientation and args.orientation != orient.get("kind"):
        data["orientation"] = {"kind": args.orientation}  # another kind: none of the old keys apply
    for flag, key in (
        ("quaternion", "columns"),
        ("quaternion_order", "order"),
        ("euler", "columns"),
        ("euler_sequence", "sequence"),
        ("euler_convention", "convention"),
        ("angle_unit", "unit"),
        ("point_unit", "unit"),
        ("max_point_residual", "max_residual"),
    ):
        if getattr(args, flag) is not None:
            _section(data, "orientation")[key] = getattr(args, flag)
    if args.point:
        points = []
        for text in args.point:
            columns, nominal = _pair(text, "--point")
            try:
                xyz = [float(v) for v in nominal.split(",")]
            except ValueError:
                raise DataError(f"--point '{text}': the nominal position '{nominal}' is not three numbers") from None
            points.append({"columns": columns, "nominal": xyz})
        _section(data, "orientation")["points"] = points


def _stamp_flags(args: argparse.Namespace, data: dict[str, Any]) -> None:
    """The time stamps' flags into ``data``: a column and its format, or a period and start (no column)."""
    if args.stamp_column:
        data["stamp"] = {"column": args.stamp_column, "format": args.stamp_format or "seconds"}
    elif args.stamp_format:
        _section(data, "stamp")["format"] = args.stamp_format
    if args.stamp_period is not None or args.stamp_start is not None:
        stamp = _section(data, "stamp")
        stamp.pop("column", None)
        stamp.pop("format", None)
        if args.stamp_period is not None:
            stamp["period_s"] = args.stamp_period
        if args.stamp_start is not None:
            stamp["start"] = args.stamp_start


def run(args: argparse.Namespace) -> int:
    start = time.perf_counter()
    if args.out.exists():  # before reading the file, not after
        raise DataError(f"{args.out} exists already, not overwriting")
    source = f"{args.spec} with flags" if args.spec else "from flags"
    spec = spec_from_dict(spec_dict_from_args(args), source)
    model_joints = chain_from_args(args).joint_names if robot_given(args) else None
    result = import_table(args.csv, spec, model_joints)
    write_pairs(args.out, result.pairs)
    summary = {"csv": str(args.csv), "out": str(args.out), **result.summary()}
    summary["seconds"] = round(time.perf_counter() - start, 3)
    dropped = ", ".join(f"{k} {v}" for k, v in summary["dropped"].items()) or "none"
    print(
        f"imported {summary['imported']} of {summary['rows']} rows into {args.out} (frame {spec.frame_id}); "
        f"dropped: {dropped}; filtered out: {summary['filtered_out']}",
        file=sys.stderr,
    )
    print(json.dumps(summary))
    return 0
