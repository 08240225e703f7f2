"""Pieces shared by the filters: the measurement check and reduced-precision calls of ``f`` and ``g``."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

AUTOCAST_DTYPES = {"bfloat16": torch.bfloat16, "float16": torch.float16}


def check_measurements(y: object) -> tuple[int, int]:
    """Validate measurements ``y [B, T, *obs_shape]`` for a filter; returns ``(B, T)``."""
    if not isinstance(y, Tensor) or y.ndim < 3:
        shape = list(y.shape) if isinstance(y, Tensor) else type(y).__name__
        raise ValueError(f"y must be a tensor [B, T, *obs_shape] (batch, time, observation), got {shape}")
    if not y.is_floating_point():
        raise ValueError(
            f"y must be floating point, got {y.dtype}: convert images with datamodules.normalizer.to_float"
        )
    bsz, steps = y.shape[:2]
    if bsz == 0 or steps == 0:
        raise ValueError(f"y must hold at least one trajectory and one step, got shape {list(y.shape)}")
    return bsz, steps


def check_autocast(name: str | None) -> torch.dtype | None:
    """``None`` or the name of a reduced precision for ``torch.autocast`` -> the torch dtype."""
    if name is None:
        return None
    if name not in AUTOCAST_DTYPES:
        raise ValueError(f"autocast must be null (full precision) or one of {sorted(AUTOCAST_DTYPES)}, got {name!r}")
    return AUTOCAST_DTYPES[name]


def call_model(fn: Callable[[Tensor], Tensor], x: Tensor, autocast: torch.dtype | None) -> Tensor:
    """``fn(x)``; with ``autocast`` set, under ``torch.autocast`` on ``x``'s device, cast back to ``x``'s dtype.

    Autocast runs the matrix products and convolutions of ``fn`` in the reduced precision (with
    higher-precision accumulation) and leaves precision-sensitive operations in float32; the caller's
    own algebra is untouched because the context ends with the call.
    """
    if autocast is None:
        return fn(x)
    with torch.autocast(x.device.type, dtype=autocast):
        out = fn(x)
    return out.to(x.dtype) if isinstance(out, Tensor) else out  # a non-tensor: the callers' checks name it


def driven(f: Callable[..., Tensor], u: Tensor | None, repeats: int) -> Callable[[Tensor], Tensor]:
    """``f`` as a function of the state alone: ``f`` itself without inputs, else ``x -> f(x, u)`` with the inputs
    ``u [B, m]`` of a batch repeated for its ``repeats`` points per trajectory (sigma points, particles), rows
    ``[B * repeats, d]`` trajectory-major."""
    if u is None:
        return f
    rows = u.repeat_interleave(repeats, dim=0)
    return lambda x: f(x, rows.to(x.dtype))


def check_inputs(u: Tensor | None, batch: int, steps: int, what: str) -> None:
    """Refuse inputs ``u`` that do not cover ``steps`` transitions of ``batch`` trajectories (``[B, >= steps, m]``)."""
    if u is None:
        return
    if u.dim() != 3 or u.shape[0] != batch or u.shape[1] < steps:
        raise ValueError(
            f"{what}: inputs u must be [B, >= {steps}, m] with B={batch} ({steps} transitions), got {list(u.shape)}"
        )
