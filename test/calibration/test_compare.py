"""Two calibrations side by side: a parameter moved beyond its σ is flagged and shows in the tip difference; a
model against itself moves nothing; both are verified on a shared check; bad pairs of models are refused."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from hybrid_kinematics_ros.calibration.compare import CHANGE_SIGMAS, compare
from hybrid_kinematics_ros.io.pairs import write_pairs
from hybrid_kinematics_ros.model.hybrid import HybridModel
from test.cli.inprocess import cli


@pytest.fixture(scope="module")
def moved(shoulder_model, tmp_path_factory):
    """The shoulder model with one joint's zero offset moved by 20 of its σ (a re-mastered joint), and which."""
    model_dir, *_ = shoulder_model
    out = tmp_path_factory.mktemp("moved") / "model"
    shutil.copytree(model_dir, out)
    manifest = json.loads((out / "model.json").read_text())
    entry = next(p for p in manifest["parametric"]["parameters"] if p["kind"] == "zero" and "sigma" in p)
    entry["value"] += 20 * entry["sigma"]
    (out / "model.json").write_text(json.dumps(manifest))
    return out, entry["name"]


def test_a_moved_zero_offset_is_flagged_and_moves_the_tip(shoulder_model, moved):
    model_dir, model, *_ = shoulder_model
    result = compare(model, HybridModel.load(moved[0]), count=500)
    assert [p["name"] for p in result.flagged] == [moved[1]]
    assert result.flagged[0]["sigmas"] == pytest.approx(20 / np.sqrt(2), rel=1e-6)  # two equal σ in quadrature
    assert result.tip_stats()["position_mm_max"] > 0.0
    same = compare(model, HybridModel.load(model_dir), count=500)
    assert not same.flagged and same.tip_stats()["position_mm_max"] < 1e-9
    assert all(p["sigmas"] <= CHANGE_SIGMAS for p in same.parameters)


def test_the_cli_verifies_both_on_a_check_and_writes_json_and_a_page(shoulder_model, moved, tmp_path):
    model_dir, _, te, _ = shoulder_model
    bag = tmp_path / "check"
    write_pairs(bag, te)
    out, report = tmp_path / "page", tmp_path / "compare.json"
    args = ["compare", str(model_dir), str(moved[0]), "--bag", str(bag), "--json", str(report), "--out", str(out)]
    result = cli(*args)
    assert result.returncode == 0, result.stderr
    assert moved[1] in result.stdout and "tip difference" in result.stdout
    data = json.loads(report.read_text())
    assert [p["name"] for p in data["parameters"] if p["flagged"]] == [moved[1]]
    assert set(data["checks"]) == {"A", "B"}
    assert data["checks"]["B"]["position_mm_mean"] > data["checks"]["A"]["position_mm_mean"]
    assert (out / "tip_difference.png").stat().st_size > 5000 and "flagged" in (out / "index.html").read_text()


def test_models_of_ranges_that_do_not_overlap_are_compared_by_their_stages(shoulder_model, tmp_path):
    model_dir, *_ = shoulder_model
    elsewhere = tmp_path / "elsewhere"
    shutil.copytree(model_dir, elsewhere)
    manifest = json.loads((elsewhere / "model.json").read_text())
    manifest["trained_range"]["lower"][0] = manifest["trained_range"]["upper"][0] + 0.5
    manifest["trained_range"]["upper"][0] += 1.0
    (elsewhere / "model.json").write_text(json.dumps(manifest))
    result = compare(HybridModel.load(model_dir), HybridModel.load(elsewhere), count=200)
    assert result.apart == ("shoulder_pan_joint",)
    assert result.tip_stats()["position_mm_max"] < 1e-9  # the same stage: the nets are not compared
    assert "the parametric stages alone" in " ".join(result.lines())


def test_models_of_other_joints_get_one_line_and_exit_2(shoulder_model, tmp_path):
    model_dir, *_ = shoulder_model
    other = tmp_path / "other"
    shutil.copytree(model_dir, other)
    manifest = json.loads((other / "model.json").read_text())
    manifest["joint_names"] = [f"{name}_renamed" for name in manifest["joint_names"]]
    (other / "model.json").write_text(json.dumps(manifest))
    result = cli("compare", str(model_dir), str(other))
    assert result.returncode == 2 and len(result.stderr.strip().splitlines()) == 1, result.stderr
