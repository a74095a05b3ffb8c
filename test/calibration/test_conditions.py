"""Condition channels as net inputs: a cell whose robot grows with its temperature, trained with and without
the temperature channel, judged on held-out pairs at other temperatures; the served paths agree."""

from __future__ import annotations

import numpy as np
import pytest

from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.calibration.evaluate import evaluate
from hybrid_kinematics_ros.calibration.fit import fit, split
from hybrid_kinematics_ros.calibration.recipe import Recipe
from hybrid_kinematics_ros.model.errors import ModelError
from test.conftest import THERMAL_PRESET, thermal_pairs


def test_the_temperature_input_learns_what_the_joints_cannot(thermal_models):
    loaded, test = thermal_models
    plain = evaluate(loaded["plain"], test)["hybrid"]["position_mm_mean"]
    thermal = evaluate(loaded["thermal"], test)["hybrid"]["position_mm_mean"]
    # growth of 2e-4/K over ±5 K at about 1 m is ±1 mm, which no function of the joints predicts
    assert plain > 0.3 and thermal < plain / 4, (plain, thermal)
    model = loaded["thermal"]
    assert model.condition_names == ("temperature",)
    assert model.manifest["conditions"]["temperature"]["default"] == pytest.approx(23.0, abs=0.5)


def test_served_paths_use_the_current_value(thermal_models):
    loaded, test = thermal_models
    model = loaded["thermal"]
    q = test.q[:5]
    warm = model.with_condition("temperature", 27.0)
    batch = warm.fk(q)
    np.testing.assert_allclose(batch, model.fk(q, conditions=np.full((5, 1), 27.0)), atol=1e-12)
    for i in range(5):  # the node's single-pose paths: numpy inference on joints plus the current value
        np.testing.assert_allclose(warm.fk_single(q[i]), batch[i], atol=5e-9)
        T, J = warm.fk_and_jacobian_single(q[i])
        np.testing.assert_allclose(T, batch[i], atol=5e-9)
        _, Jb = warm.fk_and_jacobian(q[i : i + 1])
        np.testing.assert_allclose(J, Jb[0], atol=1e-6)
        assert J.shape == (6, 6)
    cool = warm.with_condition("temperature", 19.0)
    assert np.linalg.norm(cool.fk(q)[:, :3, 3] - batch[:, :3, 3], axis=1).mean() > 0.3e-3  # m
    np.testing.assert_array_equal(warm.fk(q), batch)  # a value: the other one left it as it was
    with pytest.raises(ModelError, match="no condition 'humidity'"):
        model.with_condition("humidity", 40.0)
    with pytest.raises(ModelError, match="not a finite number"):
        model.with_condition("temperature", float("nan"))


def test_training_on_a_channel_the_pairs_lack_says_so(ur10, tmp_path):
    tr, va, te = split(thermal_pairs(ur10, 200, seed=3), seed=0)
    with pytest.raises(CalibrationError, match="carry no humidity channel"):
        fit(
            ur10.chain,
            tr,
            va,
            te,
            tmp_path / "m",
            Recipe(THERMAL_PRESET, 1.0, parametric=False, conditions=("humidity",)),
        )
    assert not (tmp_path / "m").exists()
