"""FK and Jacobians against pinocchio, on our robots and on URDFs written by others."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
import torch

from hybrid_kinematics_ros.kinematics import fk
from hybrid_kinematics_ros.kinematics.chain import chain_from_urdf
from hybrid_kinematics_ros.kinematics.robot_config import CONFIG_DIR
from hybrid_kinematics_ros.kinematics.torch_chain import TorchChain

N = 1000


def pinocchio_reference(urdf: str, tip: str, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    model = pin.buildModelFromUrdf(urdf)
    data = model.createData()
    frame = model.getFrameId(tip)
    poses, jacs = [], []
    for qi in q:
        pin.forwardKinematics(model, data, qi)
        pin.updateFramePlacements(model, data)
        poses.append(data.oMf[frame].homogeneous.copy())
        jacs.append(pin.computeFrameJacobian(model, data, qi, frame, pin.LOCAL_WORLD_ALIGNED))
    return np.array(poses), np.array(jacs)


def urdf_cases(example_robot_data):
    return [
        (str(CONFIG_DIR / "ur10.urdf"), "base_link", "tool0"),
        (str(CONFIG_DIR / "rx160.urdf"), "base_link", "tool0"),
        (str(example_robot_data / "ur_description/urdf/ur10_robot.urdf"), "base_link", "tool0"),
        (str(example_robot_data / "ur_description/urdf/ur5_robot.urdf"), "base_link", "ee_link"),
    ]


@pytest.mark.parametrize("case", range(4))
def test_fk_and_jacobian_match_pinocchio(case, example_robot_data):
    urdf, base, tip = urdf_cases(example_robot_data)[case]
    chain = chain_from_urdf(urdf, base, tip)
    q = np.random.default_rng(case).uniform(-np.pi, np.pi, (N, chain.dof))
    ref_t, ref_j = pinocchio_reference(urdf, tip, q)
    t, j = fk.fk_and_jacobian(chain, q)
    np.testing.assert_allclose(t, ref_t, atol=1e-9, rtol=0)
    np.testing.assert_allclose(j, ref_j, atol=1e-9, rtol=0)
    np.testing.assert_allclose(fk.fk(chain, q), ref_t, atol=1e-9, rtol=0)
    np.testing.assert_allclose(fk.fk_single(chain, q[:3]), ref_t[:3], atol=1e-12, rtol=0)  # a few at once
    for i in range(0, N, 97):
        np.testing.assert_allclose(fk.fk_single(chain, q[i]), ref_t[i], atol=1e-12, rtol=0)
        t_single, j_single = fk.fk_and_jacobian_single(chain, q[i])
        np.testing.assert_allclose(t_single, ref_t[i], atol=1e-12, rtol=0)
        np.testing.assert_allclose(j_single, ref_j[i], atol=1e-9, rtol=0)


@pytest.mark.parametrize("case", range(4))
def test_torch_matches_numpy_in_float64(case, example_robot_data):
    urdf, base, tip = urdf_cases(example_robot_data)[case]
    chain = chain_from_urdf(urdf, base, tip)
    q = np.random.default_rng(10 + case).uniform(-np.pi, np.pi, (N, chain.dof))
    tc = TorchChain(chain)
    qt = torch.tensor(q)
    np.testing.assert_allclose(tc(qt).numpy(), fk.fk(chain, q), atol=1e-12, rtol=0)
    np.testing.assert_allclose(tc.joint_frames(qt).numpy(), fk.joint_frames(chain, q), atol=1e-12, rtol=0)


def test_torch_float32_and_gradient_agree_with_jacobian():
    chain = chain_from_urdf(CONFIG_DIR / "ur10.urdf", "base_link", "tool0")
    q = torch.tensor(np.random.default_rng(3).uniform(-2, 2, (4, 6)), requires_grad=True)
    tc = TorchChain(chain)
    pos = tc(q)[:, :3, 3]
    grads = [torch.autograd.grad(pos[:, i].sum(), q, retain_graph=True)[0] for i in range(3)]
    autograd_linear = torch.stack(grads, dim=1)  # (B, 3, n)
    _, jac = fk.fk_and_jacobian(chain, q.detach().numpy())
    np.testing.assert_allclose(autograd_linear.numpy(), jac[:, :3], atol=1e-12)
    t32 = TorchChain(chain, dtype=torch.float32)(q.detach().float())
    assert t32.dtype == torch.float32
    np.testing.assert_allclose(t32.numpy(), fk.fk(chain, q.detach().numpy()), atol=1e-5)


def test_torch_chain_scripts_and_matches_eager(tmp_path):
    chain = chain_from_urdf(CONFIG_DIR / "rx160.urdf", "base_link", "tool0")
    eager = TorchChain(chain)
    scripted = torch.jit.script(eager)
    scripted.save(str(tmp_path / "chain.pt"))
    loaded = torch.jit.load(str(tmp_path / "chain.pt"))
    q = torch.tensor(np.random.default_rng(4).uniform(-2, 2, (16, 6)))
    assert torch.equal(loaded(q), eager(q))
