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
        raise ValueError(f"y must be floating point, got {y.dtype}: convert images with base.to_float")
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
