"""The node encoder of amortised shooting nodes: the ``history`` samples before a time -> the state at that time.

:class:`HistoryEncoder` maps the measurements ``y [N, H, *obs]`` and inputs ``u [N, H, input_dim]`` of the ``H``
samples before time ``t`` (samples ``t - H .. t - 1``) to the state ``x[t] [N, state_dim]``: a linear map of the
flattened history plus an MLP of it (tanh), the encoder of deepSI's SUBNET (Beintema, Toth & Schoukens 2021); images
are read first by the paper's per-frame CNN (:class:`~ssm_ms.nets.FrameEncoder`), each frame on its own.
Any ``nn.Module`` with this contract and a ``history`` attribute can be a model's ``node_encoder``
(:class:`~ssm_ms.module.MultipleShootingModule`); ``input_dim`` says whether it reads inputs (0: ``u`` not given).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from ssm_ms.nets.encoder import FrameEncoder


class HistoryEncoder(nn.Module):
    """``x[t] = W h + MLP(h)``, ``h = [c(y[t-H]), .., c(y[t-1]), u[t-H:t]]`` flattened, ``c`` the identity for vector
    measurements and the per-frame CNN for images.

    Args:
        state_dim: the latent dimension it outputs.
        obs_dim: the shape of one measurement: an int (vector components) or ``[C, H, W]`` (images).
        input_dim: inputs per sample (0: an autonomous system, ``u`` not read).
        history: samples read before the state's time, ``H >= 1`` (at test, the state estimate of a recording
            reads the last ``H`` of its ``n_init`` samples, so ``H <= n_init``).
        hidden: the MLP's hidden widths (deepSI's default: two layers of 64).
        frames: the per-frame CNN's preset for images (:class:`~ssm_ms.nets.FrameEncoder`: ``"pendulum"``,
            ``"quad"``, ``"mnist"``); required with image measurements, refused with vectors.
    """

    def __init__(
        self,
        state_dim: int,
        obs_dim: int | Sequence[int],
        input_dim: int = 0,
        history: int = 20,
        hidden: Sequence[int] = (64, 64),
        frames: str | None = None,
    ):
        super().__init__()
        shape = (int(obs_dim),) if isinstance(obs_dim, int) else tuple(int(s) for s in obs_dim)
        if state_dim < 1 or min(shape) < 1 or input_dim < 0 or history < 1 or any(h < 1 for h in hidden):
            raise ValueError(
                f"state_dim, obs_dim, history and the hidden widths must be >= 1 and input_dim >= 0, got {state_dim}, "
                f"{obs_dim}, {history}, {list(hidden)}, {input_dim}"
            )
        if len(shape) not in (1, 3):
            raise ValueError(f"obs_dim is an int (vector components) or [C, H, W] (images), got {list(shape)}")
        if len(shape) == 3 and frames is None:
            raise ValueError(f"images {list(shape)} need the per-frame CNN: set frames, e.g. frames: pendulum")
        if len(shape) == 1 and frames is not None:
            raise ValueError(f"vector measurements ({shape[0]} components) take no per-frame CNN: remove frames")
        self.state_dim, self.obs_shape, self.input_dim, self.history = state_dim, shape, input_dim, history
        self.frames = FrameEncoder(shape, frames) if frames is not None else None
        width = history * ((self.frames.out_features if self.frames is not None else shape[0]) + input_dim)
        self.linear = nn.Linear(width, state_dim)
        layers: list[nn.Module] = []
        for h in hidden:
            layers += [nn.Linear(width, h), nn.Tanh()]
            width = h
        layers.append(nn.Linear(width, state_dim))
        self.mlp = nn.Sequential(*layers)

    def forward(self, y: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        """``y [N, history, *obs]`` (``u [N, history, input_dim]`` where ``input_dim > 0``) -> ``[N, state_dim]``."""
        n, shape = self.history, self.obs_shape
        if tuple(y.shape[1:]) != (n, *shape):
            raise ValueError(
                f"the node encoder reads y [N, {n}, {', '.join(map(str, shape))}] (history, measurement), "
                f"got {tuple(y.shape)}"
            )
        parts = [(self.frames(y) if self.frames is not None else y).reshape(len(y), -1)]
        if self.input_dim:
            if u is None or tuple(u.shape) != (len(y), n, self.input_dim):
                got = None if u is None else tuple(u.shape)
                raise ValueError(f"the node encoder reads u [{len(y)}, {n}, {self.input_dim}] beside y, got {got}")
            parts.append(u.reshape(len(u), -1))
        flat = torch.cat(parts, -1)
        return self.linear(flat) + self.mlp(flat)
