"""Residual transition models ``f``: ``x[t+1] = x[t] + h(x[t])``.

Both take and return ``[N, state_dim]``; any ``nn.Module`` with that contract works as ``f``.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn


class LocallyLinearTransition(nn.Module):
    """SSM-LL: ``f(x) = x + sum_k beta_k(x) A_k x``.

    ``beta`` is a one-hidden-layer ReLU network with a softmax output over ``n_matrices``
    matrices ``A_k`` (``state_dim x state_dim``). All ``A_k x`` come out of one matrix product
    ``x @ [A_1; ...; A_K]^T``, then are mixed by ``beta``: cheaper than forming the mixed matrix
    per sample.
    """

    def __init__(self, state_dim: int, n_matrices: int = 32, hidden: int = 1024):
        super().__init__()
        if state_dim < 1 or n_matrices < 1 or hidden < 1:
            raise ValueError(f"state_dim, n_matrices and hidden must be >= 1, got {state_dim}, {n_matrices}, {hidden}")
        self.state_dim, self.n_matrices = state_dim, n_matrices
        self.beta = nn.Sequential(
            nn.Linear(state_dim, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, n_matrices), nn.Softmax(dim=-1)
        )
        # [K * d, d]: row block k is A_k. Uniform(-1/sqrt(K d), 1/sqrt(K d)), like a Linear(K d -> d).
        bound = 1.0 / (n_matrices * state_dim) ** 0.5
        self.matrices = nn.Parameter(torch.empty(n_matrices * state_dim, state_dim).uniform_(-bound, bound))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        beta = self.beta(x)  # [N, K]
        ax = (x @ self.matrices.t()).view(*x.shape[:-1], self.n_matrices, self.state_dim)  # [N, K, d]
        return x + (beta.unsqueeze(-2) @ ax).squeeze(-2)

    def matrix(self, x: torch.Tensor) -> torch.Tensor:
        """The local linear map ``I + sum_k beta_k(x) A_k`` at ``x``: ``[N, d, d]``."""
        a = self.matrices.view(self.n_matrices, self.state_dim, self.state_dim)
        eye = torch.eye(self.state_dim, dtype=x.dtype, device=x.device)
        return eye + torch.einsum("nk,kij->nij", self.beta(x), a)


class FullyConnectedTransition(nn.Module):
    """SSM-FC: ``f(x) = x + MLP(x)``, ReLU hidden layers of the given widths."""

    def __init__(self, state_dim: int, hidden: Sequence[int] = (512, 512, 512)):
        super().__init__()
        if state_dim < 1 or any(h < 1 for h in hidden):
            raise ValueError(f"state_dim and hidden widths must be >= 1, got {state_dim}, {list(hidden)}")
        self.state_dim = state_dim
        layers: list[nn.Module] = []
        width = state_dim
        for h in hidden:
            layers += [nn.Linear(width, h), nn.ReLU(inplace=True)]
            width = h
        layers.append(nn.Linear(width, state_dim))
        self.mlp = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.mlp(x)
