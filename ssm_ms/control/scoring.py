"""Scores of a batch of closed-loop episodes: a success rate's confidence interval, statistics over episodes, when
the pendulum first stays up."""

from __future__ import annotations

import math

import torch


def wilson_interval(successes: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """The Wilson score interval of a success rate from ``successes`` of ``n`` trials (95% for the default ``z``):
    inside ``[0, 1]`` also at 0 or ``n`` successes, where the normal approximation's collapses to a point."""
    if n < 1:
        return float("nan"), float("nan")
    p, z2 = successes / n, z * z
    centre = (p + z2 / (2 * n)) / (1 + z2 / n)
    half = z * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n)) / (1 + z2 / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def episode_stats(values: torch.Tensor) -> dict[str, float]:
    """Mean and std of the finite values over episodes, how many, how many not finite."""
    values = values.double()
    finite = values[torch.isfinite(values)]
    return {
        "mean": float(finite.mean()) if len(finite) else float("nan"),
        "std": float(finite.std(unbiased=False)) if len(finite) else float("nan"),
        "n": int(values.numel()),
        "non_finite": int(values.numel() - finite.numel()),
    }


def first_upright(error: torch.Tensor, tolerance: float, window: int) -> torch.Tensor:
    """Per episode, the first step from which the angle stays within ``tolerance`` for ``window`` steps (``nan``:
    never)."""
    inside = (error < tolerance).double()
    out = torch.full((len(error),), float("nan"), dtype=torch.float64)
    for e in range(len(error)):
        runs = torch.nn.functional.conv1d(inside[e][None, None], torch.ones(1, 1, window, dtype=torch.float64))[0, 0]
        hits = torch.nonzero(runs >= window - 0.5)
        if len(hits):
            out[e] = float(hits[0, 0])
    return out
