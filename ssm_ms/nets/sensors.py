"""Several sensors at once: named measurement streams of their own shapes and noise, packed side by side.

A system seen by a camera and a joint encoder, or by two cameras, is measured at every step by several *streams*.
ssm-ms keeps one measurement tensor per step: the streams flattened and concatenated in a fixed order, ``y [..., P]``
with ``P`` the sum of the streams' sizes, described by a :class:`SensorLayout` (names, shapes, noise levels). So the
shooting loss, the filters and the forecasts handle several sensors as they handle one vector sensor, and the layout
splits the packed vector back into streams where their shapes matter (the image of an image stream, per-stream
scores).

- **Weights**: the fit weighs each component by the inverse of its stream's noise variance (the maximum-likelihood
  weighting of independent Gaussian sensors), scaled so that the weights average 1 (the fit keeps the scale the gap
  weight ``alpha`` was chosen for): :meth:`SensorLayout.weights`. A model's ``stream_weights`` multiply a stream's
  weight by a factor of its own before that scaling (a sensor trusted less, or more, than its noise says).
- **Missing samples**: a stream sampled at a lower rate holds NaN where it was not sampled; the fit and the filters
  leave those components out (masked, not refused).
- **g**: :class:`SensorHeads`, one head per stream (e.g. a :class:`~ssm_ms.nets.ConvDecoder` for the image, a
  :class:`~ssm_ms.nets.LinearReadout` for the angle), its output packed in the layout's order.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn


def by_stream(
    layout: SensorLayout | Sequence[Mapping] | None, *tensors: torch.Tensor | None
) -> dict[str, tuple[torch.Tensor | None, ...]]:
    """Measurements ``[..., P]`` split for drawing: ``{"": tensors}`` for one sensor (``layout`` ``None``), else
    ``{name: (each tensor's stream [..., *shape])}`` in the layout's order (``None`` stays ``None``)."""
    if not layout:
        return {"": tensors}
    layout = layout if isinstance(layout, SensorLayout) else SensorLayout.from_state_dict(layout)
    parts = [None if t is None else layout.split(t) for t in tensors]
    return {name: tuple(None if p is None else p[name] for p in parts) for name in layout.names}


@dataclass(frozen=True)
class Stream:
    """One sensor: its ``name``, the ``shape`` of one sample (``[C, H, W]`` an image, ``[D]`` a vector) and the
    standard deviation of its noise (in the units it is served in)."""

    name: str
    shape: tuple[int, ...]
    noise_std: float = 1.0

    @property
    def size(self) -> int:
        return math.prod(self.shape)


class SensorLayout:
    """The streams of a packed measurement vector, in order (see the module doc)."""

    def __init__(self, streams: Sequence[Stream]):
        if not streams:
            raise ValueError("a sensor layout needs at least one stream")
        names = [s.name for s in streams]
        if len(set(names)) != len(names):
            raise ValueError(f"stream names must differ, got {names}")
        for s in streams:
            if not s.noise_std > 0 or s.size < 1:
                raise ValueError(f"stream {s.name!r}: noise_std must be > 0 and its shape non-empty, got {s}")
        self.streams = list(streams)
        self.offsets = [0]
        for s in self.streams:
            self.offsets.append(self.offsets[-1] + s.size)

    @property
    def size(self) -> int:
        """``P``, the packed vector's length."""
        return self.offsets[-1]

    @property
    def names(self) -> list[str]:
        return [s.name for s in self.streams]

    def split(self, y: torch.Tensor) -> dict[str, torch.Tensor]:
        """``y [..., P]`` -> ``{name: [..., *shape]}``."""
        lead = y.shape[:-1]
        return {
            s.name: y[..., a:b].reshape(*lead, *s.shape)
            for s, a, b in zip(self.streams, self.offsets[:-1], self.offsets[1:])
        }

    def pack(self, parts: Mapping[str, torch.Tensor], lead_dims: int = 1) -> torch.Tensor:
        """``{name: [*lead, *shape]}`` (every stream) -> ``[*lead, P]``, ``lead_dims`` leading dimensions."""
        missing = [n for n in self.names if n not in parts]
        if missing:
            raise ValueError(f"streams {missing} missing: a packed measurement holds {self.names}")
        return torch.cat([parts[s.name].flatten(lead_dims) for s in self.streams], dim=-1)

    def weights(self, scale: Mapping[str, float] | None = None) -> torch.Tensor:
        """``[P]``: each component's ``1 / noise_std^2``, times its stream's factor in ``scale`` (``{stream name:
        factor}``, default 1), scaled to average 1 over the components."""
        scale = dict(scale or {})
        self._check_names(scale, "stream_weights")
        bad = {k: v for k, v in scale.items() if not float(v) > 0}
        if bad:
            raise ValueError(f"stream_weights must be > 0, got {bad} (leave a stream out to keep its noise's weight)")
        w = torch.cat([torch.full((s.size,), float(scale.get(s.name, 1.0)) / s.noise_std**2) for s in self.streams])
        return w / w.mean()

    def _check_names(self, given: Mapping[str, Any], what: str) -> None:
        unknown = sorted(set(given) - set(self.names))
        if unknown:
            raise ValueError(f"{what} name streams {unknown}; the streams are {self.names}")

    def variances(self, given: Mapping[str, float] | None = None) -> torch.Tensor:
        """``[P]``: each component's noise variance (a filter's measurement variance), a stream's from ``given``
        (``{stream name: variance}``) where it names the stream, else its sensor's noise."""
        given = dict(given or {})
        self._check_names(given, "variances")
        return torch.cat([torch.full((s.size,), float(given.get(s.name, s.noise_std**2))) for s in self.streams])

    def state_dict(self) -> list[dict]:
        return [{"name": s.name, "shape": list(s.shape), "noise_std": s.noise_std} for s in self.streams]

    @classmethod
    def from_state_dict(cls, state: Sequence[Mapping]) -> SensorLayout:
        return cls([Stream(d["name"], tuple(int(v) for v in d["shape"]), float(d["noise_std"])) for d in state])

    def __eq__(self, other: object) -> bool:
        return isinstance(other, SensorLayout) and self.state_dict() == other.state_dict()

    def __repr__(self) -> str:
        return "SensorLayout(" + ", ".join(f"{s.name} {list(s.shape)} std {s.noise_std:g}" for s in self.streams) + ")"


class SensorHeads(nn.Module):
    """``g`` for several sensors: one head per stream, ``[N, d] -> [N, *shape]`` each, packed ``[N, P]`` in the
    order the heads are given (the data's layout: :class:`SensorLayout`; the model checks the two agree).

    Args:
        state_dim: ``d``.
        heads: ``{stream name: module}``, e.g. ``{"image": ConvDecoder(...), "angle": LinearReadout(...)}``.
    """

    def __init__(self, state_dim: int, heads: dict[str, nn.Module]):
        super().__init__()
        if not heads:
            raise ValueError("SensorHeads needs at least one head")
        self.state_dim = state_dim
        self.heads = nn.ModuleDict(heads)
        with torch.no_grad():
            probe = {name: head(torch.zeros(1, state_dim)) for name, head in self.heads.items()}
        self.shapes = {name: tuple(out.shape[1:]) for name, out in probe.items()}

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([head(x).flatten(1) for head in self.heads.values()], dim=1)

    def stream(self, name: str, x: torch.Tensor) -> torch.Tensor:
        """The head of one stream on states ``x [N, d]``: ``[N, *shape]``."""
        return self.heads[name](x)
