"""Observation models ``g``: states ``[N, state_dim]`` -> measurements ``[N, *obs_shape]``.

Any ``nn.Module`` with that contract works as ``g``.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

# (stem channels, stem size, [(out_channels, kernel, stride), ...]) of the paper's decoders.
PRESETS: dict[str, tuple[int, int, list[tuple[int, int, int]]]] = {
    # 3 -> 11 -> 23 -> 24
    "pendulum": (32, 3, [(16, 5, 3), (12, 3, 2), (1, 2, 1)]),
    # 3 -> 11 -> 23 -> 47 -> 48
    "quad": (16, 3, [(16, 5, 3), (16, 3, 2), (12, 3, 2), (1, 2, 1)]),
    # 3 -> 7 -> 15 -> 31 -> 64
    "mnist": (512, 3, [(512, 3, 2), (256, 3, 2), (256, 3, 2), (1, 4, 2)]),
}


class ConvDecoder(nn.Module):
    """Transposed-convolution image decoder: ``Linear -> ReLU -> [ConvT, LayerNorm, ReLU]* -> ConvT -> sigmoid``.

    LayerNorm normalises over a whole feature map ``(C, H, W)``, as in the paper's code.

    Args:
        state_dim: input dimension.
        preset: one of ``"pendulum"`` (24x24), ``"quad"`` (48x48), ``"mnist"`` (64x64), or ``None``
            to give ``stem_channels``, ``stem_size`` and ``layers`` explicitly.
        stem_channels, stem_size: the Linear layer maps to ``stem_channels x stem_size x stem_size``.
        layers: ``[out_channels, kernel, stride]`` of each transposed convolution; the last one
            produces the image channels.
        output: ``"sigmoid"`` (pixels in [0, 1]) or ``"linear"``.
        channels_last: run the feature maps in channels-last memory layout (same results, same
            parameters). On CPU the transposed convolutions are much faster in it: the paper's
            pendulum training step drops from ~0.41 s to ~0.31 s (benchmarks/results/train_step.md).
            LayerNorm is then applied to the ``(H, W, C)``-ordered sample, a view, never a copy.
    """

    def __init__(
        self,
        state_dim: int,
        preset: str | None = "pendulum",
        stem_channels: int | None = None,
        stem_size: int | None = None,
        layers: Sequence[Sequence[int]] | None = None,
        output: str = "sigmoid",
        channels_last: bool = True,
    ):
        super().__init__()
        if preset is not None:
            if preset not in PRESETS:
                raise ValueError(f"unknown ConvDecoder preset {preset!r}; choose one of {sorted(PRESETS)} or None")
            c0, s0, spec = PRESETS[preset]
            stem_channels = stem_channels or c0
            stem_size = stem_size or s0
            layers = layers or spec
        if stem_channels is None or stem_size is None or not layers:
            raise ValueError("ConvDecoder needs a preset, or stem_channels, stem_size and layers")
        if output not in ("sigmoid", "linear"):
            raise ValueError(f"ConvDecoder output must be 'sigmoid' or 'linear', got {output!r}")
        self.state_dim = state_dim
        self.stem_shape = (int(stem_channels), int(stem_size), int(stem_size))
        self.stem = nn.Sequential(nn.Linear(state_dim, stem_channels * stem_size * stem_size), nn.ReLU())
        blocks: list[nn.Module] = []
        c, s = int(stem_channels), int(stem_size)
        for i, (out_c, k, stride) in enumerate(layers):
            blocks.append(nn.ConvTranspose2d(c, out_c, k, stride=stride))
            c, s = out_c, (s - 1) * stride + k
            if i < len(layers) - 1:
                blocks += [nn.LayerNorm((c, s, s)), nn.ReLU()]
        if output == "sigmoid":
            blocks.append(nn.Sigmoid())
        self.deconv = nn.Sequential(*blocks)
        self.out_shape = (c, s, s)
        self.channels_last = channels_last
        if channels_last:
            self.deconv.to(memory_format=torch.channels_last)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        lead = x.shape[:-1]
        h = self.stem(x.reshape(-1, self.state_dim)).view(-1, *self.stem_shape)
        if not self.channels_last:
            return self.deconv(h).view(*lead, *self.out_shape)
        h = h.contiguous(memory_format=torch.channels_last)
        for layer in self.deconv:
            h = layer_norm_channels_last(layer, h) if isinstance(layer, nn.LayerNorm) else layer(h)
        return h.reshape(*lead, *self.out_shape)  # a view for one output channel, else a copy


def layer_norm_channels_last(ln: nn.LayerNorm, h: torch.Tensor) -> torch.Tensor:
    """``ln`` over ``(C, H, W)`` of a channels-last ``h [N, C, H, W]``, without a layout conversion.

    The statistics of a sample do not depend on the order of its elements, so the sample is
    normalised as its ``(H, W, C)`` memory order (a view) with the affine parameters permuted alike.
    """
    n, c, height, width = h.shape
    flat = h.permute(0, 2, 3, 1).reshape(n, height * width * c)
    weight = ln.weight.permute(1, 2, 0).reshape(-1) if ln.weight is not None else None
    bias = ln.bias.permute(1, 2, 0).reshape(-1) if ln.bias is not None else None
    out = F.layer_norm(flat, (flat.shape[1],), weight, bias, ln.eps)
    return out.view(n, height, width, c).permute(0, 3, 1, 2)


class Projection(nn.Module):
    """``g(x) = x[..., indices]``: the measurement reads components of the state (e.g. Lorenz's x)."""

    def __init__(self, indices: Sequence[int]):
        super().__init__()
        if len(indices) == 0:
            raise ValueError("Projection needs at least one state index")
        if min(indices) < 0:
            raise ValueError(f"Projection indices must be >= 0, got {list(indices)}")
        self.max_index = max(indices)
        self.register_buffer("indices", torch.as_tensor(list(indices), dtype=torch.long), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.max_index >= x.shape[-1]:
            raise ValueError(
                f"Projection reads state components {self.indices.tolist()} but the state has {x.shape[-1]}"
            )
        return x.index_select(-1, self.indices)

    def observation_matrix(self, state_dim: int) -> torch.Tensor:
        """``H [p, state_dim]`` with ``g(x) = H x`` (one 1 per row): lets a Kalman update skip sigma points."""
        if self.max_index >= state_dim:
            raise ValueError(f"Projection reads state components {self.indices.tolist()} but the state has {state_dim}")
        return torch.eye(state_dim, device=self.indices.device)[self.indices]
