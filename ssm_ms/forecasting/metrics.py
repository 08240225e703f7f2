"""The forecasting protocol's scores, per test sequence, as plain tensor functions (no Lightning).

Frame bookkeeping for a test sequence ``y[0..T-1]`` (:func:`split_sequence`): measurements ``y[0..k-1]`` are
given to the forecaster, which predicts ``y[k..k+p-1]`` (``p = T - k`` unless set).

Metrics (per test sequence, then mean and std over sequences by :func:`sequence_summary`):

* ``mse``: squared error averaged over the elements of a frame and the predicted frames;
* ``bce``: ``-[t log(p + 1e-12) + (1 - t) log(1 - p + 1e-12)]`` (the reference code's clamping, no
  other clipping), averaged over the pixels of a frame (``bce_reduction: mean``) or summed over them
  (``sum``, the paper's Moving MNIST Table 3 convention), then averaged over predicted frames;
* ``mse_sum``: squared error summed over the elements of a frame, averaged over the predicted frames (the
  per-frame MSE of video-prediction papers and OpenSTL);
* ``ssim`` (images in [0, 1]): the structural similarity of each predicted frame (Wang et al. 2004: an 11 x 11
  Gaussian window of std 1.5, ``C1 = 0.01^2``, ``C2 = 0.03^2``, averaged over the window positions inside
  the frame and over channels, as OpenSTL computes it), averaged over the predicted frames; higher is better.

Several sensors (:mod:`ssm_ms.nets.sensors`) are scored stream by stream, each in its own shape, a frame a stream
did not sample (NaN) left out of its average (``sequence_metrics(..., missing=True)``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch

# a simulation or forecast farther than this many training standard deviations from the data's mean has diverged
DIVERGENCE_BOUND = 100.0


def first_divergence(y: torch.Tensor, bound: float | None = DIVERGENCE_BOUND) -> torch.Tensor:
    """Per sequence of ``y [B, T, ...]`` (normalised units), the first step that is not finite or, with ``bound``,
    exceeds it in magnitude; ``-1`` where there is none."""
    bad = ~torch.isfinite(y).flatten(2).all(-1)
    if bound is not None:
        bad |= y.flatten(2).abs().amax(-1).nan_to_num(float("inf")) > bound
    return torch.where(bad.any(1), bad.float().argmax(1), torch.full(bad.shape[:1], -1, device=y.device))


BCE_EPS = 1e-12
METRICS = ("mse", "bce", "mse_sum", "ssim")
SSIM_WINDOW, SSIM_SIGMA, SSIM_K1, SSIM_K2 = 11, 1.5, 0.01, 0.03


def split_sequence(y: torch.Tensor, n_filter: int, n_predict: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """``y [B, T, ...]`` -> (measurements given to inference ``[B, k, ...]``, frames to predict ``[B, p, ...]``)."""
    t = y.shape[1]
    p = t - n_filter if n_predict is None else n_predict
    if n_filter < 1 or p < 1 or n_filter + p > t:
        raise ValueError(
            f"cannot filter {n_filter} and predict {p} frames of sequences of length {t}: "
            f"choose n_filter + n_predict <= {t} with both >= 1"
        )
    return y[:, :n_filter], y[:, n_filter : n_filter + p]


def over_frames(per_frame: torch.Tensor, sampled: torch.Tensor | None = None) -> torch.Tensor:
    """``[B, p]`` per-frame scores -> ``[B]``: their mean over the frames, or over the ``sampled [B, p]`` ones
    (NaN for a sequence with none)."""
    if sampled is None:
        return per_frame.mean(1)
    return torch.where(sampled, per_frame, 0.0).sum(1) / sampled.sum(1)


def mse_per_sequence(pred: torch.Tensor, target: torch.Tensor, sampled: torch.Tensor | None = None) -> torch.Tensor:
    """``[B, p, ...]`` -> ``[B]``: squared error averaged over frame elements and (``sampled``) frames."""
    return over_frames((pred - target).pow(2).flatten(2).mean(2), sampled)


def bce_per_sequence(
    pred: torch.Tensor, target: torch.Tensor, reduction: str = "mean", sampled: torch.Tensor | None = None
) -> torch.Tensor:
    """``[B, p, ...]`` -> ``[B]``: binary cross-entropy per frame (mean or sum over its elements), averaged over
    (``sampled``) frames."""
    if reduction not in ("mean", "sum"):
        raise ValueError(f"bce_reduction must be 'mean' or 'sum', got {reduction!r}")
    e = -(target * torch.log(pred + BCE_EPS) + (1 - target) * torch.log(1 - pred + BCE_EPS))
    per_frame = e.flatten(2)
    return over_frames(per_frame.mean(2) if reduction == "mean" else per_frame.sum(2), sampled)


def mse_sum_per_sequence(pred: torch.Tensor, target: torch.Tensor, sampled: torch.Tensor | None = None) -> torch.Tensor:
    """``[B, p, ...]`` -> ``[B]``: squared error summed over a frame's elements, averaged over (``sampled``) frames."""
    return over_frames((pred - target).pow(2).flatten(2).sum(2), sampled)


def ssim_per_sequence(pred: torch.Tensor, target: torch.Tensor, sampled: torch.Tensor | None = None) -> torch.Tensor:
    """``[B, p, C, H, W]`` images in [0, 1] -> ``[B]``: each frame's SSIM (see the module doc: the window positions
    that lie inside the frame, no padding), averaged over (``sampled``) frames. Computed in float64."""
    if pred.dim() != 5 or min(pred.shape[-2:]) < SSIM_WINDOW:
        raise ValueError(
            f"metric 'ssim' needs image frames [B, T, C, H, W] of at least {SSIM_WINDOW} x {SSIM_WINDOW} "
            f"pixels, got {list(pred.shape)}: leave 'ssim' out of metrics for this data"
        )
    b, p, c, h, w = pred.shape
    x = pred.detach().reshape(b * p * c, h, w).double()
    y = target.detach().reshape(b * p * c, h, w).double()
    r = torch.arange(SSIM_WINDOW, dtype=torch.float64, device=x.device) - SSIM_WINDOW // 2
    g = torch.exp(-(r**2) / (2 * SSIM_SIGMA**2))
    g = (g / g.sum()).tolist()

    def local_mean(z: torch.Tensor) -> torch.Tensor:
        # the Gaussian window is separable: filter the rows, then the columns (valid positions only), in shifted
        # sums that hold no more than the frames (conv2d in float64 on a CPU unfolds every window: ~7 GB for 2000
        # frames of 48 x 48)
        k = SSIM_WINDOW
        rows = sum(g[i] * z[:, i : i + h - k + 1] for i in range(k))
        return sum(g[j] * rows[:, :, j : j + w - k + 1] for j in range(k))

    mu_x, mu_y, xx, yy, xy = (local_mean(z) for z in (x, y, x * x, y * y, x * y))
    var_x, var_y, cov = xx - mu_x**2, yy - mu_y**2, xy - mu_x * mu_y
    c1, c2 = SSIM_K1**2, SSIM_K2**2
    ssim = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2))
    return over_frames(ssim.reshape(b, p, -1).mean(2), sampled).to(pred.dtype)


def sequence_metrics(
    pred: torch.Tensor, target: torch.Tensor, metrics: Sequence[str], bce_reduction: str, missing: bool = False
) -> dict[str, torch.Tensor]:
    """``{metric: [B]}`` for the names in ``metrics`` (see :data:`METRICS` and the module doc). With ``missing``,
    a target frame holding NaN is one the sensor did not sample: each sequence's scores average over its sampled
    frames only (NaN for a sequence with none; a NaN forecast of a sampled frame still scores NaN)."""
    sampled = None
    if missing:
        sampled = ~target.isnan().flatten(2).any(2)
        target = torch.where(target.isnan(), 0.5, target)  # any finite value: those frames are left out
    per_sequence = {
        "mse": mse_per_sequence,
        "bce": lambda p, t, s: bce_per_sequence(p, t, bce_reduction, s),
        "mse_sum": mse_sum_per_sequence,
        "ssim": ssim_per_sequence,
    }
    return {name: per_sequence[name](pred, target, sampled) for name in metrics}


# ---------------------------------------------------------------------------- summaries
def sequence_summary(values: torch.Tensor) -> dict[str, float]:
    """``{"mean", "std", "n", "non_finite"}`` of per-sequence scores: ``n`` sequences, of which ``non_finite`` scored
    NaN or inf (a forecast that diverged); mean and std are over the finite ones (NaN when none is)."""
    values = torch.as_tensor(values).flatten().double()
    finite = values[torch.isfinite(values)]
    mean, std = (finite.mean().item(), finite.std(unbiased=False).item()) if finite.numel() else (math.nan, math.nan)
    return {"mean": mean, "std": std, "n": values.numel(), "non_finite": values.numel() - finite.numel()}


def flat_scalars(tree: Mapping[str, Any], prefix: str = "") -> dict[str, float]:
    """Numeric leaves of a nested dict as ``{"a/b": value}`` (lists give ``a/b/0``, ...), for TensorBoard."""
    out: dict[str, float] = {}
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(flat_scalars(value, name + "/"))
        elif isinstance(value, (list, tuple)):
            out.update({f"{name}/{i}": float(v) for i, v in enumerate(value) if isinstance(v, (int, float))})
        elif isinstance(value, (int, float)) and not isinstance(value, bool) and np.isfinite(value):
            out[name] = float(value)
    return out
