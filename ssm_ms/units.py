"""The user's units and the model's: the affine normalisation a model was trained with, and ``f`` and ``g`` wrapped
to work in the user's units.

A DataModule serves measurements ``y`` and inputs ``u`` normalised per channel, ``(y - mean) / std`` (the
statistics of its training split); the model learns ``f`` and ``g`` on those. :class:`Units` holds the statistics
(read from the data state a model keeps, :attr:`ssm_ms.module.MultipleShootingModule.data_state`) and converts
between the two; :class:`TransitionInUnits` and :class:`ObservationInUnits` are ``f`` taking inputs and ``g``
returning measurements in the user's units, for code that knows nothing of normalisation (a filter, an export).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from torch import nn


class _Affine:
    """``(v - mean) / std`` per channel of the first of the ``obs_ndim`` trailing axes."""

    def __init__(self, mean: Any, std: Any, obs_ndim: int):
        self.mean = torch.as_tensor(mean, dtype=torch.float64).flatten()
        self.std = torch.as_tensor(std, dtype=torch.float64).flatten()
        self.obs_ndim = int(obs_ndim)

    @classmethod
    def of(cls, state: Mapping[str, Any] | None) -> _Affine | None:
        """From a DataModule's saved normaliser (``{"mean", "std", "obs_ndim"}``); ``None`` for the identity."""
        if state is None:
            return None
        affine = cls(state["mean"], state["std"], int(state["obs_ndim"]))
        return None if bool((affine.mean == 0).all() and (affine.std == 1).all()) else affine

    def _shaped(self, t: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        return t.to(like.device, like.dtype).view(-1, *([1] * (self.obs_ndim - 1)))

    def to_model(self, v: torch.Tensor) -> torch.Tensor:
        return (v - self._shaped(self.mean, v)) / self._shaped(self.std, v)

    def to_user(self, v: torch.Tensor) -> torch.Tensor:
        return v * self._shaped(self.std, v) + self._shaped(self.mean, v)

    def per_component_std(self, shape: tuple[int, ...]) -> torch.Tensor:
        """The std of every element of one sample of ``shape`` (the channels broadcast), flattened."""
        return self._shaped(self.std, self.std).expand(shape).flatten()


class Units:
    """The measurements' and the inputs' normalisation of a model: user's units <-> the model's.

    Built from a DataModule's saved state (:meth:`from_data_state`); a part the data were not normalised in (or have
    not: no inputs) is the identity. Tensors keep their dtype and device.
    """

    def __init__(self, measurements: _Affine | None = None, inputs: _Affine | None = None):
        self.measurements, self.inputs = measurements, inputs

    @classmethod
    def from_data_state(cls, state: Mapping[str, Any] | None) -> Units:
        """From the state a DataModule saves in checkpoints (``normalizer``, ``input_normalizer``); ``None``: the
        identity (a model trained without a DataModule)."""
        state = state or {}
        return cls(_Affine.of(state.get("normalizer")), _Affine.of(state.get("input_normalizer")))

    @property
    def is_identity(self) -> bool:
        return self.measurements is None and self.inputs is None

    def y_to_model(self, y: torch.Tensor) -> torch.Tensor:
        """Measurements ``[..., *obs_shape]``, user's units -> the model's."""
        return y if self.measurements is None else self.measurements.to_model(y)

    def y_to_user(self, y: torch.Tensor) -> torch.Tensor:
        """Measurements ``[..., *obs_shape]``, the model's units -> the user's."""
        return y if self.measurements is None else self.measurements.to_user(y)

    def u_to_model(self, u: torch.Tensor) -> torch.Tensor:
        """Inputs ``[..., m]``, user's units -> the model's."""
        return u if self.inputs is None else self.inputs.to_model(u)

    def measurement_std(self, obs_shape: tuple[int, ...]) -> torch.Tensor:
        """Each flattened measurement component's std (1 where not normalised): a variance in the model's units
        times its square is the same variance in the user's."""
        if self.measurements is None:
            return torch.ones(int(torch.Size(obs_shape).numel()), dtype=torch.float64)
        return self.measurements.per_component_std(tuple(obs_shape))


class TransitionInUnits(nn.Module):
    """``f`` taking its inputs in the user's units: ``f(x, (u - mean) / std)``; an autonomous ``f`` as it is.
    Keeps ``f``'s ``state_dim`` and ``input_dim``."""

    def __init__(self, f: nn.Module, units: Units):
        super().__init__()
        self.inner, self.units = f, units
        self.state_dim = getattr(f, "state_dim", None)
        self.input_dim = int(getattr(f, "input_dim", 0))

    def forward(self, x: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        return self.inner(x) if u is None else self.inner(x, self.units.u_to_model(u))


class ObservationInUnits(nn.Module):
    """``g`` returning measurements in the user's units: ``g(x) * std + mean``."""

    def __init__(self, g: nn.Module, units: Units):
        super().__init__()
        self.inner, self.units = g, units

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.units.y_to_user(self.inner(x))
