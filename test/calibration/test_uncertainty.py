"""Each identified parameter's σ, the condition number and the most correlated pairs: σ is the spread between
calibrations on new poses, and it narrows as the poses grow."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hybrid_kinematics_ros.calibration.parametric import identify
from hybrid_kinematics_ros.io.pairs import write_pairs
from hybrid_kinematics_ros.simulation.cell import VirtualCell
from hybrid_kinematics_ros.simulation.sampling import sample_joints
from test.cli.inprocess import cli


@pytest.fixture(scope="module")
def cell(ur10):
    return VirtualCell.from_config(ur10, seed=3)


def _fit(cell, count: int, seed: int):
    cfg = cell.config
    pairs = cell.pairs(sample_joints(cfg.chain, count, np.random.default_rng(seed)), seed=seed)
    return identify(
        cfg.chain, pairs.q, pairs.T, cfg.payload_mass, cfg.payload_com, harmonics=0, map_step=0.0, seed=seed
    )


def test_sigma_is_the_spread_between_calibrations_on_new_poses(cell):
    fits = [_fit(cell, 800, seed) for seed in range(8)]
    fitted = np.all([f.identifiable for f in fits], axis=0)
    spread = np.std([f.values[fitted] for f in fits], axis=0, ddof=1)
    sigma = np.mean([f.uncertainty.sigma[fitted] for f in fits], axis=0)
    ratio = np.median(spread / sigma)
    assert 0.5 < ratio < 2.0, ratio


def test_sigma_narrows_as_the_square_root_of_the_poses_and_is_absent_where_nothing_was_fitted(cell):
    few, many = _fit(cell, 500, 11), _fit(cell, 2000, 11)
    both = few.identifiable & many.identifiable
    ratio = np.median(many.uncertainty.sigma[both] / few.uncertainty.sigma[both])
    assert 0.35 < ratio < 0.65, ratio  # four times the poses: half the σ
    entries = many.manifest()["parameters"]
    assert all(("sigma" in e) == e["identifiable"] for e in entries)
    assert all(e["sigma"] > 0 for e in entries if e["identifiable"])


def test_the_most_correlated_pairs_come_first_and_name_the_chains_parameters(cell):
    result = _fit(cell, 500, 12)
    section = result.manifest()["uncertainty"]
    correlations = [abs(c["correlation"]) for c in section["correlated"]]
    assert correlations == sorted(correlations, reverse=True) and all(c <= 1.0 + 1e-9 for c in correlations)
    names = {p.name for p in result.params}
    assert all({c["a"], c["b"]} <= names for c in section["correlated"])
    assert section["condition_number"] >= 1.0


def test_the_model_and_its_report_carry_each_parameters_sigma(shoulder_model, tmp_path):
    model_dir, _, te, _ = shoulder_model
    section = json.loads((model_dir / "model.json").read_text())["parametric"]
    assert section["uncertainty"]["condition_number"] >= 1.0
    assert any("sigma" in p for p in section["parameters"])
    bag = tmp_path / "held_out"
    write_pairs(bag, te)
    result = cli("report", "--model", str(model_dir), "--bag", str(bag), "--out", str(tmp_path / "report"))
    assert result.returncode == 0, result.stderr
    page = (tmp_path / "report" / "index.html").read_text()
    assert "<th>σ</th>" in page and "Condition number" in page and "Most correlated" in page
