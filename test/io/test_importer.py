"""Importing metrology exports: the real data set's excerpt against an independent conversion, every
orientation kind and unit on synthetic poses with a known truth, failed rows, and malformed files and specs."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hybrid_kinematics_ros.io.errors import DataError
from hybrid_kinematics_ros.io.import_spec import load_spec_dict, spec_from_dict
from hybrid_kinematics_ros.io.importer import import_table
from hybrid_kinematics_ros.kinematics import se3
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures" / "ipa-robot-accuracy"
UR10 = load_robot_config("ur10").chain.joint_names
UPSTREAM_JOINTS = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)


def raw_table(path: Path) -> tuple[list[str], list[list[str]]]:
    """The fixture's header and fields, split by hand: the independent side of the cross-check."""
    lines = path.read_bytes().decode().split("\r\n")
    header = lines[0].split(";")
    return header, [line.split(";") for line in lines[1:] if line]


@pytest.mark.parametrize(
    ("spec", "fixture"),
    [
        ("ipa_robot_accuracy_a", "Series_A_measurements_grid_head40.csv"),
        ("ipa_robot_accuracy_bc", "Series_C_measurements_random_poses_head40.csv"),
    ],
)
def test_shipped_spec_matches_scipy_euler_and_units_by_hand(spec, fixture):
    result = import_table(FIXTURES / fixture, spec_from_dict(load_spec_dict(spec), spec), UR10)
    header, rows = raw_table(FIXTURES / fixture)
    assert result.rows == len(rows) == 40 and len(result.pairs) == 40 and not result.dropped

    def col(name):
        return np.array([float(r[header.index(name)].replace(",", ".")) for r in rows])

    position_m = np.stack([col(f"measurement_{a}") for a in "xyz"], axis=1) / 1000.0
    rotation = Rotation.from_euler("XYZ", np.stack([col(f"measurement_r{a}") for a in "xyz"], axis=1), degrees=True)
    pairs = result.pairs
    np.testing.assert_allclose(pairs.T[:, :3, 3], position_m, rtol=0, atol=1e-15)
    np.testing.assert_allclose(pairs.T[:, :3, :3], rotation.as_matrix(), rtol=0, atol=1e-15)
    np.testing.assert_array_equal(pairs.q, np.stack([col(j) for j in UPSTREAM_JOINTS], axis=1))
    np.testing.assert_array_equal(pairs.conditions["temperature"], col("measurement_temperature"))
    assert pairs.joint_names == UR10 and not pairs.position_only
    if spec.endswith("_a"):
        assert pairs.frame_id == "tracker_a"
        times = [dt.datetime.strptime(r[0], "%Y%m%d%H%M%S").replace(tzinfo=dt.UTC) for r in rows]
        np.testing.assert_array_equal(pairs.stamps, [round(t.timestamp()) * 10**9 for t in times])
    else:  # the spreadsheet-rounded stamps are not used: the row order is
        assert pairs.frame_id == "tracker_bc" and {r[0] for r in rows} == {"2,02011E+13"}
        start = dt.datetime(2020, 11, 1, tzinfo=dt.UTC).timestamp()
        np.testing.assert_array_equal(pairs.stamps, (round(start) + 7 * np.arange(40)) * 10**9)


def write_table(path: Path, header: list[str], rows: np.ndarray, sep: str = ",", decimal: str = ".") -> Path:
    lines = [sep.join(header)]
    for row in rows:
        lines.append(sep.join(repr(float(v)).replace(".", decimal) for v in row))
    path.write_text("\n".join(lines) + "\n")
    return path


def truth(n: int = 25, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.uniform(-3, 3, (n, 3)), se3.from_rotvec(rng.uniform(-2, 2, (n, 3)), rng.uniform(-3, 3, (n, 3)))


JOINTS = {"columns": ["a1", "a2", "a3"], "names": ["j1", "j2", "j3"], "unit": "rad"}
POSITION = {"columns": ["x", "y", "z"], "unit": "m"}
LAYOUT_M = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.08, 0.0], [0.02, 0.03, 0.05]])


def orientation_case(kind: str, T: np.ndarray) -> tuple[list[str], np.ndarray, dict, dict | None]:
    """Columns, values, the orientation section and the position section of one way to write the poses."""
    pos = T[:, :3, 3]
    rot = Rotation.from_matrix(T[:, :3, :3])
    if kind == "quaternion_wxyz":
        q = rot.as_quat()[:, [3, 0, 1, 2]] * np.where(np.arange(len(T)) % 2, -1.0, 1.0)[:, None]  # either sign
        spec = {"kind": "quaternion", "columns": ["qw", "qx", "qy", "qz"], "order": "wxyz"}
        return ["x", "y", "z", "qw", "qx", "qy", "qz"], np.hstack([pos, q]), spec, POSITION
    if kind == "quaternion_xyzw":
        spec = {"kind": "quaternion", "columns": ["qx", "qy", "qz", "qw"], "order": "xyzw"}
        return ["x", "y", "z", "qx", "qy", "qz", "qw"], np.hstack([pos, rot.as_quat()]), spec, POSITION
    if kind == "euler_extrinsic_rad":
        spec = {
            "kind": "euler",
            "columns": ["a", "b", "c"],
            "sequence": "ZYX",
            "convention": "extrinsic",
            "unit": "rad",
        }
        return ["x", "y", "z", "a", "b", "c"], np.hstack([pos, rot.as_euler("zyx")]), spec, POSITION
    if kind == "euler_intrinsic_deg_mm":
        angles = rot.as_euler("ZYZ", degrees=True)
        spec = {
            "kind": "euler",
            "columns": ["a", "b", "c"],
            "sequence": "zyz",
            "convention": "intrinsic",
            "unit": "deg",
        }
        return ["x", "y", "z", "a", "b", "c"], np.hstack([pos * 1e3, angles]), spec, {**POSITION, "unit": "mm"}
    if kind == "none":
        return ["x", "y", "z"], pos, {"kind": "none"}, POSITION
    assert kind == "points_mm"
    points = np.einsum("bij,kj->bki", T[:, :3, :3], LAYOUT_M) + pos[:, None]
    columns = [[f"p{k}{a}" for a in "xyz"] for k in range(len(LAYOUT_M))]
    spec = {
        "kind": "points",
        "unit": "mm",
        "points": [{"columns": c, "nominal": (1e3 * n).tolist()} for c, n in zip(columns, LAYOUT_M, strict=True)],
    }
    return [c for cols in columns for c in cols], 1e3 * points.reshape(len(T), -1), spec, None


@pytest.mark.parametrize(
    "kind", ["quaternion_wxyz", "quaternion_xyzw", "euler_extrinsic_rad", "euler_intrinsic_deg_mm", "none", "points_mm"]
)
def test_every_orientation_kind_gives_the_known_pose(tmp_path, kind):
    q, T = truth()
    columns, values, orientation, position = orientation_case(kind, T)
    deg = kind.endswith("_mm")  # joints in degrees in the same cases
    path = write_table(
        tmp_path / "t.csv", ["a1", "a2", "a3", *columns], np.hstack([np.degrees(q) if deg else q, values])
    )
    data = {"frame_id": "tracker", "joints": {**JOINTS, "unit": "deg" if deg else "rad"}, "orientation": orientation}
    if position is not None:
        data["position"] = position
    pairs = import_table(path, spec_from_dict(data, "test")).pairs
    np.testing.assert_allclose(pairs.q, q, rtol=0, atol=1e-12)
    np.testing.assert_allclose(pairs.T[:, :3, 3], T[:, :3, 3], rtol=0, atol=1e-12)
    if kind == "none":
        assert pairs.position_only and np.all(pairs.T[:, :3, :3] == np.eye(3))
    else:
        assert not pairs.position_only
        np.testing.assert_allclose(pairs.T[:, :3, :3], T[:, :3, :3], rtol=0, atol=1e-12)
    # a row-order stamp by default: one second apart from zero
    np.testing.assert_array_equal(pairs.stamps, np.arange(len(T)) * 10**9)


def test_joint_columns_by_name_or_model_order_are_checked_against_the_robot(tmp_path):
    q, T = truth(5)
    path = write_table(tmp_path / "t.csv", ["a1", "a2", "a3", "x", "y", "z"], np.hstack([q, T[:, :3, 3]]))
    base = {"frame_id": "f", "position": POSITION, "orientation": {"kind": "none"}}
    by_name = {**base, "joints": {"columns": {"j3": "a3", "j1": "a1", "j2": "a2"}, "unit": "rad"}}
    pairs = import_table(path, spec_from_dict(by_name), ("j1", "j2", "j3")).pairs
    assert pairs.joint_names == ("j1", "j2", "j3")
    np.testing.assert_array_equal(pairs.q, q)
    in_order = {**base, "joints": {"columns": ["a1", "a2", "a3"], "unit": "rad"}}
    assert import_table(path, spec_from_dict(in_order), ("r1", "r2", "r3")).pairs.joint_names == ("r1", "r2", "r3")
    with pytest.raises(DataError, match=r"nothing names the model's joints: give joints.names"):
        import_table(path, spec_from_dict(in_order))
    with pytest.raises(DataError, match=r"unknown \['j3'\], missing \['j4'\]"):
        import_table(path, spec_from_dict(by_name), ("j1", "j2", "j4"))
    with pytest.raises(DataError, match=r"joints.columns has 3 columns, the robot has 2 joints"):
        import_table(path, spec_from_dict(in_order), ("r1", "r2"))


def test_failed_rows_are_dropped_and_counted_by_reason(tmp_path):
    q, T = truth(10)
    quat = Rotation.from_matrix(T[:, :3, :3]).as_quat()
    rows = [
        ",".join(repr(float(v)) for v in [*q[i], *T[i, :3, 3], *quat[i], 1000 + i, 20 + i, i % 2])
        for i in range(len(T))
    ]
    fields = [r.split(",") for r in rows]
    fields[1][3] = ""  # the tracker lost the target: empty x
    fields[2][4] = "NaN"
    fields[3][3:10] = ["0"] * 7  # all-zero measurement
    fields[4][9] = "1.5"  # not a unit quaternion
    fields[5][10] = fields[0][10]  # the same stamp as row 0
    fields[6][11] = "nan"  # no temperature
    header = "a1,a2,a3,x,y,z,qx,qy,qz,qw,t,temp,part"
    path = tmp_path / "t.csv"
    path.write_text(header + "\n" + "\n".join(",".join(f) for f in fields) + "\n")
    data = {
        "frame_id": "f",
        "joints": JOINTS,
        "position": POSITION,
        "orientation": {"kind": "quaternion", "columns": ["qx", "qy", "qz", "qw"], "order": "xyzw"},
        "stamp": {"column": "t", "format": "seconds"},
        "conditions": {"temperature": "temp"},
    }
    result = import_table(path, spec_from_dict(data))
    assert result.rows == 10 and result.filtered == 0
    assert result.dropped == {
        "empty_field": 1,
        "nan": 2,
        "all_zero_measurement": 1,
        "non_unit_quaternion": 1,
        "duplicate_stamp": 1,
    }
    kept = [0, 7, 8, 9]
    np.testing.assert_allclose(result.pairs.T, T[kept], atol=1e-12)
    np.testing.assert_array_equal(result.pairs.stamps, (1000 + np.array(kept)) * 10**9)
    np.testing.assert_array_equal(result.pairs.conditions["temperature"], 20 + np.array(kept))
    # a row filter splits one file: rows of part 1 only; the others are filtered out, not failures (and row
    # 5 keeps its stamp: row 0, which had it first, is in the other part)
    half = import_table(path, spec_from_dict({**data, "filter": {"column": "part", "equals": 1}}))
    assert half.filtered == 5 and half.dropped == {"empty_field": 1, "all_zero_measurement": 1}
    np.testing.assert_array_equal(half.pairs.stamps, np.array([1000, 1007, 1009]) * 10**9)


def test_reflector_points_that_do_not_fit_the_layout_are_dropped(tmp_path):
    q, T = truth(6)
    columns, values, orientation, _ = orientation_case("points_mm", T)
    values[2, 3] += 5.0  # one reflector 5 mm off in one row
    path = write_table(tmp_path / "t.csv", ["a1", "a2", "a3", *columns], np.hstack([q, values]))
    data = {"frame_id": "f", "joints": JOINTS, "orientation": {**orientation, "max_residual": 0.5}}
    result = import_table(path, spec_from_dict(data))
    assert result.dropped == {"point_fit_residual": 1} and len(result.pairs) == 5
    bad = {**data, "orientation": {**orientation, "points": orientation["points"][:2]}}
    with pytest.raises(DataError, match=r"orientation.points needs three or more reflector points"):
        spec_from_dict(bad, "s.yaml")
    line = [{"columns": c["columns"], "nominal": [10.0 * i, 0, 0]} for i, c in enumerate(orientation["points"])]
    with pytest.raises(DataError, match="nominal layout is collinear"):
        spec_from_dict({**data, "orientation": {**orientation, "points": line}}, "s.yaml")


def test_text_export_with_preamble_whitespace_and_decimal_comma(tmp_path):
    q, T = truth(4)
    body = write_table(tmp_path / "b.txt", ["a1", "a2", "a3", "x", "y", "z"], np.hstack([q, T[:, :3, 3]]), "\t", ",")
    path = tmp_path / "t.txt"
    path.write_text("Exported by a tracker program\nunits: m\n" + body.read_text().replace("\n", "\n# note\n", 1))
    data = {
        "format": {"separator": "whitespace", "decimal": ",", "skip_lines": 2, "comment": "#"},
        "frame_id": "f",
        "joints": JOINTS,
        "position": POSITION,
        "orientation": {"kind": "none"},
    }
    pairs = import_table(path, spec_from_dict(data)).pairs
    np.testing.assert_allclose(pairs.T[:, :3, 3], T[:, :3, 3], atol=1e-15)


def test_malformed_file_errors_name_the_line_and_column(tmp_path):
    q, T = truth(4)
    path = write_table(tmp_path / "t.csv", ["a1", "a2", "a3", "x", "y", "z"], np.hstack([q, T[:, :3, 3]]))
    spec = spec_from_dict({"frame_id": "f", "joints": JOINTS, "position": POSITION, "orientation": {"kind": "none"}})
    lines = path.read_text().splitlines()
    lines[3] = lines[3].replace(",", ",1.2.3,", 1).rsplit(",", 1)[0]  # line 4, column 2 is not a number
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=r"t.csv: line 4, column 2 'a2': '1.2.3' is not a number"):
        import_table(path, spec)
    lines[3] = "1,2"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=r"t.csv: line 4: 2 fields, the header has 6"):
        import_table(path, spec)
    comma = spec_from_dict({"format": {"decimal": ",", "separator": ";"}, **spec_dict(spec)})
    with pytest.raises(DataError, match=r"line 1: no column 'a1' in the header"):
        import_table(path, comma)  # the whole header is one field with the wrong separator
    with pytest.raises(DataError, match="does not exist"):
        import_table(tmp_path / "none.csv", spec)


def spec_dict(spec) -> dict:
    return {"frame_id": spec.frame_id, "joints": JOINTS, "position": POSITION, "orientation": {"kind": "none"}}


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"orientation": {"kind": "eulr"}}, r"orientation.kind 'eulr' is not one of quaternion, euler, none, points"),
        ({"position": {"columns": ["x", "y", "z"], "unit": "inch"}}, r"position.unit 'inch' is not one of mm, m"),
        ({"position": {"columns": ["x", "y"], "unit": "m"}}, r"position.columns needs 3 columns"),
        (
            {"orientation": {"kind": "euler", "columns": ["a", "b", "c"], "sequence": "XXY", "unit": "deg"}},
            r"orientation.sequence 'XXY' is not an Euler sequence",
        ),
        ({"joints": {**JOINTS, "unit": "grad"}}, r"joints.unit 'grad' is not one of rad, deg"),
        ({"joints": {**JOINTS, "offset": 1}}, r"joints.offset is not a known key"),
        ({"format": {"separator": ",", "decimal": ","}}, r"format.decimal ',' is also the separator"),
        ({"stamp": {"column": "t", "format": "yyyymmdd"}}, r"stamp.format 'yyyymmdd' is not one of"),
        ({"stamp": {"period_s": -1}}, r"stamp.period_s '-1' must be a positive number"),
        ({"conditions": {"humidity": "h"}}, r"conditions.humidity is not a known condition"),
        ({"frame_id": ""}, r"frame_id is required"),
        ({"speed": 1}, r"'speed' is not a known section"),
    ],
)
def test_bad_spec_values_are_named(change, message):
    data = {"frame_id": "f", "joints": JOINTS, "position": POSITION, "orientation": {"kind": "none"}, **change}
    with pytest.raises(DataError, match=r"import spec s.yaml: .*" + message):
        spec_from_dict(data, "s.yaml")


def test_spec_extends_another_and_replaces_whole_sections(tmp_path):
    child = tmp_path / "child.yaml"
    child.write_text("extends: ipa_robot_accuracy_a\nframe_id: other\nstamp: {period_s: 2.0}\n")
    spec = spec_from_dict(load_spec_dict(child), str(child))
    assert spec.frame_id == "other" and spec.stamp_column is None and spec.stamp_period_s == 2.0
    assert spec.euler_sequence == "XYZ" and spec.decimal == ","
    with pytest.raises(
        DataError, match=r"import spec nothing_here does not exist .shipped specs: ipa_robot_accuracy_a"
    ):
        load_spec_dict("nothing_here")
