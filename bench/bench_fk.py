"""Forward kinematics speed on the embedded UR10: batched numpy and torch, and one configuration.

Pinocchio is the reference, measured in the same run: a Python loop over the batch, and a single call.
"""

from __future__ import annotations

import time

import numpy as np
import pinocchio as pin
import torch

from bench.report import table, write_section
from hybrid_kinematics_ros.kinematics import fk
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.kinematics.torch_chain import TorchChain

BATCH = 100_000
SINGLE = 20_000


def best_of(fn, repeats: int = 5) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    torch.set_num_threads(1)
    cfg = load_robot_config("ur10")
    chain = cfg.chain
    q = np.random.default_rng(0).uniform(-np.pi, np.pi, (BATCH, chain.dof))
    model = pin.buildModelFromUrdf(str(cfg.urdf_path))
    data = model.createData()
    frame = model.getFrameId(cfg.tip_link)

    def pin_loop(qs):
        for qi in qs:
            pin.framesForwardKinematics(model, data, qi)
            data.oMf[frame].homogeneous  # noqa: B018 - materialise the pose as our FK does

    t_np = best_of(lambda: fk.fk(chain, q))
    tc = TorchChain(chain)
    qt = torch.tensor(q)
    with torch.no_grad():
        t_torch = best_of(lambda: tc(qt))
    t_pin = best_of(lambda: pin_loop(q), repeats=2)

    qs = q[:SINGLE]
    t_single = best_of(lambda: [fk.fk_single(chain, qi) for qi in qs], repeats=3) / SINGLE
    t_pin_single = best_of(lambda: pin_loop(qs), repeats=3) / SINGLE

    rows = [
        ["numpy `fk` (float64)", BATCH / t_np, (BATCH / t_np) / (BATCH / t_pin)],
        ["torch `TorchChain` (float64, 1 thread)", BATCH / t_torch, (BATCH / t_torch) / (BATCH / t_pin)],
        ["pinocchio, Python loop", BATCH / t_pin, 1.0],
    ]
    body = (
        f"Batched FK of {BATCH:,} random UR10 configurations (best of 5). Target: at least 1,000,000 poses/s.\n\n"
        + table(["method", "poses/s", "ratio to pinocchio loop"], rows)
        + "\n\nSingle configuration, `fk_single` (compiled, `kinematics/fk_kernel.py`): "
        f"**{t_single * 1e6:.1f} µs** per call; pinocchio `framesForwardKinematics` from Python: "
        f"{t_pin_single * 1e6:.1f} µs; ratio {t_single / t_pin_single:.2f}. "
        "Target: at most 30 µs."
    )
    write_section("fk", "Forward kinematics speed (foundation)", body)


if __name__ == "__main__":
    main()
