"""Did a learned model capture the dynamics? Pure tensor functions (no Lightning).

A forecast score says how close a model stays to the data for a few steps; these functions ask
whether ``f`` (``[N, d] -> [N, d]``) and ``g`` (``[N, d] -> [N, *obs_shape]``) reproduce the
*system*: its local linear maps, its rates of divergence, its long-run statistics, its period.

- :func:`jacobian`, :func:`linearize`: ``df/dx`` and ``dg/dx`` at a batch of states (for LQR, an
  EKF, or to inspect the model). ``torch.func`` (``vmap(jacrev)``); a module that ``vmap`` cannot
  batch (e.g. :class:`~ssm_ms.nets.ConvDecoder` in its default channels-last layout) falls back to
  forward-mode AD with the ``d`` input directions stacked into the batch.
- :func:`lyapunov_spectrum`: the Lyapunov exponents of ``f`` by Benettin's QR method along free
  runs, **per time unit**: the per-step logarithms are divided by ``steps * dt``, so with ``dt``
  the sampling period a learned model's exponents compare with the true system's (Lorenz
  63: about ``0.906, 0, -14.57``, summing to ``-(sigma + 1 + beta)``). :func:`lyapunov_time` is
  ``1 / largest``, the time over which errors grow by ``e``.
- :func:`free_run`: ``f`` iterated from given states, after an optional transient, for the
  statistics below.
- :func:`attractor_statistics`, :func:`wasserstein_1d`: whether the long free runs of the model
  visit the same values as the data (per measured component: 1-Wasserstein distance between the
  two empirical distributions, means and standard deviations).
- :func:`both_wings_share`: the share of free runs that visit both wings of the Lorenz butterfly,
  i.e. go above ``+level`` and below ``-level`` in ``x``; the data set gives the level (Lorenz:
  :func:`datamodules.lorenz.lorenz_wing_level` ``= 0.5 * sqrt(beta (rho - 1))``, half the distance of the fixed points
  ``x = +-sqrt(beta (rho - 1))`` (about 8.49, so 4.24) from 0. A run caught on a limit cycle around
  one fixed point stays on one side).
- :func:`valid_prediction_time`, :func:`summarize_valid_time`: how many steps a forecast stays valid,
  the reservoir-computing convention (Vlachas et al., 2020): valid while the normalised RMS error
  ``sqrt(mean_D((pred - truth)^2 / scale^2))`` stays ``<= 0.5``; summarised in steps, seconds
  (``x dt``) and Lyapunov times (``x dt x largest exponent``).
- :func:`dominant_period`, :func:`amplitude_ratio`: for a conservative oscillator seen through
  images (the pendulum), the period of the model's free run and whether its amplitude is kept
  (ratio ~1), decays (< 1) or grows (> 1).

Not implemented: the correlation dimension of the attractor (no maintained implementation among
the project's dependencies: torch, lightning, numpy, matplotlib, tensorboard).

Standard deviations over runs or sequences are population ones (``ddof = 0``), as in
:mod:`ssm_ms.forecasting.protocol`.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from typing import NamedTuple

import torch
from torch.func import jacrev, jvp, vmap

from ssm_ms.training.shooting import rollout

Fn = Callable[[torch.Tensor], torch.Tensor]

__all__ = [
    "LyapunovResult",
    "amplitude_ratio",
    "attractor_statistics",
    "both_wings_share",
    "dominant_period",
    "free_run",
    "dynamics_report",
    "jacobian",
    "Linearization",
    "linearize",
    "lyapunov_spectrum",
    "lyapunov_time",
    "summarize_valid_time",
    "valid_prediction_time",
    "valid_steps",
    "wasserstein_1d",
]


# ---------------------------------------------------------------------------- checks
def _check_states(x: torch.Tensor, name: str) -> None:
    if not isinstance(x, torch.Tensor) or x.dim() != 2 or x.shape[0] < 1 or x.shape[1] < 1:
        shape = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
        raise ValueError(f"{name} must be a batch of states [N, d] (N >= 1; one state: x.unsqueeze(0)), got {shape}")


def _check_positive(value: float, name: str) -> None:
    if not value > 0 or math.isinf(value):
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")


def _check_count(value: int, name: str, minimum: int) -> None:
    if int(value) != value or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")


# ---------------------------------------------------------------------------- Jacobians
def _jacobian_and_value(fn: Fn, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(J [N, *out, d], fn(x) [N, *out])`` from one evaluation of ``fn`` per sample."""

    def single(v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = fn(v.unsqueeze(0)).squeeze(0)
        return out, out

    try:
        return vmap(jacrev(single, has_aux=True))(x)
    except RuntimeError as err:  # an operation without a vmap batching rule (e.g. a channels-last copy)
        try:
            return _jacobian_forward(fn, x)
        except RuntimeError as fallback_err:
            raise fallback_err from err


def _jacobian_forward(fn: Fn, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Forward-mode fallback without ``vmap``: one call of ``fn`` on ``[d * N, d]``, tangent ``e_i`` per block.

    Assumes, like the whole project, that ``fn`` treats the rows of its input independently.
    """
    n, d = x.shape
    points = x.unsqueeze(0).expand(d, n, d).reshape(d * n, d)
    tangents = torch.eye(d, dtype=x.dtype, device=x.device).unsqueeze(1).expand(d, n, d).reshape(d * n, d)
    with warnings.catch_warnings():  # torch loads its forward-AD decompositions through torch.jit.script
        warnings.filterwarnings("ignore", message=".*torch.jit.script.* is deprecated", category=DeprecationWarning)
        value, columns = jvp(fn, (points,), (tangents,))
    jac = columns.reshape(d, n, *columns.shape[1:]).movedim(0, -1)  # [N, *out, d]
    return jac, value.reshape(d, n, *value.shape[1:])[0]


def jacobian(fn: Fn, x: torch.Tensor) -> torch.Tensor:
    """Jacobians of a batched function at a batch of points.

    Args:
        fn: ``[N, d] -> [N, *out_shape]``, rows treated independently (any ``f`` or ``g`` of the
            project; ``nn.ReLU(inplace=True)`` is fine).
        x: points ``[N, d]``.

    Returns:
        ``[N, *out_shape, d]``: ``J[n, ..., i] = d fn(x)[n, ...] / d x[n, i]``, in ``x``'s dtype. Works under
        ``torch.no_grad()`` (then the result carries no graph to the parameters of ``fn``).

    ``vmap(jacrev)`` of ``fn`` on single samples; when ``vmap`` cannot batch an operation of ``fn``
    (e.g. :class:`~ssm_ms.nets.ConvDecoder`'s channels-last copy), forward mode instead: ``fn`` once on
    the ``d * N`` points ``x`` repeated with tangents ``e_1 .. e_d`` (memory: ``d`` times one call).
    """
    _check_states(x, "x")
    return _jacobian_and_value(fn, x)[0]


class Linearization(NamedTuple):
    """A local linear model ``x[t+1] ~ A x[t] + B u[t]``, ``y ~ C x`` (deviations from the point of linearisation).

    Attributes:
        A: ``df/dx [N, d, d]``.
        B: ``df/du [N, d, m]``, or ``None`` for an autonomous ``f(x)``.
        C: ``dg/dx [N, p, d]`` (``g``'s output flattened), or ``[N, *obs_shape, d]``.
    """

    A: torch.Tensor
    B: torch.Tensor | None
    C: torch.Tensor


def linearize(f: Fn, g: Fn, x: torch.Tensor, u: torch.Tensor | None = None, flatten: bool = True) -> Linearization:
    """Local linear model around the states ``x [N, d]`` (and inputs ``u [N, m]`` for a driven ``f(x, u)``): for LQR,
    MPC on Jacobians, an EKF (:mod:`ssm_ms.export` exports it with ``f`` and ``g``).

    Returns:
        :class:`Linearization` ``(A, B, C)``: ``A = df/dx [N, d, d]``, ``B = df/du [N, d, m]`` (``None`` without
        ``u``), ``C = dg/dx [N, p, d]`` with ``g``'s output flattened to ``p`` values (an image ``[1, 24, 24]``
        gives ``p = 576``), or, with ``flatten=False``, ``[N, *obs_shape, d]``. In ``x``'s dtype; ``f`` and ``g``
        must be of the same dtype (``f.double()`` for float64).
    """
    _check_states(x, "x")
    n, d = x.shape
    if u is None:
        a, b = jacobian(f, x), None
    else:
        if u.dim() != 2 or u.shape[0] != n:
            raise ValueError(f"u must be inputs [N, m] beside x [{n}, {d}], got shape {tuple(u.shape)}")
        joint = jacobian(lambda z: f(z[:, :d], z[:, d:]), torch.cat([x, u.to(x)], dim=1))  # [N, d, d + m]
        a, b = joint[..., :d], joint[..., d:]
    if a.shape != (n, d, d):
        raise ValueError(f"f must map states [N, {d}] to [N, {d}]; its Jacobian has shape {tuple(a.shape)}")
    c = jacobian(g, x)
    return Linearization(a, b, c.reshape(n, -1, d) if flatten else c)


# ---------------------------------------------------------------------------- Lyapunov exponents
class LyapunovResult(NamedTuple):
    """Lyapunov exponents per time unit (``1 / steps`` of the per-step logs divided by ``dt``).

    Attributes:
        exponents: ``[k]``, mean over runs, descending.
        per_run: ``[R, k]``, each run's exponents, descending.
        std: ``[k]``, population standard deviation over runs (0 for one run).
        dt: time per step used for the conversion.
        steps: accumulated steps per run.
    """

    exponents: torch.Tensor
    per_run: torch.Tensor
    std: torch.Tensor
    dt: float
    steps: int


def lyapunov_spectrum(
    f: Fn,
    x0: torch.Tensor,
    steps: int,
    dt: float = 1.0,
    transient: int = 0,
    n_exponents: int | None = None,
    align: int = 0,
) -> LyapunovResult:
    """The ``k`` largest Lyapunov exponents of ``x[t+1] = f(x[t])`` by Benettin's QR method.

    Each run first iterates ``f`` for ``transient`` steps (to reach the attractor; no Jacobians),
    then propagates an orthonormal frame ``Q [d, k]`` (initially the first ``k`` axes) with the
    Jacobian ``J = df/dx``: ``Q, R = qr(J Q)``, for ``align`` steps without accumulating, then for
    ``steps`` steps accumulating ``log |diag(R)|``. Exponent ``i`` is the sum divided by
    ``steps * dt``: per time unit when ``dt`` is the time per step (``dt = 1``: per step).
    All ``R`` runs advance together (one batched Jacobian per step), in ``x0``'s dtype (use
    float64 for accurate exponents), under ``torch.no_grad()``.

    Two errors shrink with ``steps * dt``: the spread of finite-time exponents (roughly as
    ``1 / sqrt(steps * dt)``, reduced by averaging runs) and a bias of order ``1 / (steps * dt)``
    while the initial frame turns towards the Lyapunov vectors, which ``align`` removes (a few
    times ``1 / (lambda_1 - lambda_2)`` time units suffice; Lorenz 63: ~3 time units).

    Args:
        f: transition ``[N, d] -> [N, d]``.
        x0: initial states of ``R`` independent runs, ``[R, d]``.
        steps: accumulated steps.
        dt: time per step.
        transient: steps of ``f`` alone before the frame starts.
        n_exponents: ``k`` (default ``d``), ``1 <= k <= d``.
        align: steps that turn the frame without accumulating, after the transient.

    Returns:
        :class:`LyapunovResult`. A singular Jacobian gives ``-inf`` for the exponents it kills.
    """
    _check_states(x0, "x0 (initial states of R runs)")
    _check_count(steps, "steps", 1)
    _check_count(transient, "transient", 0)
    _check_count(align, "align", 0)
    _check_positive(dt, "dt")
    r, d = x0.shape
    k = d if n_exponents is None else n_exponents
    if int(k) != k or not 1 <= k <= d:
        raise ValueError(f"n_exponents must be an integer between 1 and the state dimension {d}, got {n_exponents!r}")
    with torch.no_grad():
        x = x0
        for _ in range(int(transient)):
            x = f(x)
        q = torch.eye(d, int(k), dtype=x0.dtype, device=x0.device).expand(r, d, int(k))
        total = x0.new_zeros(r, int(k))
        for i in range(int(align) + int(steps)):
            jac, x = _jacobian_and_value(f, x)
            if jac.shape != (r, d, d):
                raise ValueError(f"f must map states [R, {d}] to [R, {d}]; its Jacobian has shape {tuple(jac.shape)}")
            q, upper = torch.linalg.qr(jac @ q)
            if i >= align:
                total += upper.diagonal(dim1=-2, dim2=-1).abs().log()
        per_run = (total / (int(steps) * dt)).sort(dim=-1, descending=True).values
    return LyapunovResult(
        exponents=per_run.mean(0), per_run=per_run, std=per_run.std(0, correction=0), dt=float(dt), steps=int(steps)
    )


def lyapunov_time(largest: float) -> float:
    """``1 / largest``: the time over which small errors grow by a factor ``e`` (``inf`` if ``largest <= 0``)."""
    largest = float(largest)
    return 1.0 / largest if largest > 0 else math.inf


# ---------------------------------------------------------------------------- free runs and their statistics
def free_run(f: Fn, x0: torch.Tensor, steps: int, transient: int = 0) -> torch.Tensor:
    """``f`` iterated from ``x0 [R, d]``: the ``steps`` states after the first ``transient`` ones.

    Returns:
        ``[R, steps, d]``: ``f^{transient}(x0), ..., f^{transient + steps - 1}(x0)`` (no gradients).
    """
    _check_states(x0, "x0 (initial states of R runs)")
    _check_count(steps, "steps", 1)
    _check_count(transient, "transient", 0)
    with torch.no_grad():
        x = x0
        for _ in range(int(transient)):
            x = f(x)
        return rollout(f, x, int(steps))


def wasserstein_1d(a: torch.Tensor, b: torch.Tensor) -> float:
    """Exact 1-Wasserstein distance between the empirical distributions of two 1-D samples.

    ``integral |F_a(t) - F_b(t)| dt`` over the merged sorted support (the samples may have different
    sizes; the same value as ``scipy.stats.wasserstein_distance``). Computed in float64.
    """
    for name, s in (("a", a), ("b", b)):
        if s.dim() != 1 or s.numel() == 0:
            raise ValueError(
                f"{name} must be a non-empty 1-D sample, got shape {tuple(s.shape)}: flatten it or pick one component"
            )
        if not torch.isfinite(s).all():
            raise ValueError(f"{name} holds NaN or inf values: drop them (or the diverged runs) first")
    a = a.detach().to(torch.float64).sort().values
    b = b.detach().to(torch.float64).to(a.device).sort().values
    support = torch.cat([a, b]).sort().values
    left = support[:-1]
    cdf_a = torch.searchsorted(a, left, right=True).to(torch.float64) / a.numel()
    cdf_b = torch.searchsorted(b, left, right=True).to(torch.float64) / b.numel()
    return float(((cdf_a - cdf_b).abs() * support.diff()).sum())


def attractor_statistics(model: torch.Tensor, reference: torch.Tensor) -> dict[str, list[float]]:
    """Per measured component, how well the model's long-run values match the reference's.

    Args:
        model: samples ``[N, D]`` of the model (e.g. its free runs decoded, flattened over runs and time).
        reference: samples ``[M, D]`` of the data, same components and units.

    Returns:
        ``{"wasserstein", "model_mean", "model_std", "reference_mean", "reference_std"}``, each a list
        of ``D`` floats (1-Wasserstein distance per component; population standard deviations).
    """
    for name, s in (("model", model), ("reference", reference)):
        if s.dim() != 2 or s.shape[0] < 1:
            raise ValueError(f"{name} must be samples [N, D] (reshape runs and time into N), got {tuple(s.shape)}")
    if model.shape[1] != reference.shape[1]:
        raise ValueError(
            f"model has {model.shape[1]} components but reference has {reference.shape[1]}: compare the same components"
        )
    model, reference = model.detach().to(torch.float64), reference.detach().to(torch.float64)
    return {
        "wasserstein": [wasserstein_1d(model[:, i], reference[:, i]) for i in range(model.shape[1])],
        "model_mean": model.mean(0).tolist(),
        "model_std": model.std(0, correction=0).tolist(),
        "reference_mean": reference.mean(0).tolist(),
        "reference_std": reference.std(0, correction=0).tolist(),
    }


def both_wings_share(x: torch.Tensor, level: float) -> float:
    """Share of runs that visit both wings: go above ``+level`` and below ``-level``.

    Args:
        x: one measured component per run, ``[R, T]`` (Lorenz: ``x`` in original units).
        level: > 0; for Lorenz :func:`datamodules.lorenz.lorenz_wing_level` (``x`` in normalised units: divide it by the
            data's std, after removing the mean).
    """
    if x.dim() != 2 or x.shape[0] < 1 or x.shape[1] < 1:
        raise ValueError(f"x must be one component per run, [R, T], got {tuple(x.shape)}")
    _check_positive(level, "level")
    both = (x.amax(dim=1) > level) & (x.amin(dim=1) < -level)
    return float(both.to(torch.float64).mean())


# ---------------------------------------------------------------------------- valid prediction time
def valid_prediction_time(
    pred: torch.Tensor, truth: torch.Tensor, scale: torch.Tensor, threshold: float = 0.5
) -> torch.Tensor:
    """Steps a forecast stays valid: the reservoir-computing valid prediction time (Vlachas et al., 2020).

    The normalised error at step ``j`` is ``sqrt(mean_D((pred - truth)^2 / scale^2))``; the forecast
    is valid while it is ``<= threshold`` (0.5 in that convention). A NaN error counts as invalid.

    Args:
        pred, truth: ``[B, p, D]``, ``p`` forecast steps of a flattened ``D``-valued measurement.
        scale: ``[D]`` (or a scalar), > 0: each component's standard deviation over the data.
        threshold: > 0.

    Returns:
        ``[B]`` float: the number of leading steps with error ``<= threshold``; ``inf`` when the error
        stays below the threshold over the whole horizon ``p`` (censored: see :func:`summarize_valid_time`).
    """
    if pred.dim() != 3:
        raise ValueError(f"pred must be [B, p, D] (flatten the measurement into D), got {tuple(pred.shape)}")
    if pred.shape != truth.shape:
        raise ValueError(f"pred {tuple(pred.shape)} and truth {tuple(truth.shape)} must have the same shape [B, p, D]")
    scale = torch.as_tensor(scale)
    if scale.dim() > 1 or (scale.dim() == 1 and scale.shape[0] != pred.shape[2]):
        raise ValueError(
            f"scale must be [D] = [{pred.shape[2]}] (one std per component) or a scalar, got {tuple(scale.shape)}"
        )
    if not (scale > 0).all():
        raise ValueError("scale must be > 0 everywhere: a constant component has no scale, leave it out")
    return valid_steps(((pred - truth) / scale.to(pred)).pow(2).mean(dim=2).sqrt(), threshold)


def valid_steps(error: torch.Tensor, threshold: float = 0.5) -> torch.Tensor:
    """``[B]``: the leading steps of each row of normalised errors ``[B, p]`` that stay ``<= threshold``
    (``inf`` when none exceeds it; NaN counts as invalid). :func:`valid_prediction_time` from the errors."""
    _check_positive(threshold, "threshold")
    if error.dim() != 2:
        raise ValueError(f"error must be [B, p] (one normalised error per sequence and step), got {tuple(error.shape)}")
    invalid = ~(error <= threshold)
    first = invalid.to(torch.int8).argmax(dim=1).to(torch.float64)  # first invalid step (0 if none)
    return torch.where(invalid.any(dim=1), first, torch.full_like(first, math.inf))


def summarize_valid_time(
    steps: torch.Tensor, horizon: int, dt: float, largest_exponent: float | None
) -> dict[str, float | None]:
    """Summary of :func:`valid_prediction_time` over sequences.

    ``inf`` (valid over the whole horizon) is censored: counted as ``horizon`` steps in the mean,
    std and median (which are then lower bounds); ``censored_share`` says how often it happened.

    Returns:
        ``mean_steps``, ``std_steps`` (population), ``median_steps``, ``censored_share``,
        ``mean_seconds``, ``median_seconds`` (``x dt``), ``mean_lyapunov_times``,
        ``median_lyapunov_times`` (``x dt x largest_exponent``; ``None`` unless ``largest_exponent > 0``),
        ``horizon``, ``n``.
    """
    if steps.dim() != 1 or steps.numel() == 0:
        raise ValueError(f"steps must be the [B] output of valid_prediction_time, got shape {tuple(steps.shape)}")
    _check_count(horizon, "horizon", 1)
    _check_positive(dt, "dt")
    steps = steps.detach().to(torch.float64)
    censored = torch.isinf(steps)
    if (steps < 0).any() or torch.isnan(steps).any() or (steps[~censored] > horizon).any():
        raise ValueError(
            f"steps must lie in [0, horizon={horizon}] or be inf; check that horizon is the forecast length"
        )
    values = torch.where(censored, torch.full_like(steps, float(horizon)), steps)
    mean, median = float(values.mean()), float(values.quantile(0.5))
    lyap = largest_exponent is not None and largest_exponent > 0
    return {
        "mean_steps": mean,
        "std_steps": float(values.std(correction=0)),
        "median_steps": median,
        "censored_share": float(censored.to(torch.float64).mean()),
        "mean_seconds": mean * dt,
        "median_seconds": median * dt,
        "mean_lyapunov_times": mean * dt * largest_exponent if lyap else None,
        "median_lyapunov_times": median * dt * largest_exponent if lyap else None,
        "horizon": int(horizon),
        "n": steps.numel(),
    }


# ---------------------------------------------------------------------------- oscillators
def _check_series(x: torch.Tensor) -> None:
    if x.dim() != 3 or x.shape[0] < 1 or x.shape[2] < 1:
        raise ValueError(f"x must be time series [R, T, D] (flatten frames into D), got {tuple(x.shape)}")


def dominant_period(x: torch.Tensor, dt: float, pad_factor: int = 4) -> torch.Tensor:
    """Per run, the period (seconds) of the strongest non-zero frequency.

    The series is mean-removed per component, Hann-windowed and zero-padded to ``pad_factor * T``;
    its power is summed over ``D``, and the peak (DC excluded) is refined by a parabola through the
    log power of the peak bin and its neighbours: a sine's period comes out within 0.1% when the run
    holds at least 3 periods (with fewer, the peak is too broad to trust).

    Args:
        x: ``[R, T, D]``, e.g. decoded frames flattened; ``T >= 4``.
        dt: sampling period.

    Returns:
        ``[R]`` periods in seconds (float64); NaN for a constant run.
    """
    _check_series(x)
    _check_positive(dt, "dt")
    _check_count(pad_factor, "pad_factor", 1)
    t = x.shape[1]
    if t < 4:
        raise ValueError(f"dominant_period needs T >= 4 samples per run, got {t}")
    x = x.detach().to(torch.float64)
    window = torch.hann_window(t, periodic=False, dtype=torch.float64, device=x.device)
    x = (x - x.mean(dim=1, keepdim=True)) * window[:, None]
    n_fft = int(pad_factor) * t
    power = torch.fft.rfft(x, n=n_fft, dim=1).abs().pow(2).sum(dim=2)  # [R, F]
    peak = power[:, 1:].argmax(dim=1) + 1
    log_power = power.clamp_min(torch.finfo(torch.float64).tiny).log()
    inner = peak.clamp(max=power.shape[1] - 2)  # the last bin has no right neighbour: no refinement there
    lo, mid, hi = (log_power.gather(1, (inner + o)[:, None])[:, 0] for o in (-1, 0, 1))
    curvature = lo - 2 * mid + hi
    shift = torch.where(curvature < 0, 0.5 * (lo - hi) / curvature, torch.zeros_like(mid))
    shift = torch.where(peak == inner, shift.clamp(-0.5, 0.5), torch.zeros_like(shift))
    freq = (peak.to(torch.float64) + shift) / (n_fft * dt)
    period = 1.0 / freq
    return torch.where(power[:, 1:].sum(dim=1) > 0, period, torch.full_like(period, math.nan))


def amplitude_ratio(x: torch.Tensor, window: int) -> torch.Tensor:
    """Per run, the amplitude of the last ``window`` steps over that of the first ``window`` steps.

    The amplitude of a window is its standard deviation over time, each component about its own
    window mean, pooled over ``D`` (root mean square of the per-component standard deviations), so
    a static background (image pixels that never change) does not count. ``~1``: a conserved
    oscillation; ``< 1``: decaying (e.g. to a fixed point); ``> 1``: growing.

    Args:
        x: ``[R, T, D]``.
        window: ``2 <= window <= T``; whole periods make the ratio exact for a sine.

    Returns:
        ``[R]`` (float64); NaN / inf when the first window is constant.
    """
    _check_series(x)
    if int(window) != window or not 2 <= window <= x.shape[1]:
        raise ValueError(f"window must be an integer between 2 and T = {x.shape[1]}, got {window!r}")
    x = x.detach().to(torch.float64)

    def amplitude(part: torch.Tensor) -> torch.Tensor:
        return part.var(dim=1, correction=0).mean(dim=1).sqrt()

    return amplitude(x[:, -int(window) :]) / amplitude(x[:, : int(window)])


# ---------------------------------------------------------------------------- one report of a learned SSM
def dynamics_report(
    f: Fn,
    g: Fn,
    starts: torch.Tensor,
    dt: float,
    *,
    to_units: Fn | None = None,
    reference: torch.Tensor | None = None,
    lyapunov_steps: int = 4000,
    transient: int = 2000,
    align: int = 600,
    free_steps: int = 20_000,
    wing_level: float | None = None,
    true_f: Fn | None = None,
    true_starts: torch.Tensor | None = None,
    free_starts: torch.Tensor | None = None,
) -> dict:
    """What ``f`` and ``g`` do on their own, from the states ``starts [R, d]`` (e.g. shooting nodes).

    - ``lyapunov``: the spectrum of ``f`` per time unit (float64, ``transient`` then ``align`` steps
      before ``lyapunov_steps`` accumulated ones), its largest exponent and the Lyapunov time; with
      ``true_f`` (and ``true_starts``, states of the true system) the same for the true system;
    - ``free_run``: ``f`` iterated ``free_steps`` steps after the transient from ``free_starts [R', d]``
      (default: ``starts``; more runs than the spectrum's steady the statistics) and decoded by ``g`` (in
      original units through ``to_units``): per measured component its mean and std, and with
      ``reference [M, D]`` (noiseless measurements of the data, original units) the 1-Wasserstein
      distance to them (:func:`attractor_statistics`); with ``wing_level`` the share of runs visiting
      both Lorenz wings in the first measured component.

    Returns a JSON-ready dict (lists and floats).
    """
    _check_states(starts, "starts")
    _check_positive(dt, "dt")

    def spectrum(fn: Fn, x0: torch.Tensor) -> dict:
        res = lyapunov_spectrum(fn, x0.double(), lyapunov_steps, dt, transient, align=align)
        largest = float(res.exponents[0])
        return {
            "exponents": res.exponents.tolist(),
            "std_over_runs": res.std.tolist(),
            "largest": largest,
            "lyapunov_time": lyapunov_time(largest),
            "runs": len(x0),
            "steps": lyapunov_steps,
            "dt": dt,
        }

    f64 = _in_float64(f)
    report: dict = {"lyapunov": spectrum(f64, starts)}
    if true_f is not None:
        if true_starts is None:
            raise ValueError("true_f needs true_starts: states of the true system to start its runs from")
        report["lyapunov_true"] = spectrum(true_f, true_starts)
    with torch.no_grad():
        if free_starts is not None:
            _check_states(free_starts, "free_starts")
        run = free_run(f, starts if free_starts is None else free_starts, free_steps, transient)  # [R, S, d]
        y = g(run.reshape(-1, run.shape[-1]))
        if to_units is not None:
            y = to_units(y)
    y = y.reshape(run.shape[0], run.shape[1], -1).double()  # [R, S, D]
    stats = {
        "runs": run.shape[0],
        "steps": free_steps,
        "transient": transient,
        "finite_share": float(torch.isfinite(y).all(dim=(1, 2)).double().mean()),
    }
    if reference is not None:
        reference = reference.reshape(len(reference), -1).double()
        if reference.shape[1] != y.shape[-1]:
            raise ValueError(f"reference has {reference.shape[1]} components per sample, g gives {y.shape[-1]}")
        finite = y[torch.isfinite(y).all(dim=(1, 2))]
        if len(finite):
            stats.update(attractor_statistics(finite.reshape(-1, y.shape[-1]), reference))
    if wing_level is not None:
        stats["both_wings_share"] = both_wings_share(y[..., 0], wing_level)
        stats["wing_level"] = wing_level
    report["free_run"] = stats
    return report


def _in_float64(f: Fn) -> Fn:
    """``f`` evaluated in float64: a copy of an ``nn.Module`` converted to double, else the function itself."""
    if isinstance(f, torch.nn.Module):
        import copy

        return copy.deepcopy(f).double()
    return f
