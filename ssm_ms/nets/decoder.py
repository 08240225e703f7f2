"""The image decoder ``g``: states ``[N, state_dim]`` -> images ``[N, C, H, W]`` by transposed convolutions."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from ssm_ms.nets import native  # the package ssm_ms.nets.native (build, ops)
from ssm_ms.nets.channels_last import conv_transpose2d, layer_norm_channels_last

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
        image_size: side of the square images to draw (``None``: what ``stem_size`` gives, e.g. the
            preset's size). The layers stay; the stem size is chosen as the smallest whose stack draws at
            least ``image_size`` (each transposed convolution maps ``s -> (s - 1) * stride + kernel``), and
            the centre ``image_size x image_size`` of that is kept (a margin narrower than the product of
            the strides; none at the sizes the stack draws exactly, e.g. the presets' 24, 48, 64). Sizes
            below what a 1x1 stem draws are refused with the sizes that work. Give ``stem_size`` or
            ``image_size``, not both.
        channels_last: on the torch-only path, run the feature maps after the first transposed convolution in
            channels-last memory layout (same results, same parameters), the layout oneDNN's CPU convolutions are
            fastest in; the transposed convolutions then run through :func:`conv_transpose2d`. LayerNorm is applied
            to the ``(H, W, C)``-ordered sample, a view, never a copy.
        native: on a CPU with AVX-512 or AVX2, in float32 (no autocast, no forward-mode AD, no tracing), run the whole
            stack after the stem (every transposed convolution, LayerNorm and ReLU) through the native kernels of
            :mod:`ssm_ms.nets.native`, one sample at a time in cache (compiled on first use; same values up to
            float rounding), where one sample's scratch fits in :data:`~ssm_ms.nets.native.NATIVE_SCRATCH` floats
            (:attr:`native_fits`: the pendulum and quadruple-pendulum decoders, not Moving MNIST's). Elsewhere, or
            where the kernels cannot be compiled, the torch-only path runs.
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
        image_size: int | None = None,
        native: bool = True,
    ):
        super().__init__()
        if image_size is not None and stem_size is not None:
            raise ValueError(
                f"ConvDecoder got stem_size={stem_size} and image_size={image_size}: give one (image_size chooses "
                "the stem size)"
            )
        if preset is not None:
            if preset not in PRESETS:
                raise ValueError(f"unknown ConvDecoder preset {preset!r}; choose one of {sorted(PRESETS)} or None")
            c0, s0, spec = PRESETS[preset]
            stem_channels = stem_channels or c0
            stem_size = stem_size or (None if image_size is not None else s0)
            layers = layers or spec
        if stem_channels is None or (stem_size is None and image_size is None) or not layers:
            raise ValueError("ConvDecoder needs a preset, or stem_channels, stem_size (or image_size) and layers")
        layers = [tuple(int(v) for v in layer) for layer in layers]
        self.crop = 0
        if image_size is not None:
            stem_size, self.crop = stem_for_image_size(int(image_size), layers, preset)
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
        self.drawn_size = s  # before the crop
        s = s if image_size is None else int(image_size)
        self.out_shape = (c, s, s)
        self.channels_last = channels_last
        self.native = native
        if channels_last:
            self.deconv.to(memory_format=torch.channels_last)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        lead = x.shape[:-1]
        h = self.stem(x.reshape(-1, self.state_dim))
        if self.native and native.applies(h) and self.native_fits:
            return self._centre(self._native_stack(h)).reshape(*lead, *self.out_shape)
        h = h.view(-1, *self.stem_shape)
        if not self.channels_last:
            return self._centre(self.deconv(h)).reshape(*lead, *self.out_shape)
        # the stem's small map stays in the Linear's NCHW order, the layout in which oneDNN convolves a 3x3 map
        # fastest (first layer forward+backward: pendulum 40 ms instead of 54, Moving MNIST 0.77 s instead of 1.1);
        # the transposed convolutions return channels-last maps
        layers = list(self.deconv)
        i = 0
        while i < len(layers):
            layer = layers[i]
            if isinstance(layer, nn.LayerNorm):
                relu = i + 1 < len(layers) and isinstance(layers[i + 1], nn.ReLU)
                h = layer_norm_channels_last(layer, h, relu=relu)
                i += relu  # the ReLU ran inside
            elif isinstance(layer, nn.ConvTranspose2d):
                h = conv_transpose2d(h, layer.weight, layer.bias, layer.stride[0])
            else:
                h = layer(h)
            i += 1
        return self._centre(h).reshape(*lead, *self.out_shape)  # a view for one uncropped channel, else a copy

    def native_scratch(self) -> int | None:
        """Floats of one sample's scratch in the native kernels (the largest products ``H_in W_in x k^2 C_out`` of a
        layer and three of the largest layer-normed maps), as the kernels count it; ``None`` without them."""
        return native.ops.scratch_floats(self._geometry())

    @property
    def native_fits(self) -> bool:
        """Whether :meth:`native_scratch` is at most :data:`~ssm_ms.nets.native.NATIVE_SCRATCH` floats: true for the pendulum and
        quadruple-pendulum decoders, not for Moving MNIST's (512 and 256 channels: oneDNN's batched convolutions are
        the faster way there)."""
        scratch = self.native_scratch()
        return scratch is not None and scratch <= native.NATIVE_SCRATCH

    def _geometry(self) -> tuple[tuple[int, int, int, int, int, int], ...]:
        """``(C_in, C_out, kernel, stride, H_in, W_in)`` of each transposed convolution."""
        geometry, size = [], self.stem_shape[1]
        for layer in self.deconv:
            if isinstance(layer, nn.ConvTranspose2d):
                c_in, c_out, k, _ = layer.weight.shape
                geometry.append((c_in, c_out, k, layer.stride[0], size, size))
                size = (size - 1) * layer.stride[0] + k
        return tuple(geometry)

    def _native_stack(self, h: torch.Tensor) -> torch.Tensor:
        """The transposed convolutions, layer norms and ReLUs after the stem through :class:`_ConvStack`, then the
        rest (the sigmoid) in torch; ``h`` is the stem's output ``[N, C S S]``."""
        c, s = self.stem_shape[0], self.stem_shape[1]
        n = h.shape[0]
        hwc = h.view(n, c, s, s).permute(0, 2, 3, 1).reshape(n, s * s * c)  # the kernels' pixel-major rows
        params: list[torch.Tensor | None] = []
        eps: list[float] = []
        layers = list(self.deconv)
        for i, layer in enumerate(layers):
            if isinstance(layer, nn.ConvTranspose2d):
                params += [layer.weight, layer.bias]
                norm = layers[i + 1] if i + 1 < len(layers) and isinstance(layers[i + 1], nn.LayerNorm) else None
                if norm is not None:
                    params += [norm.weight, norm.bias]
                eps.append(norm.eps if norm is not None else 0.0)
        geometry = self._geometry()
        out = native.conv_stack(hwc, geometry, eps, params)
        out = out.view(n, self.drawn_size, self.drawn_size, geometry[-1][1]).permute(0, 3, 1, 2)
        return self.deconv[-1](out) if isinstance(self.deconv[-1], nn.Sigmoid) else out

    def _centre(self, h: torch.Tensor) -> torch.Tensor:
        """The centre ``out_shape`` of the drawn images (a view; ``h`` itself when nothing is cropped)."""
        size = self.out_shape[-1]
        if size == self.drawn_size:
            return h
        return h[..., self.crop : self.crop + size, self.crop : self.crop + size]


def drawn_size(stem_size: int, layers: Sequence[Sequence[int]]) -> int:
    """Side of the images a transposed-convolution stack draws from a ``stem_size`` stem."""
    s = stem_size
    for _, kernel, stride in layers:
        s = (s - 1) * stride + kernel
    return s


def stem_for_image_size(image_size: int, layers: Sequence[Sequence[int]], preset: str | None = None) -> tuple[int, int]:
    """``(stem_size, crop)``: the smallest stem whose stack draws ``>= image_size``, and the margin cut per side.

    The drawn side grows by the product of the strides per stem pixel, so the margin (split between the
    sides, the odd pixel at the end) is narrower than that product.
    """
    name = f"the {preset!r} preset" if preset else "these layers"
    smallest = drawn_size(1, layers)
    step = drawn_size(2, layers) - smallest
    if image_size < smallest:
        exact = ", ".join(str(smallest + k * step) for k in range(4))
        raise ValueError(
            f"ConvDecoder: {name} cannot draw {image_size}x{image_size} images: the smallest it draws is "
            f"{smallest}x{smallest} (exactly {exact}, ...; sizes in between are cropped from the next one): "
            f"choose an image_size of at least {smallest}"
        )
    stem = 1 + -(-(image_size - smallest) // step)
    return stem, (drawn_size(stem, layers) - image_size) // 2
