"""``hybrid-kinematics ik``: solutions through the hybrid model, with their error bounds and ranked by them."""

from __future__ import annotations

import numpy as np

from hybrid_kinematics_ros.cli.main import main
from hybrid_kinematics_ros.kinematics import se3


def _poses_csv(path, T):
    position, quat = se3.pose_from_matrix(T)
    rows = np.hstack([position, quat])
    path.write_text("x,y,z,qx,qy,qz,qw\n" + "\n".join(",".join(repr(float(v)) for v in r) for r in rows) + "\n")


def test_ik_solutions_carry_bounds_and_rank_by_them(shoulder_model, tmp_path, capsys):
    # a model trained with the shoulder in [-2, -1] rad and the elbow in [0.5, 2]: the other branches lie beyond
    model_dir, model = shoulder_model[0], shoulder_model[1]
    q = np.array([[0.3, -1.2, 1.3, -0.9, 1.1, 0.2], [-0.5, -1.6, 1.0, -1.2, -0.8, 0.4]])
    T = model.fk(q)
    poses = tmp_path / "poses.csv"
    _poses_csv(poses, T)
    out = tmp_path / "solutions.csv"
    args = ["ik", "--model", str(model_dir), "--poses", str(poses), "--out", str(out), "--solutions", "4"]
    assert main([*args, "--rank-by-bound"]) == 0
    header = out.read_text().splitlines()[0].split(",")
    assert header[-2:] == ["position_bound_mm", "orientation_bound_deg"]
    text = np.genfromtxt(out, delimiter=",", skip_header=1, dtype=str)
    rows = text[:, :-3].astype(float)
    bounds = text[:, -2:].astype(float)
    assert set(text[:, header.index("success")]) == {"true"}
    spreads = []
    for i in range(len(q)):
        mine = rows[:, 0] == i
        assert mine.sum() >= 2  # several branches reach each target
        solutions = rows[mine, 2:8]
        pos, rot = se3.pose_errors(model.fk(solutions), np.repeat(T[i : i + 1], len(solutions), axis=0))
        assert np.all(pos < 1e-3) and np.all(rot < 1e-3)
        position, orientation = model.error_bounds(solutions)  # at the CSV's rounded joints: rtol 1e-6
        np.testing.assert_allclose(bounds[mine, 0], 1e3 * position, rtol=1e-6)
        np.testing.assert_allclose(bounds[mine, 1], np.degrees(orientation), rtol=1e-6)
        assert np.all(np.diff(bounds[mine, 0]) >= 0)  # the branch the model knows best first
        spreads.append(np.ptp(bounds[mine, 0]))
    assert max(spreads) > 0  # branches beyond the trained range carry wider bounds, so the order is a choice
    capsys.readouterr()
    assert main([*args, "--bounds", "--analytic"]) == 2
    assert "--bounds: --analytic answers carry none" in capsys.readouterr().err
