"""solve_many keeps a total time budget across its 65+ seeds and the refinements."""

from __future__ import annotations

import subprocess
import sys
import time

import numpy as np
import torch

from hybrid_kinematics_ros.calibration.nets import InputSpan, ResidualNet
from hybrid_kinematics_ros.ik.solver import IKOptions, IKSolver
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.model.hybrid import HybridModel


def test_solve_many_holds_a_total_budget():
    """A wide residual net makes each hybrid Jacobian cost milliseconds, and a per-solution budget of 10 s
    never binds: only the request's deadline can end the search early."""
    chain = load_robot_config("ur10").chain
    torch.manual_seed(0)
    net = torch.jit.script(
        ResidualNet("mlp:512x4", InputSpan(chain.lower, chain.upper), (np.zeros(3), np.full(3, 0.02)))
    )
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


WARM_SCRIPT = """
import numba, numpy as np, torch
from hybrid_kinematics_ros.calibration.nets import InputSpan, ResidualNet
from hybrid_kinematics_ros.ik.solver import IKOptions, IKSolver
from hybrid_kinematics_ros.ik import lm_kernel, round_kernel
from hybrid_kinematics_ros.kinematics import fk_kernel, robot_config
from hybrid_kinematics_ros.model.hybrid import HybridModel
chain = robot_config.load_robot_config("ur10").chain
torch.manual_seed(0)
net = torch.jit.script(ResidualNet("mlp:32x2", InputSpan(chain.lower, chain.upper), (np.zeros(3), np.full(3, 2e-4))))
solver = IKSolver(HybridModel(chain, {"position": net})).warm_up()
kernels = [getattr(m, n) for m in (lm_kernel, round_kernel, fk_kernel) for n in dir(m)]
kernels = [k for k in kernels if isinstance(k, numba.core.registry.CPUDispatcher)]
loaded = sum(len(k.signatures) for k in kernels)
rng = np.random.default_rng(4)
q = rng.uniform(chain.lower, chain.upper, (10, 6))
q[:, 4] = 0.0  # the wrist straight: near a singularity of the URDF model, the path regular targets do not take
for target in solver.model.fk(q):
    solver.solve(target)
print(sum(len(k.signatures) for k in kernels) - loaded)
"""


def test_warm_up_loads_the_compiled_kernels_before_the_first_request():
    """Loading a compiled kernel takes tens of milliseconds (on a fresh checkout, seconds to compile), half a
    request's budget: ``warm_up`` loads the compiled IK and FK kernels, the URDF model's pose with them, which
    regular targets never need and near-singular ones do, so that requests load none. In a fresh process, where
    no other test loaded them first. (The batched hybrid FK's TorchScript path is loaded with them; numba's
    signatures cannot show that.)"""
    out = subprocess.run([sys.executable, "-c", WARM_SCRIPT], capture_output=True, text=True, check=False)
    assert out.returncode == 0 and out.stdout.strip() == "0", out.stdout + out.stderr
