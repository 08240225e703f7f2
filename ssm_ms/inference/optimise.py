"""State inference by optimisation: the states of the given measurements fitted through the frozen ``f`` and ``g``
by the training objective itself, multiple shooting with the nodes as the only free parameters.

Nothing is trained: ``python cli.py test --config configs/pendulum_optimise.yaml --model.init_args.ssm_checkpoint
pretrained/pendulum.ckpt`` runs the protocol. For each test sequence the ``k`` given measurements are cut into
``n_nodes`` pieces, whose first states are fitted by Adam on ``fit + alpha * gap`` (:func:`fit_nodes`); the forecast
starts from the last piece's last state, as every inference method's (:class:`SSMForecaster`). With one node it is
the initial value problem (single shooting); on a chaotic system a long window wants several, as training does.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch
from torch import nn

from ssm_ms.inference.ssm_forecaster import SSMForecaster
from ssm_ms.training.shooting import rollout, shooting_residuals

STARTS = ("best_node", "nodes", "zero")
SEARCH_STATES = 2**16  # states rolled out and decoded per call of the start search (memory, not values)


def keep_lower(
    best: torch.Tensor, best_value: torch.Tensor, candidate: torch.Tensor, value: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per sequence (the first axis), ``candidate`` and its ``value`` where that value is lower than ``best_value``
    (a NaN value never is: a diverged rollout is never kept), else ``best`` and ``best_value``."""
    better = value < best_value
    mask = better.view(-1, *[1] * (best.dim() - 1))
    return torch.where(mask, candidate.to(best), best), torch.where(better, value.to(best_value), best_value)


def fit_nodes(
    f: Callable[..., torch.Tensor],
    g: Callable[[torch.Tensor], torch.Tensor],
    y: torch.Tensor,
    start: torch.Tensor,
    *,
    loss: str = "mse",
    alpha: float = 0.0,
    steps: int = 300,
    lr: float = 0.05,
    scale: torch.Tensor | None = None,
    u: torch.Tensor | None = None,
    weights: torch.Tensor | None = None,
    missing: bool = False,
    decode_chunk: int | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Shooting nodes ``[B, m, d]`` of the measurements ``y [B, T, *obs]`` (``T = m n``) under frozen ``f`` and ``g``.

    Each sequence's objective is the training one, ``fit_b + alpha * gap_b`` (:func:`shooting_residuals` with
    ``per_sequence``; ``u``, ``weights``, ``missing`` and ``decode_chunk`` as there), minimised by Adam on the nodes
    alone from ``start [B, m, d]``, each state component moved in units of ``scale [d]`` (default 1: pass the
    states' spread so that ``lr`` means the same for every model), the learning rate annealed (cosine) from ``lr``
    to ``lr / 100`` over the ``steps`` steps. The sequences are independent (the sum of their objectives has each
    one's gradient, and Adam scales per element). Per sequence, the nodes of the step with the lowest objective are
    returned, so never worse than ``start``'s; a sequence whose objective is never finite keeps ``start``.

    Returns ``(nodes [B, m, d], objective [B])``. Runs with gradients even when called under ``torch.no_grad`` or
    ``torch.inference_mode`` (the test loop's); the parameters of ``f`` and ``g`` get none.
    """
    if steps < 0:
        raise ValueError(f"steps must be >= 0, got {steps}")
    if not lr > 0:
        raise ValueError(f"lr must be > 0, got {lr}")
    with torch.inference_mode(False), torch.enable_grad():
        # tensors made under inference mode cannot be saved for backward: normal copies
        y, start = y.clone(), start.detach().clone()
        u = None if u is None else u.clone()
        scale = torch.ones_like(start[0, 0]) if scale is None else scale.detach().clone().to(start)
        delta = torch.zeros_like(start, requires_grad=True)
        optimizer = torch.optim.Adam([delta], lr=lr)
        schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=max(steps, 1), eta_min=lr / 100)
        best, best_value = start.clone(), torch.full(start.shape[:1], math.inf, dtype=start.dtype, device=start.device)
        for step in range(steps + 1):
            nodes = start + scale * delta
            fit, gaps = shooting_residuals(
                f, g, nodes, y, loss, decode_chunk, u=u, weights=weights, missing=missing, per_sequence=True
            )
            value = fit + alpha * gaps.pow(2).flatten(1).mean(1) if gaps.numel() else fit
            best, best_value = keep_lower(best, best_value, nodes.detach(), value.detach())
            if step == steps:
                break
            (delta.grad,) = torch.autograd.grad(value.sum(), delta)
            optimizer.step()
            schedule.step()
    return best, best_value


def step_scale(nodes: torch.Tensor) -> torch.Tensor:
    """``[d]``: the unit of the fit's steps per state component, the spread (std) of the SSM's shooting nodes ``[N,
    d]``, at least a thousandth of the largest component's (a component the nodes barely use still moves); unit
    steps where the nodes have not spread at all (largest std under 1e-6: an SSM whose nodes did not train)."""
    spread = nodes.std(0) if len(nodes) > 1 else torch.zeros(nodes.shape[-1], dtype=nodes.dtype)
    largest = float(spread.max())
    if not largest > 1e-6:  # NaN too
        return torch.ones_like(spread)
    return spread.clamp_min(1e-3 * largest)


def check_pieces(k: int, n_nodes: int, what: str) -> None:
    """Refuse ``k`` given measurements that ``n_nodes`` pieces do not cut into equal lengths (``what`` sets ``k``)."""
    if k % n_nodes:
        divisors = [m for m in range(1, k + 1) if k % m == 0]
        raise ValueError(
            f"{what}: {k} measurements, which n_nodes={n_nodes} does not cut into equal pieces: give a multiple "
            f"of {n_nodes}, or set model.init_args.n_nodes among {divisors}"
        )


class OptimisationForecaster(SSMForecaster):
    """The forecasting protocol with states fitted to the given measurements through the frozen SSM (:func:`fit_nodes`).

    Args:
        ssm_checkpoint: the trained ``MultipleShootingModule``: its checkpoint, or the model itself.
        n_filter: measurements given before predicting; a multiple of ``n_nodes``.
        n_nodes: pieces the given measurements are cut into, one fitted node each (1: the initial value problem).
        alpha: weight of the continuity gaps between the pieces (default: the SSM's own, as its training ended).
        steps: Adam steps per batch of sequences.
        lr: Adam's learning rate, in units of the spread of the SSM's shooting nodes (per state component,
            :func:`step_scale`).
        start: where the nodes start: ``"best_node"`` (the default), for each piece the one of ``n_candidates``
            shooting nodes of the SSM (drawn once, seed 0) whose rollout fits that piece best (the objective is not
            convex: from one fixed start Adam stops in the nearest valley); ``"nodes"`` the mean shooting node;
            ``"zero"`` zero. Either way the components the SSM's ``node_init_map`` reads from measurements start at
            the measurement (as the UKF's prior mean).
        n_candidates: shooting nodes tried by ``start: best_node`` (all of them where the SSM has fewer).
        metrics: scores of the test protocol.
        method_name: label of the results (default: ``optimise``).
        **kwargs: the protocol's other arguments (``n_predict``, ``bce_reduction``, ``original_units``,
            ``experiment``, ``results_dir``, ``figures_dir``, ``analysis``), see
            :class:`~ssm_ms.forecasting.protocol.ForecastModule`.
    """

    method_kind = "optimise"

    def __init__(
        self,
        ssm_checkpoint: str | nn.Module | None = None,
        *,
        n_filter: int,
        n_nodes: int = 1,
        alpha: float | None = None,
        steps: int = 300,
        lr: float = 0.05,
        start: str = "best_node",
        n_candidates: int = 256,
        metrics: list[str] = ["mse"],  # noqa: B006 (read, never mutated; a list for the CLI)
        method_name: str | None = None,
        **kwargs: Any,
    ):
        if n_nodes < 1:
            raise ValueError(f"n_nodes must be >= 1 (pieces of the given measurements), got {n_nodes}")
        check_pieces(n_filter, n_nodes, "n_filter")
        if steps < 0:
            raise ValueError(f"steps must be >= 0 (Adam steps per batch), got {steps}")
        if not lr > 0:
            raise ValueError(f"lr must be > 0 (in units of the nodes' spread, e.g. 0.05), got {lr}")
        if alpha is not None and alpha < 0:
            raise ValueError(f"alpha must be >= 0 (or unset: the SSM's own), got {alpha}")
        if start not in STARTS:
            raise ValueError(
                f"start must be 'best_node' (the best fitting of n_candidates shooting nodes), 'nodes' (their mean) "
                f"or 'zero', got {start!r}"
            )
        if n_candidates < 1:
            raise ValueError(
                f"n_candidates must be >= 1 (shooting nodes tried by start: best_node), got {n_candidates}"
            )
        super().__init__(ssm_checkpoint, n_filter=n_filter, metrics=metrics, method_name=method_name, **kwargs)
        self.n_nodes, self.steps, self.lr, self.start = int(n_nodes), int(steps), float(lr), start
        self.alpha = float(self.ssm.alpha) if alpha is None else float(alpha)
        nodes = self.ssm.training_states()
        self.register_buffer("scale", step_scale(nodes), persistent=False)  # never saved: it moves with the module
        pick = torch.randperm(len(nodes), generator=torch.Generator().manual_seed(0))[:n_candidates]
        self.register_buffer("candidates", nodes[pick].clone(), persistent=False)

    def setup(self, stage: str) -> None:
        super().setup(stage)
        self.ssm.adopt_sensors(getattr(self.datamodule, "sensor_layout", None))  # the fit weighs streams as training
        test = getattr(self.datamodule, "datasets", {}).get("test") if stage == "test" else None
        seq_len = getattr(test, "seq_len", None)
        if seq_len is not None and self.analysis_section("valid_time") is not None:
            check_pieces(self._valid_time_split(seq_len)[0], self.n_nodes, "analysis.valid_time's n_filter")
        given = getattr(self.datamodule, "predict_given", None) if stage == "predict" else None
        if given:  # unset: all samples of the file, checked when it is read
            check_pieces(given, self.n_nodes, "predict_given")

    def inference_settings(self) -> str:
        return (
            f"Adam on the shooting objective of the frozen f and g: n_nodes={self.n_nodes}, alpha={self.alpha:g}, "
            f"steps={self.steps}, lr={self.lr:g} in the nodes' spread (cosine to lr/100), the best step per "
            f"sequence; start={self.start}" + (f" of {len(self.candidates)}" if self.start == "best_node" else "")
        )

    def initial_nodes(self, y_filter: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        """``[B, n_nodes, d]``: where the fit of ``y_filter [B, k, *obs]`` starts (``start``); for ``best_node``, per
        piece the candidate node of the lowest fit over that piece (no gradients)."""
        k, d = y_filter.shape[1], self.ssm.state_dim
        b, m = len(y_filter), self.n_nodes
        n = k // m
        if self.start != "best_node":
            return self.start_states(y_filter[:, ::n], torch.zeros(d) if self.start == "zero" else None)
        pieces = y_filter.reshape(b * m, n, *y_filter.shape[2:])  # each piece a sequence of its own, one node
        inputs = None if u is None else u[:, :k].reshape(b * m, n, -1)
        best = torch.zeros(b * m, 1, d, dtype=self.candidates.dtype, device=y_filter.device)
        best_fit = torch.full((b * m,), math.inf, dtype=best.dtype, device=best.device)
        per_call = max(1, SEARCH_STATES // (b * m * n))
        with torch.no_grad():
            for chunk in self.candidates.split(per_call):
                c = len(chunk)
                starts = torch.cat([self.start_states(pieces[:, :1], node) for node in chunk])  # [c * B m, 1, d]
                fit, _ = shooting_residuals(
                    self.ssm.f,
                    self.ssm.g,
                    starts,
                    pieces.repeat(c, *[1] * (pieces.dim() - 1)),
                    self.ssm.hparams.loss,
                    self.ssm.hparams.decode_chunk,
                    u=None if inputs is None else inputs.repeat(c, 1, 1),
                    per_sequence=True,
                    **self.ssm.fit_options(),
                )
                fit, which = torch.nan_to_num(fit, nan=math.inf).view(c, b * m).min(0)  # NaN: min would return it
                chosen = starts.view(c, b * m, 1, d)[which, torch.arange(b * m, device=best.device)]
                best, best_fit = keep_lower(best, best_fit, chosen, fit)
        return best.view(b, m, d)

    def fit_states(self, y_filter: torch.Tensor, u: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``(nodes [B, n_nodes, d], objective [B])`` fitted to ``y_filter [B, k, *obs]`` (inputs ``u [B, >= k, m]``
        for a driven SSM: ``u[:, k - 1]`` closes the last piece)."""
        k = y_filter.shape[1]
        check_pieces(k, self.n_nodes, "the sequences given whole (predict_given unset)")
        return fit_nodes(
            self.ssm.f,
            self.ssm.g,
            y_filter,
            self.initial_nodes(y_filter, u),
            loss=self.ssm.hparams.loss,
            alpha=self.alpha,
            steps=self.steps,
            lr=self.lr,
            scale=self.scale,
            u=None if u is None else u[:, :k],
            decode_chunk=self.ssm.hparams.decode_chunk,
            **self.ssm.fit_options(),
        )

    def infer(self, y_filter: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        nodes, _ = self.fit_states(y_filter, u)
        b, m, d = nodes.shape
        n = y_filter.shape[1] // m
        pieces = None if u is None else u[:, : m * n].reshape(b * m, n, -1)
        return rollout(self.ssm.f, nodes.reshape(b * m, d), n, pieces).reshape(b, m * n, d)
