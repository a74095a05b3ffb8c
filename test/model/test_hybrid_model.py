"""Training for real on a small virtual set, export and load, and refusal of mismatched models."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from hybrid_kinematics_ros.calibration import nets
from hybrid_kinematics_ros.calibration.evaluate import coverage_report, evaluate
from hybrid_kinematics_ros.io.errors import DataError
from hybrid_kinematics_ros.kinematics import fk, se3
from hybrid_kinematics_ros.kinematics.robot_config import CONFIG_DIR
from hybrid_kinematics_ros.kinematics.se3 import left_jacobian_so3
from hybrid_kinematics_ros.model.errors import ModelError
from hybrid_kinematics_ros.model.hybrid import HybridModel
from hybrid_kinematics_ros.model.nets import AxisTurn, FastResidual, to_joint1_frame


def test_training_cuts_the_error_by_a_large_factor(trained):
    _, model, manifest, test_pairs = trained
    report = evaluate(model, test_pairs)
    assert report["analytic"]["position_mm_mean"] > 1.0
    assert report["hybrid"]["position_mm_mean"] < report["analytic"]["position_mm_mean"] / 10
    assert report["hybrid"]["orientation_deg_mean"] < report["analytic"]["orientation_deg_mean"] / 10
    assert manifest["metrics"]["test"]["hybrid"]["position_mm_mean"] == pytest.approx(
        report["hybrid"]["position_mm_mean"]
    )


def test_saved_model_reloads_bit_identical(trained):
    path, model, _, test_pairs = trained
    again = HybridModel.load(path)
    np.testing.assert_array_equal(again.fk(test_pairs.q), model.fk(test_pairs.q))
    manifest = json.loads((path / "model.json").read_text())
    assert manifest["joint_names"] == list(model.joint_names)
    assert set(manifest["nets"]) == {"position", "orientation"}
    assert len(manifest["urdf_sha256"]) == 64 and (path / "robot.urdf").is_file()
    assert not list(path.glob("*.pkl"))


def test_single_and_batched_hybrid_fk_agree(trained):
    _, model, _, test_pairs = trained
    batch = model.fk(test_pairs.q[:20])
    for i in range(20):
        # float32 nets round differently by batch size: agree to nanometres and nanoradians
        np.testing.assert_allclose(model.fk_single(test_pairs.q[i]), batch[i], atol=5e-9, rtol=0)


def _compiled_against_batch(model: HybridModel, q: np.ndarray) -> None:
    """One-configuration poses (the compiled kernel, which the model must take) against the batch path (the
    stage's numpy FK, TorchScript nets above 16 rows, scipy's rotation), to nanometres and nanoradians."""
    assert model._pose_operands() is not None
    batch = model.fk(q)
    assert len(q) > 16
    single = np.array([model.fk_single(row) for row in q])
    np.testing.assert_allclose(single, batch, atol=5e-9, rtol=0)


def test_the_compiled_pose_is_the_batch_paths(trained, thermal_models, shoulder_model):
    """Every stage the kernel takes: none (nets on the URDF), elastic with cyclic joint errors and a condition
    channel, elastic with a payload; per-net range policies; a payload changed after the first call."""
    _, rigid, _, test_pairs = trained
    _compiled_against_batch(rigid, test_pairs.q[:24])
    models, thermal_test = thermal_models
    thermal = models["thermal"]
    assert thermal.base.is_elastic and thermal.base.has_joint_error and thermal.condition_names == ("temperature",)
    for temperature in (19.0, 27.0):
        _compiled_against_batch(thermal.with_conditions([temperature]), thermal_test.q[:24])
    path, _, inside, beyond = shoulder_model
    model = HybridModel.load(path)
    _compiled_against_batch(model, inside.q[:24])
    bound = model.with_range_policy("bound")  # beyond the shoulder's range each net serves where its bound is lower
    serve = bound._nets_apply(bound.same_turn(beyond.q[:40]))
    assert serve is not True and serve.any() and not serve.all()  # some nets off, some on
    _compiled_against_batch(bound, beyond.q[:40])
    before = model.fk_single(inside.q[0])
    heavier = model.with_payload(model.base.payload_mass + 5.0, model.base.payload_com)
    _compiled_against_batch(heavier, inside.q[:24])
    assert np.abs(heavier.fk_single(inside.q[0])[:3, 3] - before[:3, 3]).max() > 1e-5  # the stage followed it
    np.testing.assert_array_equal(model.fk_single(inside.q[0]), before)


def test_hybrid_jacobian_matches_finite_differences(trained):
    _, model, _, test_pairs = trained
    q = test_pairs.q[:3]
    T, J = model.fk_and_jacobian(q)
    np.testing.assert_allclose(T, model.fk(q), atol=1e-12)
    # float32 nets: the difference quotient's rounding error grows as 1/eps (measured on this fixture, worst over
    # the 36 entries: 2.0e-6, 4.6e-6, 1.05e-5, 2.2e-5 at eps 4e-4, 2e-4, 1e-4, 5e-5), its truncation error is
    # below that at 4e-4
    eps = 4e-4
    for j in range(6):
        dq = np.zeros(6)
        dq[j] = eps
        plus, minus = model.fk(q + dq), model.fk(q - dq)
        v = (plus[:, :3, 3] - minus[:, :3, 3]) / (2 * eps)
        w = se3.rotvec(plus[:, :3, :3] @ np.swapaxes(minus[:, :3, :3], 1, 2)) / (2 * eps)
        np.testing.assert_allclose(J[:, :3, j], v, atol=1e-5)  # the nets contribute ~1e-3: checked to 1%
        np.testing.assert_allclose(J[:, 3:, j], w, atol=1e-5)  # the nets contribute ~1e-3: checked to 1%


def test_analytic_only_model_is_the_urdf_model(ur10):
    model = HybridModel.analytic_only(ur10.chain)
    q = np.random.default_rng(0).uniform(-1, 1, (5, 6))
    np.testing.assert_array_equal(model.fk(q), fk.fk(ur10.chain, q))


def test_joint1_frame_turn_is_inverted_exactly():
    axis = np.array([0.0, 0.6, 0.8])
    r = np.random.default_rng(1).normal(size=(10, 3))
    q1 = np.random.default_rng(2).uniform(-3, 3, 10)
    net = nets.ResidualNet(
        "mlp:4x1", nets.InputSpan(-np.ones(6), np.ones(6)), (np.zeros(3), np.ones(3)), joint1_axis=axis
    )
    q = torch.zeros(10, 6, dtype=torch.float64)
    q[:, 0] = torch.tensor(q1)
    local = to_joint1_frame(r, q1, axis)
    np.testing.assert_allclose(net._turn(torch.tensor(local), q).numpy(), r, atol=1e-12)
    # one vector by one angle takes the Python-float path: the same turn as the matrices'
    turn = AxisTurn(axis)
    np.testing.assert_allclose([turn.apply(v, a) for v, a in zip(local, q1, strict=True)], r, atol=1e-12)


@pytest.mark.parametrize("arch", ["D1", "D4", "D4w", "D4W", "Rw", "Rd", "mlp:32x3:relu"])
def test_paper_architectures_build_script_and_run(arch, tmp_path):
    net = nets.ResidualNet(arch, nets.InputSpan(-np.ones(6), np.ones(6)), (np.zeros(3), np.ones(3)), sincos=False)
    net.eval()
    scripted = torch.jit.script(net)
    scripted.save(str(tmp_path / "n.pt"))
    q = torch.rand(7, 6, dtype=torch.float64)
    assert torch.equal(torch.jit.load(str(tmp_path / "n.pt"))(q), net(q))


@pytest.mark.parametrize("act", ["relu", "silu", "tanh"])
@pytest.mark.parametrize("turn", [False, True])
def test_the_compiled_nets_jacobian_is_autograds(act, turn):
    """The compiled evaluator's reverse-mode Jacobian against torch's autograd, with the sines and cosines and
    a condition column (7 inputs, 6 of them joints), with and without the joint-1 turn."""
    torch.manual_seed(0)
    lower, upper = np.array([-3.0, -2.0, -2.5, -3.0, -2.0, -3.0, 10.0]), np.array([3.0, 1.0, 2.5, 3.0, 2.0, 3.0, 40.0])
    axis = np.array([0.0, 0.0, 1.0]) if turn else None
    scale = np.array([2e-3, 1e-3, 3e-3])
    net = nets.ResidualNet(f"mlp:32x3:{act}", nets.InputSpan(lower, upper, 6), (np.full(3, 1e-4), scale), True, axis)
    net.eval()
    fast = FastResidual.from_module(torch.jit.script(net))
    for q in np.random.default_rng(3).uniform(lower, upper, (5, 7)):
        value, jac = fast.value_and_jacobian(q)
        auto = torch.autograd.functional.jacobian(lambda x: net(x[None])[0], torch.tensor(q)).numpy()
        np.testing.assert_allclose(jac, auto, atol=1e-5 * np.abs(auto).max())
        np.testing.assert_allclose(value, net(torch.tensor(q[None]))[0].detach().numpy(), atol=1e-9)


@pytest.mark.parametrize("members", [1, 3])
def test_a_batch_through_the_compiled_net_is_its_rows_and_torchscripts(members):
    """A batch through the compiled net (the path of up to COMPILED_ROWS rows): each row's own residual, and
    TorchScript's, ensembles included."""
    torch.manual_seed(1)
    lower, upper = np.array([-3.0, -2.0, -2.5, -3.0, -2.0, -3.0]), np.array([3.0, 1.0, 2.5, 3.0, 2.0, 3.0])
    scale = np.array([2e-3, 1e-3, 3e-3])
    net = nets.ResidualNet(
        "mlp:64x3:silu", nets.InputSpan(lower, upper), (np.full(3, 1e-4), scale), True, members=members
    )
    net.eval()
    fast = FastResidual.from_module(torch.jit.script(net))
    assert fast is not None and fast.members == members
    q = np.random.default_rng(5).uniform(lower, upper, (40, 6))
    batch = fast(q)
    rows = np.array([fast(row) for row in q])
    np.testing.assert_allclose(batch, rows, atol=1e-6 * np.abs(rows).max(), rtol=0)  # float32 sums, in any order
    np.testing.assert_allclose(batch, net(torch.tensor(q)).detach().numpy(), atol=1e-9, rtol=0)
    assert np.abs(batch).max() > 1e-4  # the residuals are not just the mean


def test_one_vectors_left_jacobian_is_the_batchs():
    w = np.concatenate([np.random.default_rng(4).normal(size=(12, 3)) * s for s in (1e-10, 1e-4, 1.0, 3.0)])
    np.testing.assert_allclose([left_jacobian_so3(v) for v in w], left_jacobian_so3(w), atol=1e-15)
    # and it maps a change of the rotation vector to the angular velocity of exp(ω): against a difference
    v, dv = np.array([0.3, -0.2, 0.5]), 1e-7 * np.array([1.0, 2.0, -1.0])
    r0, r1 = se3.exp_so3(v), se3.exp_so3(v + dv)
    omega = se3.rotvec((r1 @ r0.T)[None])[0]
    np.testing.assert_allclose(left_jacobian_so3(v) @ dv, omega, atol=1e-13)


def test_unknown_architecture_is_refused():
    with pytest.raises(ValueError, match="unknown architecture 'D9'"):
        nets.build_body("D9", 6)


def test_mismatched_and_corrupt_models_are_refused(trained, tmp_path):
    path = trained[0]
    other = (CONFIG_DIR / "rx160.urdf").read_text()
    with pytest.raises(DataError, match="trained for another URDF"):
        HybridModel.load(path, expect_urdf=other.replace("tool0", "tool0"))
    with pytest.raises(DataError, match="trained for joints"):
        HybridModel.load(path, expect_joint_names=("a", "b", "c", "d", "e", "f"))

    def broken(edit):
        copy = tmp_path / f"m{len(list(tmp_path.iterdir()))}"
        shutil.copytree(path, copy)
        edit(copy)
        return copy

    with pytest.raises(DataError, match=r"position\.pt is corrupt"):
        HybridModel.load(broken(lambda p: (p / "position.pt").write_bytes(b"junk")))
    with pytest.raises(DataError, match=r"orientation\.pt does not exist"):
        HybridModel.load(broken(lambda p: (p / "orientation.pt").unlink()))
    with pytest.raises(DataError, match="the URDF copy was changed"):
        HybridModel.load(broken(lambda p: (p / "robot.urdf").write_text(other)))
    with pytest.raises(DataError, match="not valid JSON"):
        HybridModel.load(broken(lambda p: (p / "model.json").write_text("{")))
    with pytest.raises(DataError, match=r"coverage\.npy is corrupt"):
        HybridModel.load(broken(lambda p: np.save(p / "coverage.npy", np.zeros((3, 6)))))
    with pytest.raises(DataError, match=r"model\.json does not exist"):
        HybridModel.load(tmp_path)


def test_range_policies(trained):
    path, _, _, _ = trained
    model = HybridModel.load(path)
    q = np.array([[0.1, -1.0, 1.0, -1.0, 1.0, 0.0], [0.1, -1.0, model.trained_upper[2] + 0.05, -1.0, 1.0, 0.0]])
    assert list(model.in_calibrated_range(q)) == [True, False]
    warn = model.fk(q)
    parametric = model.with_range_policy("parametric")
    fallback = parametric.fk(q)
    np.testing.assert_array_equal(fallback[0], warn[0])
    np.testing.assert_array_equal(fallback[1], model.fk(q[1:], nets=False)[0])
    np.testing.assert_allclose(parametric.fk_single(q[1]), fallback[1], atol=1e-12)
    np.testing.assert_allclose(parametric.fk_and_jacobian(q)[0], fallback, atol=1e-12)
    np.testing.assert_array_equal(model.fk(q), warn)  # the value it came from serves as before
    refuse = model.with_range_policy("refuse")
    refuse.check_range(q[:1])
    with pytest.raises(ModelError, match=f"configuration 1 lies outside.*{model.joint_names[2]}"):
        refuse.check_range(q)
    with pytest.raises(ModelError, match="range policy 'sometimes' is not one of"):
        model.with_range_policy("sometimes")


def test_coverage_radius_drops_the_nets_far_from_the_training_data(trained):
    path, _, _, test = trained
    model = HybridModel.load(path)
    stored = np.load(path / "coverage.npy")
    assert len(stored) == model.manifest["coverage"]["configurations"] and stored.shape[1] == 6
    # the distance is that to the nearest stored configuration (float32 copies of the training joints)
    q = test.q[:50]
    brute = np.linalg.norm(q[:, None, :] - stored[None].astype(float), axis=2).min(axis=1)
    np.testing.assert_allclose(model.coverage_distance(q), brute, atol=1e-12)
    near, far = stored[0].astype(float), stored[0] + np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.9])
    far = np.clip(far, model.trained_lower, model.trained_upper)
    q = np.stack([near, far])
    radius = 0.5 * float(model.coverage_distance(far[None])[0])
    assert list(model.in_calibrated_range(q)) == [True, True]  # the per-joint range alone
    covered = model.with_coverage_radius(radius).with_range_policy("parametric")
    assert list(covered.in_calibrated_range(q)) == [True, False]
    served = covered.fk(q)
    np.testing.assert_array_equal(served[1], model.fk(q[1:], nets=False)[0])
    assert not np.allclose(served[0], model.fk(q[:1], nets=False)[0], atol=1e-9)  # the nets still correct near
    with pytest.raises(ModelError, match=r"from the nearest training configuration \(coverage radius"):
        covered.with_range_policy("refuse").check_range(q)
    with pytest.raises(ModelError, match="positive number of radians"):
        model.with_coverage_radius(-1.0)
    with pytest.raises(ModelError, match="stores no training configurations"):
        HybridModel.analytic_only(model.chain).with_coverage_radius(0.5)


def test_coverage_report_finds_the_radius_where_the_nets_stop_helping():
    rng = np.random.default_rng(0)
    distance = rng.uniform(0.0, 2.0, 4000)
    hybrid = np.where(distance < 0.7, 0.02, 0.3) + rng.uniform(0, 0.01, 4000)
    base = np.full(4000, 0.1)
    report = coverage_report(distance, (hybrid, np.zeros(4000)), (base, np.zeros(4000)), "parametric")
    assert 0.68 < report["suggested_radius_rad"] < 0.7
    best = np.where(distance <= report["suggested_radius_rad"], hybrid, base).mean()
    assert report["position_mm_mean_with_radius"] == pytest.approx(best, rel=1e-12)
    assert sum(b["count"] for b in report["bins"]) == 4000
    helpful = coverage_report(distance, (base / 2, np.zeros(4000)), (base, np.zeros(4000)), "analytic")
    assert helpful["suggested_radius_rad"] is None


def test_a_whole_turn_of_a_joint_gets_the_same_correction(trained):
    """q and q ± 2π are one URDF pose: every path gives them one hybrid pose and one range verdict (the
    nets used to take the raw angle, 2π outside the range they were trained on)."""
    path, _, _, test = trained
    model = HybridModel.load(path)
    q = test.q[:20]
    turned = q.copy()
    turned[:, 0] -= 2 * np.pi
    turned[:, 5] += 2 * np.pi
    assert model.in_calibrated_range(q).all() and model.in_calibrated_range(turned).all()
    assert model.in_calibrated_range_one(turned[0].tolist())
    np.testing.assert_allclose(model.fk(turned), model.fk(q), atol=1e-9)
    np.testing.assert_allclose(model.fk_single(turned[0]), model.fk_single(q[0]), atol=1e-9)
    for a, b in zip(model.fk_and_jacobian(turned), model.fk_and_jacobian(q), strict=True):
        np.testing.assert_allclose(a, b, atol=1e-9)
    for a, b in zip(model.fk_and_jacobian_single(turned[0]), model.fk_and_jacobian_single(q[0]), strict=True):
        np.testing.assert_allclose(a, b, atol=1e-9)
    np.testing.assert_array_equal(model.same_turn(q), q)  # inside the range: untouched, bit for bit
    # the correction is not the analytic model's: the nets do act at these joints
    assert np.abs(model.fk(turned)[:, :3, 3] - model.fk(turned, nets=False)[:, :3, 3]).max() > 1e-6
