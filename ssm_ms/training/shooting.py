"""The multiple-shooting objective as pure tensor functions (no Lightning).

A batch of ``B`` trajectories ``y`` of length ``T`` is cut into ``m`` sub-trajectories of length
``n = T / m``. Sub-trajectory ``i`` of trajectory ``b`` starts at the shooting node ``s[b, i]``;
the model predicts its measurements ``g(f^k(s[b, i]))``, ``k = 0..n-1``, and the continuity gap
``s[b, i+1] - f^n(s[b, i])`` measures how far the sub-trajectories are from forming one.

With inputs ``u [B, T, m_u]`` (a system driven by torques, voltages, ...) the transition is
``x[t+1] = f(x[t], u[t])``: the input at time ``t`` acts between ``t`` and ``t + 1``. Sub-trajectory
``i`` then rolls out with its own slice ``u[b, i n : (i + 1) n]``, ``f^k`` meaning ``k`` steps under
those inputs; ``u[b, T - 1]`` only closes the last piece (whose end has no node to meet).
"""

from __future__ import annotations

import shutil
import sys
from collections.abc import Callable

import torch
import torch.nn.functional as F

from ssm_ms.runtime.private import dynamo_supported

LOSSES: dict[str, Callable[[torch.Tensor, torch.Tensor], torch.Tensor]] = {
    "mse": F.mse_loss,
    "bce": F.binary_cross_entropy,
}


def loss_function(name: str) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    """The elementwise-mean loss called ``name`` (``"mse"`` or ``"bce"``)."""
    if name not in LOSSES:
        raise ValueError(f"unknown loss {name!r}: choose one of {sorted(LOSSES)}")
    return LOSSES[name]


def weighted_fit(
    loss: str,
    y_hat: torch.Tensor,
    y: torch.Tensor,
    weights: torch.Tensor | None = None,
    missing: bool = False,
    per_sequence: bool = False,
) -> torch.Tensor:
    """The fit of several sensors: the elementwise ``loss`` weighted per component by ``weights`` (broadcast over
    ``y``'s trailing dimensions: one per measurement component), averaged over the observed elements; with
    ``missing``, the NaN elements of ``y`` (samples a sensor did not take) are left out. With ``per_sequence``,
    one average per sequence (``y [B, ...]`` -> ``[B]``) in place of one over the batch."""
    loss_function(loss)
    observed = torch.isfinite(y) if missing else None
    target = y if observed is None else torch.where(observed, y, y_hat.detach())
    per_element = (F.mse_loss if loss == "mse" else F.binary_cross_entropy)(y_hat, target, reduction="none")
    if weights is not None:
        per_element = per_element * weights.to(per_element)
    if per_sequence:
        per_element, observed = per_element.flatten(1), None if observed is None else observed.flatten(1)
    dims = 1 if per_sequence else None
    if observed is None:
        return per_element.mean(dims)
    return (per_element * observed).sum(dims) / observed.sum(dims).clamp_min(1)


Rollout = Callable[..., torch.Tensor]  # (x0 [N, d], steps, u [N, steps - 1, m] or None) -> [N, steps, d]

COMPILE_MODES = ("default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs")


def rollout(
    f: Callable[..., torch.Tensor], x0: torch.Tensor, steps: int, u: torch.Tensor | None = None
) -> torch.Tensor:
    """States ``x0, f(x0), ..., f^{steps-1}(x0)``: ``[N, d] -> [N, steps, d]``.

    With inputs ``u [N, >= steps - 1, m]``, ``x[k + 1] = f(x[k], u[:, k])`` (inputs past ``steps - 1`` are not
    used); without, ``f`` takes the state alone."""
    if u is not None and u.shape[1] < steps - 1:
        raise ValueError(f"a rollout of {steps} states needs {steps - 1} inputs, got u of shape {tuple(u.shape)}")
    xs = [x0]
    for k in range(steps - 1):
        xs.append(f(xs[-1]) if u is None else f(xs[-1], u[:, k]))
    return torch.stack(xs, dim=1)


def compile_unavailable_reason(mode: str) -> str | None:
    """Why ``torch.compile`` cannot build a rollout here (``None``: it can)."""
    if mode not in COMPILE_MODES:
        return f"unknown torch.compile mode {mode!r}: choose one of {list(COMPILE_MODES)}"
    if not dynamo_supported():
        return f"torch.compile does not support this Python ({sys.version.split()[0]}) or platform"
    if not torch.cuda.is_available() and not any(shutil.which(c) for c in ("g++", "c++", "clang++")):
        return "torch.compile on CPU needs a C++ compiler (g++ or clang++) on PATH, and none was found"
    return None


class CompiledRollout:
    """``rollout(f, x0, steps)`` through ``torch.compile``: the ``steps - 1`` calls of ``f`` become one graph.

    On a GPU the rollout is many small sequential kernels; compiled, inductor fuses each step's
    elementwise work, and ``mode="reduce-overhead"`` also replays the whole rollout (forward and
    backward) as CUDA graphs, removing the per-kernel launch cost. The graph is specialised to
    ``steps`` and to the input's shape, dtype and device (a new value compiles once more; torch's
    recompile limit applies). Same values as :func:`rollout` up to floating-point reassociation.
    Unavailable (no ``torch.compile``, or on CPU no C++ compiler): :class:`RuntimeError` naming why.
    """

    def __init__(self, f: Callable[..., torch.Tensor], mode: str = "default"):
        reason = compile_unavailable_reason(mode)
        if reason is not None:
            raise RuntimeError(f"compiled rollout unavailable: {reason}; use the eager rollout (compile_rollout: null)")
        self.f, self.mode = f, mode
        self._compiled = torch.compile(rollout, mode=mode, dynamic=False)

    def __call__(self, x0: torch.Tensor, steps: int, u: torch.Tensor | None = None) -> torch.Tensor:
        if self.mode == "reduce-overhead" and x0.is_cuda:
            torch.compiler.cudagraph_mark_step_begin()  # each call is a new step: earlier outputs may be reused
        return self._compiled(self.f, x0, steps, u)


def decode(g: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor, chunk: int | None = None) -> torch.Tensor:
    """``g`` on states ``[..., d]`` -> ``[..., *obs_shape]``, in one call or in chunks of ``chunk`` states."""
    lead, d = x.shape[:-1], x.shape[-1]
    flat = x.reshape(-1, d)
    if chunk is None or chunk >= len(flat):
        out = g(flat)
    else:
        out = torch.cat([g(part) for part in flat.split(chunk)])
    return out.view(*lead, *out.shape[1:])


def check_shapes(nodes: torch.Tensor, y: torch.Tensor, u: torch.Tensor | None = None) -> int:
    """Validate ``nodes [B, m, d]`` against ``y [B, T, ...]`` (and inputs ``u [B, T, m_u]``); return ``n = T / m``."""
    if nodes.dim() != 3:
        raise ValueError(f"nodes must be [batch, n_nodes, state_dim], got shape {tuple(nodes.shape)}")
    if y.dim() < 3:
        raise ValueError(f"y must be [batch, T, *obs_shape] with at least one observation axis, got {tuple(y.shape)}")
    b, m, _ = nodes.shape
    if y.shape[0] != b:
        raise ValueError(f"nodes hold {b} trajectories but y holds {y.shape[0]}")
    t = y.shape[1]
    if t % m != 0:
        divisors = [k for k in range(1, t + 1) if t % k == 0]
        raise ValueError(
            f"trajectory length T={t} is not divisible by the number of shooting nodes m={m}: "
            f"choose n_nodes among {divisors}, or cut the trajectories to a multiple of {m}"
        )
    if u is not None and (u.dim() != 3 or tuple(u.shape[:2]) != (b, t)):
        raise ValueError(f"inputs u must be [batch, T, input_dim] = [{b}, {t}, m] beside y, got {tuple(u.shape)}")
    return t // m


def shooting_residuals(
    f: Callable[[torch.Tensor], torch.Tensor],
    g: Callable[[torch.Tensor], torch.Tensor],
    nodes: torch.Tensor,
    y: torch.Tensor,
    loss: str = "mse",
    decode_chunk: int | None = None,
    rollout_fn: Rollout | None = None,
    u: torch.Tensor | None = None,
    weights: torch.Tensor | None = None,
    missing: bool = False,
    per_sequence: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(fit, c)``: the fit term of :func:`multiple_shooting_loss` (with ``per_sequence``, one per trajectory,
    ``[B]``) and the continuity gaps themselves, ``c[b, i] = s[b, i+1] - f^n(s[b, i])``, shape ``[B, m-1, d]``
    (empty when ``m = 1``). Other arguments as :func:`multiple_shooting_loss`."""
    n = check_shapes(nodes, y, u)
    loss_fn = loss_function(loss)
    b, m, d = nodes.shape
    # n + 1 states: f^0 .. f^{n-1} are decoded, f^n closes the gap; piece i under its own inputs u[i n : (i+1) n]
    x0 = nodes.reshape(b * m, d)
    pieces = None if u is None else u.reshape(b * m, n, u.shape[-1])
    states = rollout(f, x0, n + 1, pieces) if rollout_fn is None else rollout_fn(x0, n + 1, pieces)
    traj = states[:, :n]  # [B*m, n, d]
    y_hat = decode(g, traj, decode_chunk)  # [B*m, n, *obs]
    if y_hat.shape[2:] != y.shape[2:]:
        raise ValueError(
            f"the observation model outputs measurements of shape {tuple(y_hat.shape[2:])} but the data "
            f"have shape {tuple(y.shape[2:])}: make g's output match the data (e.g. decoder preset / image size)"
        )
    if weights is None and not missing and not per_sequence:
        fit = loss_fn(y_hat.reshape(y.shape), y)
    else:
        fit = weighted_fit(loss, y_hat.reshape(y.shape), y, weights, missing, per_sequence)
    end = states[:, n].view(b, m, d)
    return fit, nodes[:, 1:] - end[:, :-1]


GAP_SCALES = ("absolute", "node_variance")  # how the gap term is measured (model.gap_scale; checks.check_gap_scale)


def check_scale(scale: str) -> None:
    """``scale`` is one of :data:`GAP_SCALES` (a ValueError naming them, also under ``python -O``)."""
    if scale not in GAP_SCALES:
        raise ValueError(f"unknown gap_scale {scale!r}: choose one of {list(GAP_SCALES)}")


def gap_term(residual: torch.Tensor, nodes: torch.Tensor, scale: str = "absolute") -> torch.Tensor:
    """The gap term of the objective from the gaps ``residual [B, m-1, d]`` of the nodes ``nodes [B, m, d]``.

    ``"absolute"`` (the paper): ``mean(c^2)``. ``"node_variance"``: each state coordinate's squared gaps divided by
    that coordinate's variance over the batch's nodes, ``mean_{b,i,j}(c[b,i,j]^2 / var_j(s))``, the variance kept in
    the graph: the term is unchanged when the states are mapped by ``x -> D x + e`` (``D`` diagonal), so states that
    shrink toward a point, with ``g`` scaled up to read them, no longer lower it. Exactly zero without gaps.
    """
    check_scale(scale)
    if residual.numel() == 0:
        return residual.new_zeros(())
    if scale == "absolute":
        return residual.pow(2).mean()
    var = nodes.reshape(-1, nodes.shape[-1]).var(0, unbiased=False)
    return (residual.pow(2) / (var + torch.finfo(var.dtype).tiny)).mean()


def multiple_shooting_loss(
    f: Callable[[torch.Tensor], torch.Tensor],
    g: Callable[[torch.Tensor], torch.Tensor],
    nodes: torch.Tensor,
    y: torch.Tensor,
    loss: str = "mse",
    decode_chunk: int | None = None,
    rollout_fn: Rollout | None = None,
    u: torch.Tensor | None = None,
    weights: torch.Tensor | None = None,
    missing: bool = False,
    gap_scale: str = "absolute",
) -> tuple[torch.Tensor, torch.Tensor]:
    """The two terms of the multiple-shooting objective.

    Args:
        f: transition, ``[N, d] -> [N, d]``.
        g: observation model, ``[N, d] -> [N, *obs_shape]``.
        nodes: shooting nodes ``[B, m, d]``.
        y: measurements ``[B, T, *obs_shape]`` with ``T = m * n``.
        loss: ``"mse"`` or ``"bce"`` (then ``g`` must output values in [0, 1]).
        decode_chunk: decode at most this many states per call of ``g`` (``None``: all at once).
        rollout_fn: ``(x0 [N, d], steps, u) -> [N, steps, d]`` states of ``f`` (``None``: :func:`rollout`
            with ``f``; a :class:`CompiledRollout` of ``f`` gives the same values).
        u: inputs ``[B, T, m_u]`` for a transition ``f(x, u)`` (``None``: ``f(x)``, an autonomous system); piece
            ``i`` rolls out under ``u[:, i n : (i + 1) n]``.
        weights, missing: several sensors (:mod:`ssm_ms.nets.sensors`): the fit weighs measurement component ``c``
            by ``weights[c]`` and, with ``missing``, leaves out the NaN elements of ``y`` (:func:`weighted_fit`).
        gap_scale: how the gap is measured (:func:`gap_term`): ``"absolute"`` (the paper) or ``"node_variance"``.

    Returns:
        ``(fit, gap)``: ``fit`` is the mean over all elements of ``loss(g(f^k(s_i)), y[(i-1)n + k])``;
        ``gap`` is the mean over all elements of ``(s_{i+1} - f^n(s_i))^2``, ``i = 1..m-1`` (with
        ``"node_variance"``, each divided by its coordinate's variance over the nodes), and exactly
        zero when ``m = 1`` (the initial value problem).
    """
    fit, residual = shooting_residuals(f, g, nodes, y, loss, decode_chunk, rollout_fn, u, weights, missing)
    return fit, gap_term(residual, nodes, gap_scale)
