"""``hybrid-kinematics import`` through the console entry point: the shipped spec on the real data's excerpt,
the same spec given by flags, and one-line errors for a malformed file and a bad spec."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hybrid_kinematics_ros.cli.main import main
from hybrid_kinematics_ros.io.pairs import read_pairs
from hybrid_kinematics_ros.kinematics import se3
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from test.cli.inprocess import cli

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures" / "ipa-robot-accuracy"
SERIES_A = FIXTURES / "Series_A_measurements_grid_head40.csv"
UR10 = load_robot_config("ur10").chain.joint_names


def run(*args):
    return subprocess.run(["hybrid-kinematics", *args], capture_output=True, text=True, check=False)


def test_import_with_the_shipped_spec_or_the_same_by_flags(tmp_path, capsys):
    result = run(
        "import",
        "--spec",
        "ipa_robot_accuracy_a",
        "--robot",
        "ur10",
        "--csv",
        str(SERIES_A),
        "--out",
        str(tmp_path / "a"),
    )
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout.strip().splitlines()[-1])
    assert (summary["rows"], summary["imported"], summary["dropped"]) == (40, 40, {})
    assert summary["frame_id"] == "tracker_a" and summary["conditions"] == ["temperature"]
    assert "imported 40 of 40 rows" in result.stderr
    pairs = read_pairs(tmp_path / "a", UR10)
    header = SERIES_A.read_text().splitlines()[0].split(";")
    raw = [line.split(";") for line in SERIES_A.read_text().splitlines()[1:]]
    temperature = [float(r[header.index("measurement_temperature")].replace(",", ".")) for r in raw]
    np.testing.assert_array_equal(pairs.conditions["temperature"], temperature)

    # the same spec from flags alone, with another station's frame
    flags = [
        "import",
        "--csv",
        str(SERIES_A),
        "--separator",
        ";",
        "--decimal",
        ",",
        "--frame-id",
        "tracker_x",
        "--joints",
        "shoulder_pan_joint,shoulder_lift_joint,elbow_joint,wrist_1_joint,wrist_2_joint,wrist_3_joint",
        "--joint-names",
        ",".join(UR10),
        "--joint-unit",
        "rad",
        "--position",
        "measurement_x,measurement_y,measurement_z",
        "--position-unit",
        "mm",
        "--orientation",
        "euler",
        "--euler",
        "measurement_rx,measurement_ry,measurement_rz",
        "--euler-sequence",
        "XYZ",
        "--euler-convention",
        "intrinsic",
        "--angle-unit",
        "deg",
        "--condition",
        "temperature=measurement_temperature",
    ]
    stamp = ["--stamp-column", "Timestamp", "--stamp-format", "%Y%m%d%H%M%S"]
    assert main([*flags, *stamp, "--out", str(tmp_path / "flags")]) == 0
    by_flags = read_pairs(tmp_path / "flags", UR10)
    assert by_flags.frame_id == "tracker_x"
    for name in ("q", "T", "stamps"):
        np.testing.assert_array_equal(getattr(by_flags, name), getattr(pairs, name))
    np.testing.assert_array_equal(by_flags.conditions["temperature"], temperature)
    # a file whose timestamps are unusable: the row order stamps it
    assert main([*flags, "--stamp-period", "7", "--stamp-start", "100", "--out", str(tmp_path / "rows")]) == 0
    np.testing.assert_array_equal(read_pairs(tmp_path / "rows").stamps, (100 + 7 * np.arange(40)) * 10**9)
    capsys.readouterr()


def one_line_error(result) -> str:
    assert result.returncode == 2, result.stdout + result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    return lines[0]


def test_malformed_file_and_bad_spec_end_with_one_line(tmp_path):
    lines = SERIES_A.read_bytes().decode().split("\r\n")
    header = lines[0].split(";")
    fields = lines[6].split(";")  # line 7 of the file
    column = header.index("measurement_x")
    fields[column] = "2361,98x"
    lines[6] = ";".join(fields)
    bad = tmp_path / "bad.csv"
    bad.write_bytes("\r\n".join(lines).encode())
    args = ["import", "--spec", "ipa_robot_accuracy_a", "--robot", "ur10", "--out", str(tmp_path / "out")]
    line = one_line_error(cli(*args, "--csv", str(bad)))
    assert f"bad.csv: line 7, column {column + 1} 'measurement_x': '2361,98x' is not a number" in line
    assert not (tmp_path / "out").exists()

    line = one_line_error(cli(*args, "--csv", str(SERIES_A), "--position", "measurement_x,measurement_y,z_mm"))
    assert "Series_A_measurements_grid_head40.csv: line 1: no column 'z_mm' in the header" in line

    spec = tmp_path / "spec.yaml"
    position = "{columns: [measurement_x, measurement_y, measurement_z], unit: inch}"
    spec.write_text(f"extends: ipa_robot_accuracy_a\nposition: {position}\n")
    line = one_line_error(cli(*args[:2], str(spec), *args[3:], "--csv", str(SERIES_A)))
    assert line.endswith(f"import spec {spec} with flags: position.unit 'inch' is not one of mm, m")


def test_reflector_points_quaternions_and_a_row_filter_by_flags(tmp_path, capsys):
    rng = np.random.default_rng(2)
    q = rng.uniform(-3, 3, (8, 3))
    T = se3.from_rotvec(rng.uniform(-2, 2, (8, 3)), rng.uniform(-3, 3, (8, 3)))
    layout_mm = np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [0.0, 80.0, 0.0]])
    points = np.einsum("bij,kj->bki", T[:, :3, :3], layout_mm) + 1e3 * T[:, None, :3, 3]
    quat = Rotation.from_matrix(T[:, :3, :3]).as_quat()[:, [3, 0, 1, 2]]
    part = np.arange(8) % 2
    header = "a1,a2,a3," + ",".join(f"p{k}{a}" for k in range(3) for a in "xyz") + ",x,y,z,qw,qx,qy,qz,part"
    table = np.hstack([q, points.reshape(8, 9), 1e3 * T[:, :3, 3], quat, part[:, None]])
    path = tmp_path / "t.csv"
    path.write_text(header + "\n" + "\n".join(",".join(repr(float(v)) for v in row) for row in table) + "\n")
    common = ["import", "--csv", str(path), "--frame-id", "f", "--joints", "j1=a1,j2=a2,j3=a3", "--joint-unit", "rad"]
    common += ["--filter", "part=1"]
    point_flags = [f"p{k}x,p{k}y,p{k}z=" + ",".join(str(v) for v in layout_mm[k]) for k in range(3)]
    by_points = [*common, "--orientation", "points", "--point-unit", "mm", "--out", str(tmp_path / "points")]
    assert main([*by_points, *(f for p in point_flags for f in ("--point", p))]) == 0
    by_quat = [*common, "--position", "x,y,z", "--position-unit", "mm", "--orientation", "quaternion"]
    assert (
        main([*by_quat, "--quaternion", "qw,qx,qy,qz", "--quaternion-order", "wxyz", "--out", str(tmp_path / "q")]) == 0
    )
    summaries = [json.loads(line) for line in capsys.readouterr().out.strip().splitlines()]
    assert [(s["imported"], s["filtered_out"]) for s in summaries] == [(4, 4), (4, 4)]
    for bag in ("points", "q"):
        pairs = read_pairs(tmp_path / bag, ("j1", "j2", "j3"))
        np.testing.assert_allclose(pairs.T, T[part == 1], rtol=0, atol=1e-12)
        np.testing.assert_array_equal(pairs.q, q[part == 1])


def test_the_reflectors_scatter_gives_the_trackers_floor_and_the_bag_keeps_it(tmp_path, capsys):
    """Four reflectors measured with 20 µm of noise each: the import estimates that noise from how far each
    row leaves the rigid layout, and the floor it reports is what that noise does to the pose's origin."""
    rows, sigma_mm = 400, 0.02
    rng = np.random.default_rng(4)
    T = se3.from_rotvec(rng.uniform(-2, 2, (rows, 3)), rng.uniform(-1, 1, (rows, 3)))
    layout_mm = np.array([[0.0, 0.0, 0.0], [150.0, 0.0, 0.0], [130.0, 90.0, 0.0], [20.0, 100.0, 5.0]])
    points = np.einsum("bij,kj->bki", T[:, :3, :3], layout_mm) + 1e3 * T[:, None, :3, 3]
    points += rng.normal(0.0, sigma_mm, points.shape)
    header = "a1,a2,a3," + ",".join(f"p{k}{a}" for k in range(4) for a in "xyz")
    table = np.hstack([rng.uniform(-3, 3, (rows, 3)), points.reshape(rows, 12)])
    path = tmp_path / "t.csv"
    path.write_text(header + "\n" + "\n".join(",".join(repr(float(v)) for v in row) for row in table) + "\n")
    flags = ["import", "--csv", str(path), "--frame-id", "f", "--joints", "j1=a1,j2=a2,j3=a3", "--joint-unit", "rad"]
    flags += ["--orientation", "points", "--point-unit", "mm", "--out", str(tmp_path / "pairs")]
    for k in range(4):
        flags += ["--point", f"p{k}x,p{k}y,p{k}z=" + ",".join(str(v) for v in layout_mm[k])]
    assert main(flags) == 0
    floor = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["tracker_floor"]
    # what 20 µm per reflector does to the fitted pose, simulated here apart from the importer
    noisy = layout_mm + np.random.default_rng(9).normal(0.0, sigma_mm, (20_000, 4, 3))
    fitted, _ = se3.fit_rigid(layout_mm, noisy)
    expected_mm = np.linalg.norm(fitted[:, :3, 3], axis=1).mean()
    expected_deg = np.degrees(se3.rotation_angle(fitted[:, :3, :3])).mean()
    assert abs(floor["position_mm"] / expected_mm - 1.0) < 0.1
    assert abs(floor["orientation_deg"] / expected_deg - 1.0) < 0.1
    pairs = read_pairs(tmp_path / "pairs", ("j1", "j2", "j3"))
    assert pairs.floor is not None and np.isclose(1e3 * pairs.floor[0], floor["position_mm"])
    assert read_pairs(tmp_path / "pairs", ("j1", "j2", "j3")).subset(np.arange(10)).floor == pairs.floor


def test_the_trackers_uncertainty_columns_give_its_floor(tmp_path, capsys):
    """An export with the tracker's uncertainty per position (twice the standard deviation, one column for every
    axis or one per axis): the floor is the mean length of errors of that size."""
    rows = 200
    rng = np.random.default_rng(6)
    table = np.hstack([rng.uniform(-3, 3, (rows, 3)), rng.uniform(-1000, 1000, (rows, 3))])
    sigma_mm = rng.uniform(0.005, 0.015, rows)  # a tracker's uncertainty grows with the distance
    header = "a1,a2,a3,x,y,z,u,ux,uy,uz"
    table = np.hstack([table, 2 * sigma_mm[:, None], 2 * sigma_mm[:, None] * [1.0, 1.0, 0.0]])
    path = tmp_path / "t.csv"
    path.write_text(header + "\n" + "\n".join(",".join(repr(float(v)) for v in row) for row in table) + "\n")
    flags = ["import", "--csv", str(path), "--frame-id", "f", "--joints", "j1=a1,j2=a2,j3=a3", "--joint-unit", "rad"]
    flags += ["--position", "x,y,z", "--position-unit", "mm", "--orientation", "none", "--uncertainty-coverage", "2"]
    assert main([*flags, "--position-uncertainty", "u", "--out", str(tmp_path / "one")]) == 0
    assert main([*flags, "--position-uncertainty", "ux,uy,uz", "--out", str(tmp_path / "three")]) == 0
    one, three = (json.loads(line)["tracker_floor"] for line in capsys.readouterr().out.strip().splitlines())
    # the mean length of a 3-D Gaussian error of σ per axis is σ √(8/π); of a 2-D one, σ √(π/2)
    assert one["position_mm"] == pytest.approx(np.mean(sigma_mm) * np.sqrt(8 / np.pi), rel=0.03)
    assert three["position_mm"] == pytest.approx(np.mean(sigma_mm) * np.sqrt(np.pi / 2), rel=0.03)
    assert one["orientation_deg"] is None
    assert read_pairs(tmp_path / "three", ("j1", "j2", "j3")).floor[0] == pytest.approx(1e-3 * three["position_mm"])
