"""The HTML accuracy report, rendered by a real browser (Debian's Chromium, headless)."""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
import pytest
from PIL import Image

from hybrid_kinematics_ros.calibration.report import iso9283
from hybrid_kinematics_ros.io.pairs import Pairs, write_pairs
from hybrid_kinematics_ros.simulation.cell import VirtualCell


@pytest.fixture(scope="module")
def test_bag(ur10, trained, tmp_path_factory):
    """Random test poses plus 8 poses measured 6 times each (ISO 9283 cycles), with tracker noise."""
    cell = VirtualCell.from_config(ur10, noise=True)
    rng = np.random.default_rng(11)
    q = np.vstack([trained[3].q[:300], np.repeat(trained[3].q[300:308], 6, axis=0)])
    T = cell.measure(q, rng)
    path = tmp_path_factory.mktemp("report") / "test_bag"
    write_pairs(path, Pairs(q, T, 10**9 + 10**6 * np.arange(len(q)), ur10.chain.joint_names, "base_link"))
    return path, Pairs(q, T, np.arange(len(q)), ur10.chain.joint_names, "base_link")


def test_iso9283_accuracy_and_repeatability(trained, test_bag):
    model = trained[1]
    entries = iso9283(model, test_bag[1])
    assert len(entries) == 8 and all(e["repeats"] == 6 for e in entries)
    for e in entries:
        assert e["AP_hybrid_mm"] < e["AP_analytic_mm"] / 3  # the calibration shows in AP
        assert 0.005 < e["RP_mm"] < 0.2  # 15 µm per-axis tracker noise: RP ≈ l̄ + 3 s ≈ 0.05 mm


def test_report_renders_in_chromium(trained, test_bag, tmp_path):
    out = tmp_path / "report"
    result = subprocess.run(
        ["hybrid-kinematics", "report", "--model", str(trained[0]), "--bag", str(test_bag[0]), "--out", str(out)],
        capture_output=True,
        text=True,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    page = out / "index.html"
    for png in ("position_error_distribution.png", "orientation_error_distribution.png", "workspace.png"):
        assert (out / png).stat().st_size > 5000
    browser = shutil.which("chromium")
    assert browser, "chromium is not installed: run make bootstrap (it installs Debian's chromium)"
    flags = ["--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars"]
    dom = subprocess.run(
        [browser, *flags, "--dump-dom", page.as_uri()], capture_output=True, text=True, timeout=120, check=True
    ).stdout
    for heading in ("Errors before and after calibration", "ISO 9283", "Referencing", "Parametric stage"):
        assert heading in dom
    assert dom.count("<img") == 3 and dom.count("<tr>") > 8 + 3
    shot = tmp_path / "shot.png"
    subprocess.run(
        [browser, *flags, f"--screenshot={shot}", "--window-size=1200,1600", page.as_uri()],
        capture_output=True,
        timeout=120,
        check=True,
    )
    image = np.asarray(Image.open(shot).convert("RGB"))
    assert image.shape[:2] == (1600, 1200)
    # the histograms drew: the plots' orange and blue bars are on screen, not just black text on white
    colours = {tuple(c) for c in image.reshape(-1, 3)[::7]}
    assert len(colours) > 100
    orange = np.all(np.abs(image.astype(int) - [255, 127, 14]) < 40, axis=2)
    assert orange.sum() > 500


def test_iso9283_groups_repeated_poses_read_by_real_encoders(ur10):
    """Readings of one commanded pose differ by encoder noise and quantisation (20 bits); grouping by
    joints equal to 1e-6 rad found no repeated pose at all."""
    from hybrid_kinematics_ros.model.hybrid import HybridModel

    rng = np.random.default_rng(5)
    chain = ur10.chain
    commanded = np.vstack([rng.uniform(-2, 2, (300, chain.dof)), np.repeat(rng.uniform(-2, 2, (8, chain.dof)), 6, 0)])
    step = 2 * np.pi / 2**20
    q = np.round((commanded + rng.normal(0, 2e-6, commanded.shape)) / step) * step
    T = VirtualCell.from_config(ur10, noise=True).measure(commanded, rng)
    entries = iso9283(HybridModel.analytic_only(chain), Pairs(q, T, np.arange(len(q)), chain.joint_names, "base_link"))
    assert len(entries) == 8 and all(e["repeats"] == 6 for e in entries)
