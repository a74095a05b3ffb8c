"""A served net tuned briefly on a few new poses, held where the parent was trained.

``update`` moves the stage's parameters; what the new poses show beyond them (a smooth change of the
orientation over the working range, say) is the nets' to learn. A few dozen poses cannot train a net, but
they can move one a little: Adam steps on what the new poses still miss, with the net's outputs held at the
parent's training configurations (its ``coverage.npy``) so that the parent's range keeps what the parent
learned there. How far to move is chosen by the caller on held-out blocks of the new poses, from the
checkpoints ``STEPS`` (0: keep the net).
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np
import torch

STEPS = (0, 50, 100, 150, 200)  # the checkpoints a caller chooses among
RATE = 6e-3  # Adam's step size: a couple of hundred steps move a trained net by a fraction of its correction
ANCHORS = 200  # the parent's training configurations that hold the net where it was trained


@dataclass(frozen=True)
class Anchors:
    """The net's inputs ``inputs (A, k)`` at the parent's training configurations and its outputs there."""

    inputs: np.ndarray
    outputs: np.ndarray


def tuned(
    net: torch.jit.ScriptModule,
    inputs: np.ndarray,
    targets: np.ndarray,
    anchors: Anchors,
    steps: tuple[int, ...] = STEPS,
) -> dict[int, torch.jit.ScriptModule]:
    """Copies of ``net`` after each count of ``steps`` towards ``targets (N, 3)`` at ``inputs (N, k)``; the
    loss weighs the targets and the anchors' outputs alike (the mean squared error over each)."""
    net = _copy(net)
    optimiser = torch.optim.Adam(list(net.parameters()), lr=RATE)
    x = torch.as_tensor(np.vstack([inputs, anchors.inputs]))
    wanted = torch.as_tensor(np.vstack([targets, anchors.outputs]))
    each = [np.full(len(rows), 1.0 / len(rows)) for rows in (inputs, anchors.inputs)]
    weight = torch.as_tensor(np.concatenate(each))
    out = {}
    for step in range(max(steps) + 1):
        if step in steps:
            out[step] = _copy(net)
        if step == max(steps):
            break
        optimiser.zero_grad()
        loss = (weight * ((net(x) - wanted) ** 2).sum(dim=1)).sum()
        loss.backward()
        optimiser.step()
    return out


def outputs(net: torch.jit.ScriptModule, inputs: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        return net(torch.as_tensor(inputs)).numpy()


def _copy(net: torch.jit.ScriptModule) -> torch.jit.ScriptModule:
    """A copy with its own parameters, trainable (a deep copy's would be clones, not leaves)."""
    buffer = io.BytesIO()
    torch.jit.save(net, buffer)
    buffer.seek(0)
    return torch.jit.load(buffer)
