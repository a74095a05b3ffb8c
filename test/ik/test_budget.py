"""solve_many keeps a total time budget across its 65+ seeds and the refinements."""

from __future__ import annotations

import time

import numpy as np
import torch

from hybrid_kinematics_ros.calibration.nets import ResidualNet
from hybrid_kinematics_ros.ik.solver import IKOptions, IKSolver
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.model.hybrid import HybridModel


def test_solve_many_holds_a_total_budget():
    """A wide residual net makes each hybrid Jacobian cost milliseconds, and a per-solution budget of 10 s
    never binds: only the request's deadline can end the search early."""
    chain = load_robot_config("ur10").chain
    torch.manual_seed(0)
    net = torch.jit.script(ResidualNet("mlp:512x4", chain.lower, chain.upper, np.zeros(3), np.full(3, 0.02)))
    solver = IKSolver(HybridModel(chain, {"position": net}), IKOptions(timeout_s=10.0))
    q = np.array([0.3, -1.0, 1.2, -0.5, 0.7, 0.2])
    target = solver.model.fk_single(q)
    free = solver.solve_many(target, q, 16)
    assert free and all(r.success for r in free)
    budget = 0.05
    start = time.perf_counter()
    held = solver.solve_many(target, q, 16, deadline=start + budget)
    elapsed = time.perf_counter() - start
    # one step in flight may overrun the deadline; a loaded machine makes a step slow, never 65 of them
    assert elapsed < budget + 2.0, elapsed
    assert len(held) <= len(free) and all(r.success for r in held)
    # a deadline already past: no seed is tried
    assert solver.solve_many(target, q, 16, deadline=time.perf_counter()) == []
