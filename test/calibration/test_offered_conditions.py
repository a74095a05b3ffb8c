"""Condition channels offered, not named: each net takes them only where its validation errors are
significantly better with them, and a channel that no net takes leaves the model's inputs."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from hybrid_kinematics_ros.calibration import train
from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.calibration.evaluate import evaluate
from hybrid_kinematics_ros.calibration.fit import fit, split
from hybrid_kinematics_ros.calibration.nets import InputSpan, ResidualNet
from hybrid_kinematics_ros.calibration.report import _capacity_section
from hybrid_kinematics_ros.model.hybrid import HybridModel
from test.conftest import EXPANSION_PER_K, THERMAL_STAGE, thermal_pairs


def _job(drift_per_unit: float) -> train.NetJob:
    """Six joints and one condition column: a smooth error of joint 2 plus ``drift_per_unit`` times the
    condition (m per unit), which no function of the joints predicts."""
    rng = np.random.default_rng(0)

    def inputs(count: int) -> np.ndarray:
        return np.column_stack([rng.uniform(-2.0, 2.0, (count, 6)), rng.uniform(-1.0, 1.0, count)])

    def residual(x: np.ndarray) -> np.ndarray:
        joints = 1e-4 * np.column_stack([np.sin(2 * x[:, 1]), np.cos(x[:, 1]), np.sin(x[:, 1] + x[:, 2])])
        return joints + drift_per_unit * x[:, 6:7] * np.array([1.0, -0.5, 0.5])

    x_train, x_val = inputs(600), inputs(200)
    preset = replace(train.PRESETS["fast"], arch="mlp:32x2:silu", batch=64, max_epochs=60, ensemble=1)
    lower, upper = np.r_[np.full(6, -2.0), -1.0], np.r_[np.full(6, 2.0), 1.0]
    return train.NetJob(
        "position",
        preset,
        x_train,
        residual(x_train),
        x_val,
        residual(x_val),
        lower,
        upper,
        None,
        120.0,
        0,
        6,
        offered=(6,),
        offered_label="temperature",
    )


def _reads_the_channel(net: ResidualNet, x: np.ndarray) -> bool:
    moved = x.copy()
    moved[:, 6] = -moved[:, 6]
    with torch.no_grad():
        return not torch.equal(net(torch.tensor(x)), net(torch.tensor(moved)))


def test_a_channel_that_explains_the_error_is_taken():
    job = _job(1e-4)
    net, history = train.train_net(job)
    last = history[-1]
    assert last["takes_offered"] and last["offered"] == "temperature"
    rungs = {size["arch"]: size for size in last["sizes"]}
    with_it, without = rungs["mlp:32x2:silu + temperature"], rungs["mlp:32x2:silu"]
    assert with_it["kept"] and with_it["crossed_val_mm"] < 0.5 * without["crossed_val_mm"]
    assert _reads_the_channel(net, job.q_val)
    # the ladder's entries of the net served read the channel; fit's manifest counts those epochs alone
    assert any(e.get("reads_offered") for e in history) and not history[0].get("reads_offered")


def test_a_channel_that_explains_nothing_is_left_out():
    job = _job(0.0)
    net, history = train.train_net(job)
    assert history[-1]["takes_offered"] is False
    (rung,) = [s for s in history[-1]["sizes"] if s["arch"] == "mlp:32x2:silu + temperature"]
    assert rung["crossed_val_mm"] is not None and not rung["kept"]  # tried and judged, not taken
    assert not _reads_the_channel(net, job.q_val)  # its half span is infinite: the column enters as zero


def test_a_column_no_net_reads_can_leave_its_input():
    torch.manual_seed(0)
    lower, upper = np.r_[np.full(6, -3.0), 15.0, 0.0], np.r_[np.full(6, 3.0), 30.0, 1.0]
    x = np.column_stack([np.random.default_rng(1).uniform(-3, 3, (50, 6)), np.full(50, 22.0), np.full(50, 0.3)])
    zero, one = np.zeros(3), np.ones(3)
    for members in (1, 3):
        net = ResidualNet("mlp:16x2:silu", InputSpan(lower, upper, 6, (6,)), (zero, one), members=members)
        before = net(torch.tensor(x)).detach()
        net.drop_inputs((6,))
        narrow = torch.tensor(np.delete(x, 6, axis=1))
        torch.testing.assert_close(net(narrow).detach(), before, rtol=0, atol=1e-15)
        assert net.center.shape == (7,) and torch.jit.script(net)(narrow).shape == (50, 3)
    with pytest.raises(CalibrationError, match="only condition columns the net ignores"):
        net.drop_inputs((6,))  # the other condition column is read
    with pytest.raises(CalibrationError, match="only condition columns"):
        ResidualNet("mlp:16x2:silu", InputSpan(lower, upper, 6, (2,)), (np.zeros(3), np.ones(3)))


def test_fit_offers_the_channels_the_pairs_carry(ur10, tmp_path):
    """The temperature that grows the arm is taken where it counts; a channel of noise, on a cell that does not
    grow, is taken by no net and leaves the model's inputs, which then need no value for it."""
    pairs, test = thermal_pairs(ur10, 2000, seed=1), thermal_pairs(ur10, 300, seed=2)
    tr, va, _ = split(pairs, seed=0)
    _, manifest = fit(ur10.chain, tr, va, test, tmp_path / "thermal", THERMAL_STAGE)
    offer = manifest["offered_conditions"]
    assert offer["channels"] == ["temperature"] and "position" in offer["taken_by"]
    thermal = HybridModel.load(tmp_path / "thermal")
    assert thermal.condition_names == ("temperature",)
    errors = evaluate(thermal, test)
    assert errors["hybrid"]["position_mm_mean"] < 0.25 * errors["parametric"]["position_mm_mean"]

    def cold(p):  # the same cell without the growth, and a humidity channel that explains nothing
        T = p.T.copy()
        T[:, :3, 3] /= (1.0 + EXPANSION_PER_K * (p.conditions["temperature"] - 23.0))[:, None]
        humidity = np.random.default_rng(len(p)).uniform(30.0, 60.0, len(p))
        return replace(p, T=T, conditions={"humidity": humidity})

    tr, va, _ = split(cold(pairs), seed=0)
    _, manifest = fit(ur10.chain, tr, va, cold(test), tmp_path / "plain", THERMAL_STAGE)
    assert manifest["offered_conditions"] == {"channels": ["humidity"], "taken_by": []}
    plain = HybridModel.load(tmp_path / "plain")
    assert plain.condition_names == () and "conditions" not in plain.manifest
    assert all(net.center.shape == (6,) for net in plain.nets.values())
    without = replace(cold(test), conditions={})  # no humidity wanted
    assert evaluate(plain, without)["hybrid"]["position_mm_mean"] < 0.05


def test_the_report_marks_the_rung_served_with_the_channel_taken():
    """An ensemble fixed by --members trains every rung as an ensemble, so no rung carries its ``xK``: the row
    served is the size with the channel it took, not the size without it."""
    net = {
        "arch": "mlp:64x2:silu",
        "members": 4,
        "offered": "temperature",
        "takes_offered": True,
        "sizes": [
            {"arch": "mlp:64x2:silu", "crossed_val_mm": 0.05, "kept": True},
            {"arch": "mlp:64x2:silu + temperature", "crossed_val_mm": 0.03, "kept": True},
        ],
    }
    html = "".join(_capacity_section(None, {"position": net}))
    rows = {row.split("</td><td>")[1]: row for row in html.split("<tr>") if "net size" in row}
    assert "served" in rows["mlp:64x2:silu + temperature"] and "a later rung beat it" in rows["mlp:64x2:silu"]
