"""The compiled kernels take the chain and the stage as plain arrays, in an order their named operand tuples
(``fk_kernel.ChainOperands``, ``fk_kernel.ElasticOperands``) spell out: each kernel's parameters carry those
names in that order, so reordering one side without the other fails here, not in a pose."""

from __future__ import annotations

import inspect

import numpy as np

from hybrid_kinematics_ros.ik import lm_kernel, round_kernel, valley_kernel
from hybrid_kinematics_ros.kinematics import fk_kernel
from hybrid_kinematics_ros.kinematics.elastic import ElasticChain
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.simulation.truth import TrueRobot

CHAIN = list(fk_kernel.ChainOperands._fields)


def parameters(kernel) -> list[str]:
    return list(inspect.signature(kernel.py_func).parameters)


def test_every_kernel_that_takes_the_chain_names_its_operands_in_order():
    kernels = [fk_kernel.tip_pose, fk_kernel.tip_pose_and_jacobian]
    kernels += [lm_kernel.lm_steps, round_kernel.error_and_compensated, round_kernel.chord_step]
    kernels += [valley_kernel.onto, valley_kernel.advance, valley_kernel.settle_step, valley_kernel.along_one]
    for kernel in kernels:
        names = parameters(kernel)
        start = names.index("generators")
        # lm_steps's joint limits have their own ``revolute``: the chain's is ``chain_revolute`` there
        assert [n.removeprefix("chain_") for n in names[start : start + 4]] == CHAIN, kernel.__name__
    assert parameters(fk_kernel.elastic_pose)[1:-1] == list(fk_kernel.ElasticOperands._fields)


def test_the_named_operands_give_the_poses_of_the_batched_code():
    cfg = load_robot_config("ur10")
    stage: ElasticChain = TrueRobot.from_config(cfg).elastic
    q = np.random.default_rng(0).uniform(cfg.chain.lower, cfg.chain.upper, (20, cfg.chain.dof))
    ops = stage._kernel_operands
    assert isinstance(ops, fk_kernel.ElasticOperands) and isinstance(cfg.chain.kernel_operands, fk_kernel.ChainOperands)
    q_eff = stage.corrected_joints(q)
    single = [fk_kernel.elastic_pose(np.ascontiguousarray(x), *ops, False)[0] for x in q_eff]
    np.testing.assert_allclose(single, stage.fk(q), atol=1e-12)
