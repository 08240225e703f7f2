"""Continuity constraints of multiple shooting: the paper's penalty, or an augmented Lagrangian.

The constraints are ``c = s_{i+1} - f^n(s_i) = 0``, one vector per gap (``m - 1`` per trajectory).
With ``K`` the number of gap elements in a batch (``B * (m-1) * d``), the two objectives are

    penalty              fit + alpha * mean(c^2)
    augmented_lagrangian fit + mean(lambda * c) + alpha * mean(c^2)
                       = fit + (1/K) * (<lambda, c> + rho/2 * ||c||^2),   rho = 2 * alpha

so the quadratic term is exactly the paper's penalty (same alpha, same normalisation: with all
multipliers at zero the two losses are equal), and the multipliers, one per gap element, stored per
trajectory like the nodes, follow the first-order update of that objective,

    lambda <- lambda + rho * c = lambda + 2 * alpha * c,

applied on a cadence (every ``every_n_epochs`` epochs, to the trajectories of each batch, with the
gap of that step). At a solution ``lambda / K`` is the Lagrange multiplier of the mean-normalised
problem ``min fit s.t. c = 0``; the penalty alone reaches it only as alpha -> infinity.

Optionally alpha grows when the gaps stop shrinking: after each update epoch, if the root mean
square gap is above ``shrink`` times its value at the previous update epoch, alpha's factor is
multiplied by ``growth`` (at most ``max_factor``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import Any

import torch

CONSTRAINTS = ("penalty", "augmented_lagrangian")


@dataclass(frozen=True)
class AugmentedLagrangianOptions:
    """Settings of the augmented Lagrangian (``model.constraint_options`` in a config).

    Args:
        every_n_epochs: the multipliers are updated during every ``every_n_epochs``-th epoch
            (epochs ``k-1, 2k-1, ...``), once for each trajectory seen in it.
        growth: factor applied to alpha when the gaps stop shrinking (1: alpha is never raised).
        shrink: the gaps "stop shrinking" when their RMS is above ``shrink`` times its previous value.
        max_factor: alpha is never raised beyond this multiple of the schedule's value.
    """

    every_n_epochs: int = 1
    growth: float = 1.0
    shrink: float = 0.25
    max_factor: float = 1e4

    @classmethod
    def from_mapping(cls, options: Mapping[str, Any] | None) -> AugmentedLagrangianOptions:
        options = dict(options or {})
        known = set(asdict(cls()))
        unknown = sorted(set(options) - known)
        if unknown:
            raise ValueError(f"unknown constraint_options {unknown}: choose among {sorted(known)}")
        out = cls(**options)
        if int(out.every_n_epochs) != out.every_n_epochs or out.every_n_epochs < 1:
            raise ValueError(f"constraint_options.every_n_epochs must be a whole number >= 1, got {out.every_n_epochs}")
        if out.growth < 1 or out.shrink <= 0 or out.max_factor < 1:
            raise ValueError(
                f"constraint_options need growth >= 1, shrink > 0 and max_factor >= 1, got growth={out.growth}, "
                f"shrink={out.shrink}, max_factor={out.max_factor}"
            )
        return out


def check_constraint(constraint: str, n_nodes: int) -> None:
    """Refuse an unknown constraint, and an augmented Lagrangian without any gap."""
    if constraint not in CONSTRAINTS:
        raise ValueError(f"unknown constraint {constraint!r}: choose one of {list(CONSTRAINTS)}")
    if constraint == "augmented_lagrangian" and n_nodes < 2:
        raise ValueError(
            f"constraint='augmented_lagrangian' needs continuity gaps, but n_nodes={n_nodes} has none (the "
            "initial value problem): use n_nodes >= 2, or constraint: penalty"
        )


def augmented_lagrangian(
    fit: torch.Tensor, residual: torch.Tensor, multipliers: torch.Tensor, alpha: torch.Tensor | float
) -> torch.Tensor:
    """``fit + mean(multipliers * c) + alpha * mean(c^2)`` (``multipliers`` shaped like ``c``)."""
    return fit + (multipliers * residual).mean() + alpha * residual.pow(2).mean()


def update_multipliers(multipliers: torch.Tensor, residual: torch.Tensor, alpha: torch.Tensor | float) -> torch.Tensor:
    """``lambda + 2 * alpha * c``: the first-order multiplier update of :func:`augmented_lagrangian`."""
    return multipliers + 2 * alpha * residual


def raised_factor(factor: float, gap_rms: float, previous_rms: float, options: AugmentedLagrangianOptions) -> float:
    """alpha's factor after an update epoch whose RMS gap is ``gap_rms`` (``previous_rms``: the last one)."""
    if math.isfinite(previous_rms) and gap_rms > options.shrink * previous_rms:
        return min(factor * options.growth, options.max_factor)
    return factor
