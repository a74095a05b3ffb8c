"""The elasto-geometric chain: rigid when its parameters are zero, one pose path equal to the batch path,
and a Jacobian close to finite differences (it leaves out the torque derivative by design)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hybrid_kinematics_ros.kinematics import fk, fk_kernel, se3
from hybrid_kinematics_ros.kinematics.chain import chain_from_urdf
from hybrid_kinematics_ros.kinematics.elastic import ElasticChain, JointMap
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.simulation.truth import TrueRobot


@pytest.fixture(scope="module", params=["ur10", "rx160"])
def elastic(request) -> ElasticChain:
    return TrueRobot.from_config(load_robot_config(request.param)).elastic


def joints(chain, n, seed=0):
    return np.random.default_rng(seed).uniform(chain.lower, chain.upper, (n, chain.dof))


def test_exp_so3_matches_scipy_from_tiny_to_large_angles():
    w = np.random.default_rng(0).normal(size=(200, 3)) * np.logspace(-14, 0.5, 200)[:, None]
    np.testing.assert_allclose(se3.exp_so3(w), Rotation.from_rotvec(w).as_matrix(), atol=1e-15, rtol=0)
    # one vector takes a path of its own (Python floats): each alone, and no rotation at all
    for v in [*w, np.zeros(3), np.array([np.pi, 0.0, 0.0])]:
        np.testing.assert_allclose(se3.exp_so3(v), Rotation.from_rotvec(v).as_matrix(), atol=1e-15, rtol=0)


def test_rigid_elastic_chain_is_the_plain_chain(elastic):
    rigid = ElasticChain.rigid(elastic.chain, 3.0, np.array([0.0, 0.0, 0.1]))
    q = joints(elastic.chain, 100)
    np.testing.assert_array_equal(rigid.fk(q), fk.fk(elastic.chain, q))
    assert rigid.is_rigid and not elastic.is_rigid
    # backlash alone shifts the joints wherever their approach directions are known: not the plain chain
    # (a model counted it rigid and served the URDF's unrolled FK, without the shift, on its one-pose path)
    assert not replace(rigid, backlash=np.full(rigid.dof, 1e-3)).is_rigid
    assert replace(rigid, backlash=np.zeros(rigid.dof)).is_rigid


def _single_paths_agree(model: ElasticChain, q: np.ndarray) -> np.ndarray:
    """The single-pose paths give the batch's poses and Jacobians for the first three of ``q``; returns
    the batch's Jacobians."""
    T, J = model.fk_and_jacobian(q)
    for i in range(3):
        np.testing.assert_allclose(model.fk_single(q[i]), T[i], atol=1e-14)
        np.testing.assert_allclose(model.fk_and_jacobian_single(q[i])[1], J[i], atol=1e-12)
    return J


@pytest.mark.parametrize("bending", [True, False])
def test_single_pose_paths_equal_the_batch(elastic, bending):
    """With bending, and without (compliance alone, as most identified stages are: the single path then
    skips the bends)."""
    assert elastic.bending.any()
    if not bending:
        elastic = replace(elastic, bending=np.zeros_like(elastic.bending))
    q = joints(elastic.chain, 20, seed=1)
    T, J = elastic.fk_and_jacobian(q)
    np.testing.assert_allclose(elastic.fk(q), T, atol=1e-15)
    for i in range(len(q)):
        np.testing.assert_allclose(elastic.fk_single(q[i]), T[i], atol=1e-14, rtol=0)
        Ts, Js = elastic.fk_and_jacobian_single(q[i])
        np.testing.assert_allclose(Ts, T[i], atol=1e-14, rtol=0)
        np.testing.assert_allclose(Js, J[i], atol=1e-12, rtol=0)


def test_every_term_on_a_chain_with_a_prismatic_joint_has_one_pose_equal_to_the_batch(tmp_path):
    """The compiled one-pose path against the batch with every term of the stage at once: load-dependent and
    sign-dependent stiffness, the truth's stiffening, bending, a payload, a tilted gravity and a prismatic
    joint (which carries the weight beyond it along its axis)."""
    from test.kinematics.test_chain import MIXED

    path = tmp_path / "mixed.urdf"
    path.write_text(MIXED)
    chain = chain_from_urdf(path, "world", "tip")
    rng = np.random.default_rng(7)
    model = ElasticChain(
        chain,
        zero_offset=rng.normal(scale=1e-3, size=3),
        compliance=np.array([2e-3, 1e-4, 3e-3]),
        bending=rng.normal(scale=1e-3, size=(3, 3)),
        payload_mass=1.5,
        payload_com=np.array([0.01, -0.02, 0.05]),
        cubic_ratio=0.3,
        torque_ref=5.0,
        cubic_compliance=np.array([1e-5, 0.0, -2e-5]),
        signed_compliance=np.array([4e-4, 1e-5, -3e-4]),
        gravity=np.array([0.5, -1.0, -9.7]),
    )
    q = np.column_stack([rng.uniform(-1.5, 2, 20), rng.uniform(-0.1, 0.3, 20), rng.uniform(-6, 6, 20)])
    T, J = model.fk_and_jacobian(q)
    assert model.is_elastic and np.abs(model.gravity_torques(q)).max() > 1.0
    for i in range(len(q)):
        np.testing.assert_allclose(model.fk_single(q[i]), T[i], atol=1e-14, rtol=0)
        Ts, Js = model.fk_and_jacobian_single(q[i])
        np.testing.assert_allclose(Ts, T[i], atol=1e-14, rtol=0)
        np.testing.assert_allclose(Js, J[i], atol=1e-12, rtol=0)


def test_jacobian_is_within_the_stated_approximation(elastic):
    q = joints(elastic.chain, 5, seed=2)
    _, J = elastic.fk_and_jacobian(q)
    eps = 1e-6
    for j in range(elastic.dof):
        dq = np.zeros(elastic.dof)
        dq[j] = eps
        plus, minus = elastic.fk(q + dq), elastic.fk(q - dq)
        v = (plus[:, :3, 3] - minus[:, :3, 3]) / (2 * eps)
        w = se3.rotvec(plus[:, :3, :3] @ np.swapaxes(minus[:, :3, :3], 1, 2)) / (2 * eps)
        numeric = np.concatenate([v, w], axis=1)
        # the left-out c·∂τ/∂q is a few 1e-3 of a column for these arms; a wrong axis would be O(1)
        np.testing.assert_allclose(J[:, :, j], numeric, atol=1e-2 * np.abs(numeric).max() + 1e-9)


def _with_cyclic(elastic: ElasticChain, rigid: bool) -> ElasticChain:
    """The chain with cyclic joint errors at harmonics 1-3 (about an arcminute), elastic or not."""
    rng = np.random.default_rng(4)
    coef = rng.normal(0.0, 3e-4, (elastic.dof, 3, 2))
    base = ElasticChain.rigid(elastic.chain) if rigid else elastic
    return replace(base, zero_offset=elastic.zero_offset, joint_error=coef)


@pytest.mark.parametrize("rigid", [True, False])
def test_cyclic_joint_errors_turn_the_joints(elastic, rigid):
    """A cyclic joint error is a joint-angle shift: the chain at q equals the chain without it at the
    shifted joints; the single-pose paths agree with the batch and the Jacobian is by the commanded joints."""
    model = _with_cyclic(elastic, rigid)
    q = joints(elastic.chain, 20, seed=3)
    f = np.arange(1, 4)
    shift = np.einsum("bnk,nk->bn", np.sin(q[..., None] * f), model.joint_error[..., 0]) + np.einsum(
        "bnk,nk->bn", np.cos(q[..., None] * f), model.joint_error[..., 1]
    )
    plain = replace(model, joint_error=None)
    np.testing.assert_allclose(model.fk(q), plain.fk(q + shift), atol=1e-14)
    assert not model.is_rigid and model.has_joint_error
    J = _single_paths_agree(model, q)
    eps = 1e-6
    for j in range(model.dof):
        dq = np.zeros(model.dof)
        dq[j] = eps
        plus, minus = model.fk(q + dq), model.fk(q - dq)
        numeric = (plus[:, :3, 3] - minus[:, :3, 3]) / (2 * eps)
        # without the cyclic slope the columns would be off by f·a ≈ 1e-3 of their size
        tol = (1e-2 if not rigid else 1e-6) * np.abs(numeric).max() + 1e-9
        np.testing.assert_allclose(J[:, :3, j], numeric, atol=tol)


def test_joint_map_interpolates_like_numpy_and_holds_its_ends():
    """The map's value is numpy's linear interpolation of its knots (ends held), its slope the
    finite difference inside the knots and zero beyond them."""
    rng = np.random.default_rng(5)
    lower, step = np.array([-1.0, 0.5]), 0.01
    joint_map = JointMap(lower, step, rng.normal(scale=1e-5, size=(2, 40)))
    q = np.column_stack([rng.uniform(-1.1, -0.5, 300), rng.uniform(0.4, 1.0, 300)])
    value, slope = joint_map(q)
    for k in range(2):
        knots = lower[k] + step * np.arange(40)
        np.testing.assert_allclose(value[:, k], np.interp(q[:, k], knots, joint_map.values[k]), atol=1e-18)
        inside = (q[:, k] > knots[0]) & (q[:, k] < knots[-1])
        eps = 1e-7
        numeric = (joint_map(q + eps)[0][:, k] - joint_map(q - eps)[0][:, k]) / (2 * eps)
        np.testing.assert_allclose(slope[inside, k], numeric[inside], rtol=1e-5, atol=1e-12)
        assert not slope[~inside, k].any()
    assert (q[:, 0] < -1.0).any() and (q[:, 0] > -0.61).any()  # the draw does leave the map
    for row in range(len(q)):  # one configuration takes a path of Python floats: the same bits
        one = joint_map(q[row])
        assert np.array_equal(one[0], value[row]) and np.array_equal(one[1], slope[row])


def test_joint_map_turns_the_joints(elastic):
    """Mapped joint errors are joint-angle shifts, on the batch and single-pose paths alike."""
    rng = np.random.default_rng(6)
    chain = elastic.chain
    lower = np.where(np.isfinite(chain.lower), chain.lower, -np.pi)
    joint_map = JointMap(lower, 0.05, rng.normal(scale=2e-4, size=(chain.dof, 300)))
    model = replace(elastic, joint_map=joint_map)
    q = joints(chain, 20, seed=4)
    np.testing.assert_allclose(model.fk(q), elastic.fk(q + joint_map(q)[0]), atol=1e-14)
    _single_paths_agree(model, q)
    assert not model.is_rigid


def test_the_compiled_cyclic_errors_are_the_batch_paths(elastic):
    """One pose's cyclic joint errors by the kernel's angle-addition recurrence, 40 harmonics a joint (what a
    real UR10's stage holds), against the batch path's complex exponentials at 200 configurations."""
    rng = np.random.default_rng(9)
    model = replace(elastic, joint_error=rng.normal(0.0, 4e-5, (elastic.dof, 40, 2)))
    q = joints(elastic.chain, 200, seed=8) * 3.0  # beyond ±π too: joints that turn more than once
    batch = model._joint_errors(q, slopes=False)[0]
    single = np.array([fk_kernel.cyclic_errors(row, model._cyclic_coefficients) for row in q])
    np.testing.assert_allclose(single, batch, rtol=0, atol=1e-15)
    np.testing.assert_allclose(
        np.array([model.corrected_joints(row) for row in q]), model.corrected_joints(q), atol=1e-15
    )
