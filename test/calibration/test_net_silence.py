"""A residual net must beat correcting nothing on validation, or it is silenced: the nets never make the
stage before them worse where it can be checked."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from hybrid_kinematics_ros.calibration import train


def _job(sign: float) -> train.NetJob:
    rng = np.random.default_rng(0)
    q_train, q_val = rng.uniform(-2.0, 2.0, (600, 6)), rng.uniform(-2.0, 2.0, (150, 6))

    def residual(q: np.ndarray) -> np.ndarray:  # m: a smooth error of joint 2, 0.1 mm
        return 1e-4 * np.column_stack([np.sin(2 * q[:, 1]), np.cos(q[:, 1]), np.sin(q[:, 1] + q[:, 2])])

    preset = replace(train.PRESETS["fast"], arch="mlp:32x2:silu", batch=64, max_epochs=60)
    lower, upper = np.full(6, -2.0), np.full(6, 2.0)
    # sign -1: validation says the opposite of training, so whatever the net learns makes it worse there
    return train.NetJob(
        "position", preset, q_train, residual(q_train), q_val, sign * residual(q_val), lower, upper, None, 60.0, 0, 6
    )


def test_a_net_that_only_hurts_on_validation_is_silenced():
    job = _job(-1.0)
    net, history = train.train_net(job)
    assert history[-1]["silenced"]
    out = net(torch.tensor(job.q_val)).detach().numpy()
    assert not out.any()  # exactly zero: the model serves the stage before the nets


def test_a_net_that_helps_is_kept():
    job = _job(1.0)
    net, history = train.train_net(job)
    assert "silenced" not in history[-1]
    nothing = np.linalg.norm(job.y_val, axis=1).mean()
    err = np.linalg.norm(net(torch.tensor(job.q_val)).detach().numpy() - job.y_val, axis=1).mean()
    assert err < 0.5 * nothing


class _Fixed(torch.nn.Module):
    """A stand-in for a trained net: a fixed answer for each validation pair (its index in ``q[:, 0]``)."""

    def __init__(self, answers: np.ndarray):
        super().__init__()
        self.register_buffer("answers", torch.tensor(answers))

    def forward(self, q: torch.Tensor) -> torch.Tensor:
        return self.answers[q[:, 0].long()]


def test_the_gate_counts_a_block_of_the_recording_once():
    """Along a recording, neighbours share their errors: a net that helps on half of the validation blocks
    and hurts on the other half helps on average, by less than the blocks' spread. Counted by single pairs
    (1,000 of them, 100 a block) that average looks certain; counted by blocks it is noise, and the stage wins."""
    blocks, per_block = 10, 100
    y = np.tile([[1e-4, 0.0, 0.0]], (blocks * per_block, 1))  # what the stage leaves: 0.1 mm
    # the net's error per block, as a share of y: 0 (it fixes the block) or 1.8 (it overshoots)
    share = np.repeat(np.where(np.arange(blocks) % 2 == 0, 0.0, 1.8), per_block)
    answers = y * (1.0 - share[:, None])
    q = torch.tensor(np.column_stack([np.arange(len(y)), np.zeros((len(y), 5))]), dtype=torch.float64)
    net = _Fixed(answers)
    diff = np.linalg.norm(answers - y, axis=1) - np.linalg.norm(y, axis=1)
    assert diff.mean() < -3 * diff.std(ddof=1) / np.sqrt(len(diff))  # by single pairs: beats nothing
    assert not train._beats_nothing(net, q, torch.tensor(y))
    # the same mean gain, the same in every block: the net is kept
    steady = y * (1.0 - np.full(len(y), 0.9)[:, None])
    assert train._beats_nothing(_Fixed(steady), q, torch.tensor(y))
