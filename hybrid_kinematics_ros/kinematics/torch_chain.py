"""The chain's FK in torch: differentiable and scriptable, in its own module so that what needs numpy FK
alone (the recorder, the simulated cell, most of the CLI) starts without importing torch (about a second)."""

from __future__ import annotations

import torch

from hybrid_kinematics_ros.kinematics.chain import Chain
from hybrid_kinematics_ros.kinematics.fk import transposed_generators


class TorchChain(torch.nn.Module):
    """The chain's constants as torch buffers: differentiable FK, scriptable, any float dtype.

    Uses the same transposed-frame layout as the numpy path (see ``_frames_block``).
    """

    def __init__(self, chain: Chain, dtype: torch.dtype = torch.float64) -> None:
        super().__init__()
        self.register_buffer("g0", torch.tensor(chain.generators[0][:, :3], dtype=dtype))  # (3 c, 3 i, 4 j)
        self.register_buffer("gt", torch.tensor(transposed_generators(chain), dtype=dtype))
        self.register_buffer("post_t", torch.tensor(chain.post.T.copy(), dtype=dtype))
        self.register_buffer("axes", torch.tensor(chain.axes, dtype=dtype))
        self.register_buffer("revolute", torch.tensor(chain.revolute))
        self.dof = chain.dof

    def _coefficients(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        a = torch.where(self.revolute, torch.sin(q), q).T.contiguous()
        b = torch.where(self.revolute, 1.0 - torch.cos(q), torch.zeros_like(q)).T.contiguous()
        return a, b

    def _frames(self, q: torch.Tensor, every: bool) -> list[torch.Tensor]:
        """Transposed frames ``(4, 3, B)`` of each joint (if ``every``) and of the tip (always last)."""
        a, b = self._coefficients(q)
        nb = q.shape[0]
        g0 = self.g0
        x = (g0[0, :, :, None] + a[0] * g0[1, :, :, None] + b[0] * g0[2, :, :, None]).permute(1, 0, 2)
        frames = [x] if every else []
        for k in range(1, self.dof):
            y = (self.gt[k] @ x.reshape(4, 3 * nb)).reshape(3, 4, 3, nb)
            x = y[0] + a[k] * y[1] + b[k] * y[2]
            if every:
                frames.append(x)
        frames.append((self.post_t @ x.reshape(4, 3 * nb)).reshape(4, 3, nb))
        return frames

    @staticmethod
    def _homogeneous(x: torch.Tensor) -> torch.Tensor:
        """``(..., B, 4, 4)`` from transposed frames ``(..., 4, 3, B)``."""
        top = x.movedim(-1, -3).transpose(-1, -2)
        bottom = torch.zeros_like(top[..., :1, :])
        bottom[..., 0, 3] = 1.0
        return torch.cat([top, bottom], dim=-2)

    def forward(self, q: torch.Tensor) -> torch.Tensor:
        """Tip poses ``(B, 4, 4)``."""
        return self._homogeneous(self._frames(q, every=False)[-1])

    def joint_frames(self, q: torch.Tensor) -> torch.Tensor:
        """``(B, n + 1, 4, 4)``, as the numpy :func:`joint_frames`."""
        return self._homogeneous(torch.stack(self._frames(q, every=True), dim=0)).transpose(0, 1)
