"""Sparse updates of the shooting-node table: a row-wise ("lazy") Adam.

With ``node_optimizer: sparse`` only the rows of the trajectories in the batch change. Each row keeps
its own Adam moments and its own step count, so a trajectory's nodes follow exactly the Adam
iterates of their own gradient sequence (one step each time the trajectory is in a batch), and rows
outside the batch stay bit-for-bit unchanged. (``torch.optim.SparseAdam`` uses one step count for the
whole table: a row seen for the first time late in training would get a first step ~3x larger than
Adam's.) The moments live in the model optimizer's state for the node parameter, so the schedule's
optimizer reset clears them, its learning-rate drops apply to the node group, and checkpoints carry
them.
"""

from __future__ import annotations

from typing import Any

import torch


def row_adam_(
    weight: torch.Tensor,
    state: dict[str, Any],
    index: torch.Tensor,
    grad: torch.Tensor,
    lr: float,
    betas: tuple[float, float] = (0.9, 0.999),
    eps: float = 1e-8,
) -> None:
    """One Adam step on the rows ``index`` of ``weight`` (in place), with per-row moments and steps.

    ``grad`` is ``[len(index), weight.shape[1]]``; repeated indices have their gradients summed.
    ``state`` holds ``exp_avg``, ``exp_avg_sq`` (shaped like ``weight``) and ``step`` (Adam's step count,
    here one per row), created at the first call.
    """
    if "exp_avg" not in state:
        state["exp_avg"] = torch.zeros_like(weight)
        state["exp_avg_sq"] = torch.zeros_like(weight)
        state["step"] = torch.zeros(weight.shape[0], dtype=weight.dtype, device=weight.device)
    if state["step"].device != weight.device:  # torch's optimizer loading leaves "step" where it was saved
        state["step"] = state["step"].to(weight.device)
    rows, inverse = torch.unique(index, return_inverse=True)
    if len(rows) != len(index):
        grad = grad.new_zeros((len(rows), grad.shape[1])).index_add_(0, inverse, grad)
    else:
        grad = grad.new_empty(grad.shape).index_copy_(0, inverse, grad)
    beta1, beta2 = betas
    step = state["step"][rows] + 1
    exp_avg = state["exp_avg"][rows].mul_(beta1).add_(grad, alpha=1 - beta1)
    exp_avg_sq = state["exp_avg_sq"][rows].mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
    # torch.optim.Adam's formula: p -= lr / bc1 * m / (sqrt(v) / sqrt(bc2) + eps)
    bc1 = 1 - beta1**step
    bc2_sqrt = (1 - beta2**step).sqrt()
    denom = (exp_avg_sq.sqrt() / bc2_sqrt[:, None]).add_(eps)
    weight[rows] = weight[rows] - (lr / bc1)[:, None] * exp_avg / denom
    state["exp_avg"][rows] = exp_avg
    state["exp_avg_sq"][rows] = exp_avg_sq
    state["step"][rows] = step


def node_group(optimizer: torch.optim.Optimizer, weight: torch.Tensor) -> dict[str, Any]:
    """The parameter group that holds the node table alone, with Adam's settings; else a clear error."""
    groups = [g for g in optimizer.param_groups if any(p is weight for p in g["params"])]
    if not isinstance(optimizer, torch.optim.Adam) or len(groups) != 1 or len(groups[0]["params"]) != 1:
        raise ValueError(
            f"node_optimizer='sparse' updates the node table row by row with Adam, in a parameter group of its "
            f"own (learning rate node_lr), but the optimizer in use is a {type(optimizer).__name__} over "
            "all parameters (an `optimizer:` section in the config replaces the model's own): remove that "
            "section, or use node_optimizer: dense"
        )
    return groups[0]


# ------------------------------------------------------------------------------------------------- the strategies
class DenseNodes:
    """The paper's node update: the node table is a parameter like any other, in the model's one Adam (momentum moves
    every row at every step)."""

    own_group = False  # the nodes need no parameter group of their own (unless given their own learning rate)

    def prepare(self, weight: torch.Tensor) -> None:
        """The node table ``weight`` just made."""

    def rows(self, weight: torch.Tensor, index: torch.Tensor) -> torch.Tensor | None:
        """The rows ``index`` as a leaf of their own, where they are updated outside autograd (else None)."""
        return None

    def check(self, optimizers: list[torch.optim.Optimizer], weight: torch.Tensor) -> None:
        """At the fit's start: the optimizers can update the table this way."""

    def step(self, optimizer: torch.optim.Optimizer, weight: torch.Tensor, index: torch.Tensor, grads: torch.Tensor):
        """Before the optimizer's step: update the rows ``index`` from their gradients ``grads`` (nothing here)."""


class SparseNodes(DenseNodes):
    """Only the batch's rows change, each by its own Adam (:func:`row_adam_`), outside autograd and DDP."""

    own_group = True

    def prepare(self, weight: torch.Tensor) -> None:
        weight.requires_grad_(False)  # updated row by row, outside autograd and DDP

    def rows(self, weight: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        return weight.detach()[index].requires_grad_()  # the batch's rows as a leaf: their gradient alone

    def check(self, optimizers: list[torch.optim.Optimizer], weight: torch.Tensor) -> None:
        for optimizer in optimizers:
            node_group(optimizer, weight)  # a clear error for an optimizer replaced by the config

    @torch.no_grad()
    def step(self, optimizer: torch.optim.Optimizer, weight: torch.Tensor, index: torch.Tensor, grads: torch.Tensor):
        group = node_group(optimizer, weight)
        row_adam_(weight, optimizer.state[weight], index, grads, group["lr"], group["betas"], group["eps"])


NODE_UPDATES = {"dense": DenseNodes, "sparse": SparseNodes}  # model.node_optimizer -> its strategy
