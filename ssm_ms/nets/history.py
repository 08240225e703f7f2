"""The node encoder of amortised shooting nodes: the ``history`` samples before a time -> the state at that time.

:class:`HistoryEncoder` maps the measurements ``y [N, H, obs_dim]`` and inputs ``u [N, H, input_dim]`` of the ``H``
samples before time ``t`` (samples ``t - H .. t - 1``) to the state ``x[t] [N, state_dim]``: a linear map of the
flattened history plus an MLP of it (tanh), the encoder of deepSI's SUBNET (Beintema, Toth & Schoukens 2021).
Any ``nn.Module`` with this contract and a ``history`` attribute can be a model's ``node_encoder``
(:class:`~ssm_ms.module.MultipleShootingModule`); ``input_dim`` says whether it reads inputs (0: ``u`` not given).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn


class HistoryEncoder(nn.Module):
    """``x[t] = W h + MLP(h)``, ``h = [y[t-H:t], u[t-H:t]]`` flattened (vector measurements).

    Args:
        state_dim: the latent dimension it outputs.
        obs_dim: measurement components per sample.
        input_dim: inputs per sample (0: an autonomous system, ``u`` not read).
        history: samples read before the state's time, ``H >= 1`` (at test, the state estimate of a recording
            reads the last ``H`` of its ``n_init`` samples, so ``H <= n_init``).
        hidden: the MLP's hidden widths (deepSI's default: two layers of 64).
    """

    def __init__(
        self, state_dim: int, obs_dim: int, input_dim: int = 0, history: int = 20, hidden: Sequence[int] = (64, 64)
    ):
        super().__init__()
        if state_dim < 1 or obs_dim < 1 or input_dim < 0 or history < 1 or any(h < 1 for h in hidden):
            raise ValueError(
                f"state_dim, obs_dim, history and the hidden widths must be >= 1 and input_dim >= 0, got {state_dim}, "
                f"{obs_dim}, {history}, {list(hidden)}, {input_dim}"
            )
        self.state_dim, self.obs_dim, self.input_dim, self.history = state_dim, obs_dim, input_dim, history
        width = history * (obs_dim + input_dim)
        self.linear = nn.Linear(width, state_dim)
        layers: list[nn.Module] = []
        for h in hidden:
            layers += [nn.Linear(width, h), nn.Tanh()]
            width = h
        layers.append(nn.Linear(width, state_dim))
        self.mlp = nn.Sequential(*layers)

    def forward(self, y: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        """``y [N, history, obs_dim]`` (``u [N, history, input_dim]`` where ``input_dim > 0``) -> ``[N, state_dim]``."""
        n, h = self.history, self.obs_dim
        if y.dim() != 3 or tuple(y.shape[1:]) != (n, h):
            raise ValueError(f"the node encoder reads y [N, {n}, {h}] (history, obs_dim), got {tuple(y.shape)}")
        parts = [y.reshape(len(y), -1)]
        if self.input_dim:
            if u is None or tuple(u.shape) != (len(y), n, self.input_dim):
                got = None if u is None else tuple(u.shape)
                raise ValueError(f"the node encoder reads u [{len(y)}, {n}, {self.input_dim}] beside y, got {got}")
            parts.append(u.reshape(len(u), -1))
        flat = torch.cat(parts, -1)
        return self.linear(flat) + self.mlp(flat)
