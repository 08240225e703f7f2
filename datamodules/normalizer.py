"""The measurements' normalisation, and arrays served as float tensors.

:class:`Normalizer` is the per-channel affine normalisation ``(y - mean) / std`` that a DataModule
(:mod:`datamodules.base`) fits on its training split, for the measurements and for the inputs ``u``; a
checkpoint keeps it as a plain dictionary of tensors (:meth:`Normalizer.state_dict`,
:meth:`Normalizer.from_state_dict`), never as a pickled object. :func:`to_float` turns a stored array (``uint8``
images as 0..255) into the float32 tensor a batch holds.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch


class Normalizer:
    """Per-channel affine normalisation ``(y - mean) / std`` over the first observation axis.

    ``mean`` and ``std`` have shape ``[C]`` (images, normalised per channel) or ``[D]`` (vectors,
    per component); they broadcast over the remaining observation axes.
    """

    def __init__(self, mean: torch.Tensor, std: torch.Tensor, obs_ndim: int):
        self.mean = torch.as_tensor(mean, dtype=torch.float32)
        self.std = torch.as_tensor(std, dtype=torch.float32)
        self.obs_ndim = obs_ndim
        if (self.std <= 0).any() or not torch.isfinite(self.std).all():
            raise ValueError(
                f"normalisation std must be positive and finite, got {self.std.tolist()}: a channel of the "
                "training data is constant; turn normalisation off (data.normalize: false) or drop that channel"
            )

    @classmethod
    def identity(cls, channels: int, obs_ndim: int) -> Normalizer:
        return cls(torch.zeros(channels), torch.ones(channels), obs_ndim)

    @property
    def is_identity(self) -> bool:
        return bool((self.mean == 0).all() and (self.std == 1).all())

    def _view(self, t: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        return t.to(like.device, like.dtype).view(-1, *([1] * (self.obs_ndim - 1)))

    def normalize(self, y: torch.Tensor) -> torch.Tensor:
        """``y``: ``[..., *obs_shape]`` in original units -> normalised units."""
        return (y - self._view(self.mean, y)) / self._view(self.std, y)

    def denormalize(self, y: torch.Tensor) -> torch.Tensor:
        """``y``: ``[..., *obs_shape]`` in normalised units -> original units."""
        return y * self._view(self.std, y) + self._view(self.mean, y)

    def state_dict(self) -> dict[str, Any]:
        return {"mean": self.mean.clone(), "std": self.std.clone(), "obs_ndim": self.obs_ndim}

    @classmethod
    def from_state_dict(cls, state: Mapping[str, Any]) -> Normalizer:
        return cls(state["mean"], state["std"], int(state["obs_ndim"]))


def to_float(a: np.ndarray) -> torch.Tensor:
    """Array -> float32 tensor (a copy); ``uint8`` arrays are images stored as 0..255 and map to [0, 1]."""
    t = torch.from_numpy(np.array(a))  # copies: `a` may be a read-only memory map
    if t.dtype == torch.uint8:
        return t.to(torch.float32).mul_(1.0 / 255.0)
    return t.to(torch.float32)
