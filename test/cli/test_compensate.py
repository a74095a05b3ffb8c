"""hybrid-kinematics compensate: a plan CSV to the corrected trajectory CSV."""

from __future__ import annotations

import numpy as np

from hybrid_kinematics_ros.cli.common import read_csv, write_csv
from hybrid_kinematics_ros.cli.main import main
from test.ik.test_compensate import A, B, errors_against_plan, plan


def test_compensate_writes_the_corrected_trajectory(trained, tmp_path, capsys):
    path, model = trained[0], trained[1]
    names = list(model.joint_names)
    t, q, qd, _ = plan(A, B, n=100)
    plan_csv = tmp_path / "plan.csv"
    write_csv(plan_csv, ["time_from_start", *names, *(f"{n}_velocity" for n in names)], np.hstack([t[:, None], q, qd]))
    out = tmp_path / "corrected.csv"
    assert main(["compensate", "--model", str(path), "--joints", str(plan_csv), "--out", str(out)]) == 0
    assert "wrote 100 corrected points" in capsys.readouterr().out
    header, values = read_csv(out)
    assert header[: 1 + 2 * len(names)] == ["time_from_start", *names, *(f"{n}_velocity" for n in names)]
    np.testing.assert_array_equal(values[:, 0], t)
    corrected = values[:, 1 : 1 + len(names)]
    pos, _ = errors_against_plan(model, corrected, q)
    assert pos.max() < 1e-5 and np.abs(corrected - q).max() > 1e-5
    assert values[:, header.index("in_calibrated_range")].min() == 1.0


def test_compensate_refuses_with_one_line_naming_the_point(trained, tmp_path, capsys):
    path, model = trained[0], trained[1]
    j = int(np.argmax(model.chain.upper - model.trained_upper))
    a, b = A.copy(), A.copy()
    a[j], b[j] = model.trained_upper[j] - 0.1, 0.5 * (model.trained_upper[j] + model.chain.upper[j])
    t, q, _, _ = plan(a, b, n=50)
    plan_csv = tmp_path / "plan.csv"
    write_csv(plan_csv, ["time_from_start", *model.joint_names], np.hstack([t[:, None], q]))
    out = tmp_path / "corrected.csv"
    argv = ["compensate", "--model", str(path), "--joints", str(plan_csv), "--out", str(out)]
    assert main([*argv, "--out-of-range", "refuse"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "outside the calibrated range" in err[0] and str(plan_csv) in err[0], err
    assert "(line " in err[0] and not out.exists()
