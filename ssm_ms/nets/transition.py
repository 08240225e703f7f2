"""Residual transition models ``f``: ``x[t+1] = x[t] + h(x[t])``, or ``x[t+1] = x[t] + h(x[t], u[t])`` for a
system driven by inputs.

Both take and return ``[N, state_dim]`` (with ``input_dim > 0`` also ``u [N, input_dim]``: ``f(x, u)``); any
``nn.Module`` with that contract works as ``f``, its ``input_dim`` attribute (0 when absent) saying whether it
takes inputs. ``input_dim: 0``, the default, is the autonomous model of the paper, with the same parameters.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from ssm_ms.nets.linear import NarrowLinear

# SSM-LL's first beta layer is a NarrowLinear (same parameters and values, its weight gradient formed as x^T dy) where
# its input width is at most this: faster at the widths measured up to 10 (Lorenz's 3, the pendulum's 10), slower from
# 12 on (benchmarks/results/narrow_linear.md: an AMD EPYC and an Intel Xeon; docs/performance.md).
NARROW_MAX = 10


def _check_input(module: nn.Module, u: torch.Tensor | None, x: torch.Tensor) -> None:
    if (u is None) != (module.input_dim == 0):
        raise ValueError(
            f"{type(module).__name__} with input_dim={module.input_dim} "
            + ("needs inputs u [N, input_dim]: f(x, u)" if u is None else "takes no inputs: f(x)")
        )
    if u is not None and (u.shape[:-1] != x.shape[:-1] or u.shape[-1] != module.input_dim):
        raise ValueError(f"u must be [N, {module.input_dim}] beside x {tuple(x.shape)}, got {tuple(u.shape)}")


class LocallyLinearTransition(nn.Module):
    """SSM-LL: ``f(x) = x + sum_k beta_k(x) A_k x``; with inputs ``f(x, u) = x + sum_k beta_k(x, u) (A_k x + B_k u)``.

    ``beta`` is a one-hidden-layer ReLU network (of ``[x, u]`` with inputs) with a softmax output over
    ``n_matrices`` pairs ``(A_k, B_k)`` (``state_dim x state_dim``, ``state_dim x input_dim``): locally the system
    is linear in state and input, ``x[t+1] = A(x, u) x + B(x, u) u``, its matrices mixed by where it is and what
    drives it. All ``A_k x + B_k u`` come out of one matrix product ``[x, u] @ [A_1 B_1; ...; A_K B_K]^T``, then
    are mixed by ``beta``: cheaper than forming the mixed matrix per sample. With ``input_dim = 0`` (the paper's
    model) the ``B_k`` and ``u`` are absent: same parameters, same values.
    """

    def __init__(self, state_dim: int, n_matrices: int = 32, hidden: int = 1024, input_dim: int = 0):
        super().__init__()
        if state_dim < 1 or n_matrices < 1 or hidden < 1 or input_dim < 0:
            raise ValueError(
                f"state_dim, n_matrices and hidden must be >= 1 and input_dim >= 0, got {state_dim}, "
                f"{n_matrices}, {hidden}, {input_dim}"
            )
        self.state_dim, self.n_matrices, self.input_dim = state_dim, n_matrices, input_dim
        width = state_dim + input_dim
        self.beta = nn.Sequential(
            (NarrowLinear if width <= NARROW_MAX else nn.Linear)(width, hidden),
            nn.ReLU(inplace=True),
            nn.Linear(hidden, n_matrices),
            nn.Softmax(dim=-1),
        )
        # [K * d, d]: row block k is A_k; [K * d, m]: row block k is B_k. Uniform(-1/sqrt(K d), 1/sqrt(K d)), like
        # a Linear(K d -> d).
        bound = 1.0 / (n_matrices * state_dim) ** 0.5
        self.matrices = nn.Parameter(torch.empty(n_matrices * state_dim, state_dim).uniform_(-bound, bound))
        if input_dim:
            self.input_matrices = nn.Parameter(torch.empty(n_matrices * state_dim, input_dim).uniform_(-bound, bound))

    def forward(self, x: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        _check_input(self, u, x)
        if u is None:
            beta = self.beta(x)  # [N, K]
            ax = x @ self.matrices.t()
        else:
            beta = self.beta(torch.cat([x, u], dim=-1))
            ax = x @ self.matrices.t() + u @ self.input_matrices.t()
        ax = ax.view(*x.shape[:-1], self.n_matrices, self.state_dim)  # [N, K, d]
        return x + (beta.unsqueeze(-2) @ ax).squeeze(-2)

    def _beta(self, x: torch.Tensor, u: torch.Tensor | None) -> torch.Tensor:
        _check_input(self, u, x)
        return self.beta(x if u is None else torch.cat([x, u], dim=-1))

    def matrix(self, x: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        """The local linear map ``I + sum_k beta_k(x, u) A_k`` at ``x`` (and ``u``): ``[N, d, d]``."""
        a = self.matrices.view(self.n_matrices, self.state_dim, self.state_dim)
        eye = torch.eye(self.state_dim, dtype=x.dtype, device=x.device)
        return eye + torch.einsum("nk,kij->nij", self._beta(x, u), a)

    def input_matrix(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """The local input map ``sum_k beta_k(x, u) B_k`` at ``(x, u)``: ``[N, d, m]`` (so that
        ``f(x, u) = matrix(x, u) x + input_matrix(x, u) u``; not the Jacobian, which also differentiates beta)."""
        b = self.input_matrices.view(self.n_matrices, self.state_dim, self.input_dim)
        return torch.einsum("nk,kij->nij", self._beta(x, u), b)


ACTIVATIONS = {"relu": nn.ReLU, "tanh": nn.Tanh}


def mlp(width: int, hidden: Sequence[int], out: int, activation: str) -> nn.Sequential:
    """``width -> hidden... -> out``: linear layers with ``activation`` between them, none after the last."""
    if activation not in ACTIVATIONS:
        raise ValueError(f"activation must be one of {sorted(ACTIVATIONS)}, got {activation!r}")
    layers: list[nn.Module] = []
    for h in hidden:
        layers += [nn.Linear(width, h), ACTIVATIONS[activation]()]
        width = h
    return nn.Sequential(*layers, nn.Linear(width, out))


class FullyConnectedTransition(nn.Module):
    """SSM-FC: ``f(x) = x + MLP(x)``, hidden layers of the given widths; with inputs ``f(x, u) = x + MLP([x, u])``.

    ``activation``: ``"relu"`` (the paper's) or ``"tanh"``; ``linear``: add a linear map of ``[x, u]``, ``f = x +
    W [x, u] + MLP([x, u])`` (``W`` starts at zero: the same function at initialisation), the form of deepSI's SUBNET
    transition (a linear part beside the network, there without the identity); ``identity_init``: the MLP's last
    layer starts at zero, so that ``f`` starts as the identity map (default: PyTorch's initialisation, the paper's);
    ``residual=False`` (with ``linear``): no identity, ``f = W [x, u] + MLP([x, u])`` with ``W`` at PyTorch's
    initialisation: SUBNET's transition (whose biases start at zero). On Silverbox, with ``MLPReadout`` and Adam at a
    constant 1e-3, it left the ~1 mV plateau where the identity form stalled (results/benchmarks/silverbox.notes.md).
    On Cascaded Tanks the default initialisation stalled at a training fit of ~1 (the data's variance) in every seed
    run on AMD EPYC, where ``identity_init`` trained (results/benchmarks/cascaded_tanks.notes.md)."""

    def __init__(
        self,
        state_dim: int,
        hidden: Sequence[int] = (512, 512, 512),
        input_dim: int = 0,
        activation: str = "relu",
        linear: bool = False,
        identity_init: bool = False,
        residual: bool = True,
    ):
        super().__init__()
        if state_dim < 1 or any(h < 1 for h in hidden) or input_dim < 0:
            raise ValueError(
                f"state_dim and hidden widths must be >= 1 and input_dim >= 0, got {state_dim}, "
                f"{list(hidden)}, {input_dim}"
            )
        if not residual and not linear:
            raise ValueError("residual=False keeps f = W [x, u] + MLP([x, u]): it needs linear=True")
        self.state_dim, self.input_dim, self.residual = state_dim, input_dim, residual
        self.mlp = mlp(state_dim + input_dim, hidden, state_dim, activation)
        if identity_init:
            nn.init.zeros_(self.mlp[-1].weight)
            nn.init.zeros_(self.mlp[-1].bias)
        self.linear: nn.Linear | None = None
        if linear:
            self.linear = nn.Linear(state_dim + input_dim, state_dim, bias=False)
            if residual:
                nn.init.zeros_(self.linear.weight)

    def forward(self, x: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        _check_input(self, u, x)
        xu = x if u is None else torch.cat([x, u], dim=-1)
        out = x + self.mlp(xu) if self.residual else self.mlp(xu)
        return out if self.linear is None else out + self.linear(xu)
