"""Arrays in and out of :class:`ssm_ms.SSM`'s methods: numpy or torch, one sequence ``[T, ...]`` or a batch
``[B, T, ...]``, checked with one message naming the argument and the shape expected."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch


def as_tensor(a: Any, what: str) -> tuple[torch.Tensor, bool]:
    """``a`` (an array, a tensor, nested lists) as a float32 tensor, and whether it came as numpy."""
    if isinstance(a, torch.Tensor):
        return a.detach().to(torch.float32), False
    try:
        arr = np.asarray(a, dtype=np.float32)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{what} must be an array of numbers ({err})") from None
    return torch.from_numpy(arr.copy()), True


def check_finite(t: torch.Tensor, what: str) -> None:
    """One message naming the first NaN or inf of ``what``."""
    bad = ~torch.isfinite(t)
    if bool(bad.any()):
        where = bad.nonzero()[0].tolist()
        raise ValueError(f"{what} holds NaN or inf (first at index {where}): give finite values")


def as_output(t: torch.Tensor, batched: bool, as_numpy: bool) -> np.ndarray | torch.Tensor:
    """A result as it came in: one sequence or a batch, numpy or torch."""
    t = t if batched else t[0]
    return t.detach().cpu().numpy() if as_numpy else t


def stream_tensor(y: Any, obs: tuple[int, ...], what: str, missing: bool = False) -> tuple[torch.Tensor, bool, bool]:
    """One stream's samples of shape ``obs`` -> ``([B, T, *obs]``, batched, was numpy): ``[T, *obs]`` or
    ``[B, T, *obs]``; one component also ``[T]``, grey images ``(1, H, W)`` also ``[T, H, W]`` / ``[B, T, H, W]``.
    ``missing``: NaN allowed (a sensor's unsampled times)."""
    t, as_numpy = as_tensor(y, what)
    if obs == (1,) and t.ndim == 1:
        t = t.unsqueeze(-1)  # one measured component: [T]
    grey = len(obs) == 3 and obs[0] == 1 and t.ndim in (3, 4) and tuple(t.shape[-3:]) != obs
    if grey and tuple(t.shape[-2:]) == obs[1:]:
        t = t.unsqueeze(-3)  # [T, H, W] or [B, T, H, W]: grey images without their channel
    if t.ndim not in (len(obs) + 1, len(obs) + 2) or tuple(t.shape[t.ndim - len(obs) :]) != obs:
        raise ValueError(
            f"{what} must be [T, {', '.join(map(str, obs))}] (or a batch [B, T, ...]): this model's measurements "
            f"have shape {obs}, got {list(t.shape)}"
        )
    batched = t.ndim == len(obs) + 2
    t = t if batched else t.unsqueeze(0)
    check_finite(torch.nan_to_num(t, nan=0.0) if missing else t, what)
    return t, batched, as_numpy


def input_tensor(u: Any, m: int, what: str) -> tuple[torch.Tensor, bool, bool]:
    """``u``, ``m`` inputs per step -> ``([B, T, m]`` in the user's units, batched, was numpy)."""
    t, as_numpy = as_tensor(u, what)
    if m == 1 and t.ndim == 1:
        t = t.unsqueeze(-1)  # one input: [T]
    if t.ndim not in (2, 3) or t.shape[-1] != m:
        raise ValueError(f"{what} must be [T, {m}] (or a batch [B, T, {m}]): got {list(t.shape)}")
    batched = t.ndim == 3
    t = t if batched else t.unsqueeze(0)
    check_finite(t, what)
    return t, batched, as_numpy
