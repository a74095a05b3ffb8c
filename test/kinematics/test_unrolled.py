"""The generated float code of one configuration's FK against the batch FK, on every kind of chain."""

from __future__ import annotations

import numpy as np
import pytest

from hybrid_kinematics_ros.kinematics import fk
from hybrid_kinematics_ros.kinematics.chain import chain_from_urdf
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.kinematics.se3 import matrix_from_pose
from hybrid_kinematics_ros.kinematics.unrolled import unrolled_fk
from hybrid_kinematics_ros.model.hybrid import HybridModel
from test.kinematics.test_chain import MIXED


def assert_matches_batch(chain, q: np.ndarray) -> None:
    rows_fk = unrolled_fk(chain)
    got = np.array([rows_fk(qi.tolist()) for qi in q])
    np.testing.assert_allclose(got, fk.fk(chain, q)[:, :3], atol=1e-12, rtol=0)


@pytest.mark.parametrize("robot", ["ur10", "rx160"])
def test_every_embedded_robot_with_and_without_a_tool(robot):
    chain = load_robot_config(robot).chain
    rng = np.random.default_rng(1)
    q = rng.uniform(-2 * np.pi, 2 * np.pi, (300, chain.dof))
    assert_matches_batch(chain, q)
    quat = rng.normal(size=4)
    assert_matches_batch(chain.with_tool(matrix_from_pose(rng.normal(0, 0.2, 3), quat / np.linalg.norm(quat))[0]), q)


def test_prismatic_and_continuous_joints_odd_axes_and_fixed_joints(tmp_path):
    path = tmp_path / "mixed.urdf"
    path.write_text(MIXED)
    chain = chain_from_urdf(path, "world", "tip")
    assert not chain.revolute.all()
    rng = np.random.default_rng(2)
    q = np.column_stack([rng.uniform(-1.5, 2, 300), rng.uniform(-3, 3, 300), rng.uniform(-9, 9, 300)])
    assert_matches_batch(chain, q)


@pytest.mark.parametrize("joints", range(1, 7))
def test_every_chain_length(joints):
    chain = chain_from_urdf(load_robot_config("ur10").chain.urdf_text, "base_link", f"link_{joints}")
    assert_matches_batch(chain, np.random.default_rng(joints).uniform(-np.pi, np.pi, (50, joints)))


def test_a_wrong_joint_count_raises_and_non_finite_constants_fall_back():
    chain = load_robot_config("ur10").chain
    with pytest.raises(ValueError):
        unrolled_fk(chain)([0.0] * 5)
    pre = chain.pre.copy()
    pre[2, 0, 3] = np.nan
    assert unrolled_fk(chain.with_geometry(pre, chain.post)) is None


def test_the_model_uses_it_where_numpy_is_not_needed_and_fk_single_elsewhere(ur10, trained):
    q = np.random.default_rng(3).uniform(-1, 1, (20, 6))
    analytic = HybridModel.analytic_only(ur10.chain)
    corrected = HybridModel.load(trained[0])
    for qi in q:
        np.testing.assert_allclose(analytic.fk_rows(qi.tolist()), analytic.fk_single(qi)[:3], atol=1e-12, rtol=0)
        np.testing.assert_array_equal(corrected.fk_rows(qi.tolist()), corrected.fk_single(qi)[:3])  # nets: numpy
        reference = fk.fk_single(corrected.chain, qi)[:3]
        np.testing.assert_allclose(corrected.fk_rows(qi.tolist(), analytic=True), reference, atol=1e-12, rtol=0)
