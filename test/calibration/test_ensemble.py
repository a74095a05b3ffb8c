"""Ensembles of residual nets: members from distinct seeds, averaged in the saved TorchScript and in the
node's numpy path alike, silenced as a whole when their average does not help."""

from __future__ import annotations

import subprocess
from dataclasses import replace

import numpy as np
import pytest
import torch

from hybrid_kinematics_ros.calibration import train
from hybrid_kinematics_ros.calibration.fit import fit, split
from hybrid_kinematics_ros.calibration.nets import Ensemble
from hybrid_kinematics_ros.calibration.recipe import Recipe
from hybrid_kinematics_ros.model.nets import FastResidual

MEMBERS = 3


@pytest.fixture(scope="module")
def ensemble(ur10, virtual_pairs, tmp_path_factory):
    out = tmp_path_factory.mktemp("models") / "ensemble"
    tr, va, te = split(virtual_pairs.subset(np.arange(2000)), seed=0)
    preset = replace(train.PRESETS["fast"], arch="mlp:32x2:silu", max_epochs=40, members=MEMBERS)
    model, manifest = fit(ur10.chain, tr, va, te, out, Recipe(preset, 1.0, parametric=False))
    return model, manifest, te


def test_members_differ_and_are_averaged(ensemble):
    model, manifest, te = ensemble
    net = model.nets["position"]
    members = list(net.body.members.children())
    assert len(members) == MEMBERS
    first = [p.detach().numpy() for p in members[0].parameters()]
    second = [p.detach().numpy() for p in members[1].parameters()]
    assert not all(np.array_equal(a, b) for a, b in zip(first, second, strict=True))  # distinct seeds
    features = net.features(torch.tensor(te.q))
    with torch.no_grad():
        outputs = [m(features).double() for m in members]
        mean = torch.stack(outputs).mean(0) * net.target_scale + net.target_mean
        served = net(torch.tensor(te.q))
    # the saved module's output is the members' mean (before the joint-1 turn, which keeps lengths)
    assert torch.linalg.vector_norm(served, dim=1).numpy() == pytest.approx(
        torch.linalg.vector_norm(mean, dim=1).numpy(), rel=1e-5
    )
    assert manifest["preset"]["members"] == MEMBERS
    history = manifest["nets"]["position"]
    assert history["epochs"] == MEMBERS * 40


def test_the_compiled_path_matches_torchscript_for_an_ensemble(ensemble):
    model, _, te = ensemble
    fast = FastResidual.from_module(model.nets["orientation"])
    assert fast is not None and fast.members == MEMBERS
    batch = model.fk(te.q[:10])
    for i in range(10):
        np.testing.assert_allclose(model.fk_single(te.q[i]), batch[i], atol=5e-9, rtol=0)
    q = te.q[0]
    value, jac = fast.value_and_jacobian(q)
    # against autograd through the saved TorchScript ensemble
    net = model.nets["orientation"]
    auto = torch.autograd.functional.jacobian(lambda x: net(x[None])[0], torch.tensor(q)).numpy()
    np.testing.assert_allclose(jac, auto, atol=1e-4 * np.abs(auto).max())
    np.testing.assert_allclose(value, net(torch.tensor(q[None]))[0].detach().numpy(), atol=1e-9)


def test_an_ensemble_that_only_hurts_on_validation_is_silenced():
    rng = np.random.default_rng(0)
    q_train, q_val = rng.uniform(-2.0, 2.0, (600, 6)), rng.uniform(-2.0, 2.0, (150, 6))

    def residual(q: np.ndarray) -> np.ndarray:
        return 1e-4 * np.column_stack([np.sin(2 * q[:, 1]), np.cos(q[:, 1]), np.sin(q[:, 1] + q[:, 2])])

    preset = replace(train.PRESETS["fast"], arch="mlp:32x2:silu", batch=64, max_epochs=30, members=2)
    lower, upper = np.full(6, -2.0), np.full(6, 2.0)
    job = train.NetJob(
        "position", preset, q_train, residual(q_train), q_val, -residual(q_val), lower, upper, None, 60.0, 0, 6
    )
    net, history = train.train_net(job)
    assert isinstance(net.body, Ensemble)
    assert history[-1]["silenced"] and {e["member"] for e in history} == {0, 1}
    assert not net(torch.tensor(q_val)).detach().numpy().any()


def test_cli_refuses_an_empty_ensemble(tmp_path):
    result = subprocess.run(
        [
            "hybrid-kinematics",
            "train",
            "--bag",
            str(tmp_path),
            "--robot",
            "ur10",
            "--out",
            str(tmp_path / "m"),
            "--members",
            "0",
        ],
        capture_output=True,
        text=True,
        check=False,
    )
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0 and "members = 0" in result.stderr
    assert not (tmp_path / "m").exists()
