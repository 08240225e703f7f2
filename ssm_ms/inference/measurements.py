"""Input checks shared by the filters."""

from __future__ import annotations

from torch import Tensor


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
