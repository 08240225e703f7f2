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

from ssm_ms.training.shooting import multiple_shooting_loss, shooting_residuals

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


# ------------------------------------------------------------------------------------------------- the strategies
# A model's constraint is one of these objects (:func:`make_constraint`). They keep their state in the model's buffers
# (``alpha``; the augmented Lagrangian's ``alpha_factor``, ``last_gap_rms`` and ``multipliers``), so checkpoints and
# DDP see them as before; the objects hold the options and an epoch's running sums only.
class Penalty:
    """The paper's objective, ``fit + alpha * mean(c^2)`` (or its gap measured as ``gap_scale`` says:
    :func:`~ssm_ms.training.shooting.gap_term`): nothing kept between steps."""

    def __init__(self, gap_scale: str = "absolute"):
        self.gap_scale = gap_scale

    def attach(self, model: torch.nn.Module) -> None:
        """Register the buffers this constraint keeps on ``model`` (none)."""

    def attach_table(self, model: torch.nn.Module, num_trajectories: int, gaps: int) -> None:
        """Register the per-trajectory state beside ``model``'s node table (none)."""

    def weight(self, model: torch.nn.Module) -> torch.Tensor:
        """The gap term's weight now: the schedule's ``alpha``."""
        return model.alpha

    def loss(
        self, model: torch.nn.Module, args: tuple, options: Mapping[str, Any], index: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """``(loss, fit, mean gap^2, residuals to keep)`` of a batch (``args`` as :func:`multiple_shooting_loss`'s)."""
        fit, gap = multiple_shooting_loss(*args, **options, gap_scale=self.gap_scale)
        return fit + self.weight(model) * gap, fit, gap, None

    def start_epoch(self) -> None:
        """A training epoch begins."""

    def update(self, model: torch.nn.Module, index: torch.Tensor, residual: torch.Tensor) -> None:
        """After a step's backward, with every rank's trajectories ``index`` and their kept residuals (none here)."""

    def end_epoch(self, model: torch.nn.Module) -> None:
        """A training epoch ends."""


class AugmentedLagrangian(Penalty):
    """``fit + mean(lambda * c) + alpha * factor * mean(c^2)``, the multipliers ``lambda`` per gap element and
    trajectory (the buffer ``multipliers``), updated every ``every_n_epochs``-th epoch; ``factor`` (``alpha_factor``)
    raised when the gaps stop shrinking."""

    def __init__(self, options: AugmentedLagrangianOptions):
        super().__init__()
        self.options = options
        self._sums = [0.0, 0]  # an update epoch's sum of squared residuals, and their count

    def attach(self, model: torch.nn.Module) -> None:
        model.register_buffer("alpha_factor", torch.tensor(1.0))  # raised when the gaps stop shrinking
        model.register_buffer("last_gap_rms", torch.tensor(float("inf")))

    def attach_table(self, model: torch.nn.Module, num_trajectories: int, gaps: int) -> None:
        model.register_buffer("multipliers", model.nodes.weight.new_zeros(num_trajectories, gaps))
        # identical on every rank (updated from the gathered batch): DDP need not broadcast them
        model._ddp_params_and_buffers_to_ignore = ["multipliers"]

    def weight(self, model: torch.nn.Module) -> torch.Tensor:
        return model.alpha * model.alpha_factor

    def loss(
        self, model: torch.nn.Module, args: tuple, options: Mapping[str, Any], index: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
        fit, residual = shooting_residuals(*args, **options)
        lam = model.multipliers[index].view_as(residual)
        loss = augmented_lagrangian(fit, residual, lam, self.weight(model))
        return loss, fit, residual.pow(2).mean(), residual.detach().flatten(1)

    def updating(self, epoch: int) -> bool:
        """Whether the multipliers are updated during ``epoch``."""
        return (epoch + 1) % self.options.every_n_epochs == 0

    def start_epoch(self) -> None:
        self._sums = [0.0, 0]

    @torch.no_grad()
    def update(self, model: torch.nn.Module, index: torch.Tensor, residual: torch.Tensor) -> None:
        if not self.updating(model.current_epoch):
            return
        model.multipliers[index] = update_multipliers(model.multipliers[index], residual, self.weight(model))
        self._sums[0] += float(residual.pow(2).sum())
        self._sums[1] += residual.numel()

    def end_epoch(self, model: torch.nn.Module) -> None:
        if self.updating(model.current_epoch) and self._sums[1] > 0 and self.options.growth > 1:
            rms = (self._sums[0] / self._sums[1]) ** 0.5
            factor = raised_factor(float(model.alpha_factor), rms, float(model.last_gap_rms), self.options)
            model.alpha_factor.fill_(factor)
            model.last_gap_rms.fill_(rms)


def make_constraint(
    constraint: str, n_nodes: int, options: Mapping[str, Any] | None, gap_scale: str = "absolute"
) -> Penalty:
    """The strategy of ``model.constraint`` (checked: :func:`check_constraint`; options for the augmented Lagrangian
    only; a ``gap_scale`` other than ``"absolute"`` for the penalty only)."""
    check_constraint(constraint, n_nodes)
    if constraint == "augmented_lagrangian":  # free nodes only, whose gap is absolute (checks.check_gap_scale)
        return AugmentedLagrangian(AugmentedLagrangianOptions.from_mapping(options))
    if options:
        raise ValueError("constraint_options apply to constraint: augmented_lagrangian only: remove them")
    return Penalty(gap_scale)
