"""The image decoder ``g``: states ``[N, state_dim]`` -> images ``[N, C, H, W]`` by transposed convolutions."""

from __future__ import annotations

import functools
import logging
from collections.abc import Sequence

import torch
from torch import nn

from ssm_ms.nets import native as kernels  # the package ssm_ms.nets.native (build, ops)
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
        backend: how the layers after the stem run; one switch, same parameters and same values up to float rounding:

            * ``"auto"`` (default): the native kernels on a CPU with AVX-512 or with full-width AVX2, the ``"torch"``
              path everywhere else (an AMD Zen 1 or Zen+, whose AVX2 runs as two 128-bit halves; a CPU with neither;
              CUDA or any other device). Decided from the device and the CPU's vector unit alone (:func:`auto_path`,
              a pure function of the two; the vector unit is :func:`ssm_ms.nets.native.build.cpu_simd`, /proc/cpuinfo
              read once per process, and not read at all for a tensor on another device): nothing is timed and
              nothing is written. Where the native path cannot run it is the ``"torch"`` path anyway, as for
              ``"native"`` (below), and also where the kernels are not built, where one sample does not fit them
              (:attr:`native_fits`: Moving MNIST's decoder), and under ``torch.compile`` and ``torch.export``
              tracing. The rule follows the measured ratio of the two paths (decoder forward + backward, per
              machine: ``benchmarks/results/decoder_profile.md``, written by ``make bench``): the kernels win on
              AVX-512 and full-width AVX2 and lose on Zen 1's split AVX2. Give ``"torch"`` where
              ``python benchmarks/profile_decoder.py`` says it is faster.
            * ``"native"``: the native kernels of :mod:`ssm_ms.nets.native` wherever they can run (AVX2 CPUs included):
              the whole stack after the stem (every transposed convolution, LayerNorm and ReLU) one sample at a time
              in cache, float32 on a CPU with AVX-512 or AVX2 + FMA, where one sample's scratch fits in
              :data:`~ssm_ms.nets.native.NATIVE_SCRATCH` floats (:attr:`native_fits`: the pendulum and
              quadruple-pendulum decoders, not Moving MNIST's). Refused at construction where the kernels cannot be
              built or the stack does not fit. They run as the custom operator ``torch.ops.ssm_ms.conv_stack``, which
              ``torch.compile``, ``torch.export`` and ``torch.jit.trace`` record as one operator. Inputs they cannot
              take (float64, autocast, ``torch.func`` transforms and forward-mode AD, other devices) run the
              ``"torch"`` path. (``"auto"`` under ``torch.compile`` and ``torch.export`` traces the ``"torch"`` path.)
            * ``"torch"``: torch operations on channels-last feature maps (:mod:`ssm_ms.nets.channels_last`), the
              layout oneDNN's CPU convolutions are fastest in.
            * ``"plain"``: torch's own ``nn`` layers on NCHW maps, as built: the reference the tests compare with,
              and what :mod:`ssm_ms.export` exports.
    """

    def __init__(
        self,
        state_dim: int,
        preset: str | None = "pendulum",
        stem_channels: int | None = None,
        stem_size: int | None = None,
        layers: Sequence[Sequence[int]] | None = None,
        output: str = "sigmoid",
        image_size: int | None = None,
        backend: str = "auto",
    ):
        super().__init__()
        if backend not in BACKENDS:
            raise ValueError(f"ConvDecoder backend must be one of {list(BACKENDS)}, got {backend!r}")
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
        if backend != "plain":
            self.deconv.to(memory_format=torch.channels_last)
        self.backend = backend
        if backend == "native":
            reason = kernels.unavailable_reason() or (
                None
                if self.native_fits
                else (
                    f"one sample of this stack needs {self.native_scratch()} floats of scratch, more than the kernels' "
                    f"{kernels.NATIVE_SCRATCH} (NATIVE_SCRATCH)"
                )
            )
            if reason is not None:
                raise ValueError(
                    f"ConvDecoder backend 'native' cannot run here: {reason}; use backend 'auto' (the "
                    "default: the kernels where they run and are the faster) or 'torch'"
                )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        lead = x.shape[:-1]
        h = self.stem(x.reshape(-1, self.state_dim))
        if self._runs_native(h):
            return self._centre(self._native_stack(h)).reshape(*lead, *self.out_shape)
        return self._centre(self._torch_stack(h)).reshape(*lead, *self.out_shape)

    def _runs_native(self, h: torch.Tensor) -> bool:
        """Whether this forward takes the native kernels (``h``: the stem's output); see ``backend``."""
        if self.backend == "native":  # built and fitting: checked at construction
            return kernels.applies(h)
        if self.backend != "auto" or torch.compiler.is_compiling():  # compile / export: the torch path
            return False
        device = h.device.type
        simd = kernels.build.cpu_simd() if device == "cpu" else None  # no CPU probe for another device's tensors
        if device == "cpu":
            _say_choice(simd)
        return auto_path(device, simd) == "native" and kernels.applies(h) and self.native_fits

    def _torch_stack(self, h: torch.Tensor) -> torch.Tensor:
        """The layers after the stem in torch: the ``"plain"`` backend's ``nn`` layers, or the channels-last path."""
        h = h.view(-1, *self.stem_shape)
        if self.backend == "plain":
            return self.deconv(h)
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
        return h

    def native_scratch(self) -> int | None:
        """Floats of one sample's scratch in the native kernels (the largest products ``H_in W_in x k^2 C_out`` of a
        layer and three of the largest layer-normed maps), as the kernels count it; ``None`` without them."""
        return kernels.ops.scratch_floats(self.geometry)

    @functools.cached_property
    def native_fits(self) -> bool:
        """Whether :meth:`native_scratch` is at most :data:`~ssm_ms.nets.native.NATIVE_SCRATCH` floats: true for the
        pendulum and quadruple-pendulum decoders, not for Moving MNIST's (512 and 256 channels: oneDNN's batched
        convolutions are the faster way there). Asked once per decoder (the layers do not change)."""
        scratch = self.native_scratch()
        return scratch is not None and scratch <= kernels.NATIVE_SCRATCH

    @functools.cached_property
    def geometry(self) -> tuple[tuple[int, int, int, int, int, int], ...]:
        """``(C_in, C_out, kernel, stride, H_in, W_in)`` of each transposed convolution (read on every forward:
        computed once, the layers' sizes do not change)."""
        geometry, size = [], self.stem_shape[1]
        for layer in self.deconv:
            if isinstance(layer, nn.ConvTranspose2d):
                c_in, c_out, k, _ = layer.weight.shape
                geometry.append((c_in, c_out, k, layer.stride[0], size, size))
                size = (size - 1) * layer.stride[0] + k
        return tuple(geometry)

    def _native_stack(self, h: torch.Tensor) -> torch.Tensor:
        """The transposed convolutions, layer norms and ReLUs after the stem through the native kernels, then the
        rest (the sigmoid) in torch; ``h`` is the stem's output ``[N, C S S]``."""
        c, s = self.stem_shape[0], self.stem_shape[1]
        n = h.shape[0]
        hwc = h.view(n, c, s, s).permute(0, 2, 3, 1).reshape(n, s * s * c)  # the kernels' pixel-major rows
        per_layer: list[tuple] = []
        eps: list[float] = []
        layers = list(self.deconv)
        for i, layer in enumerate(layers):
            if isinstance(layer, nn.ConvTranspose2d):  # no bias: a zero one (the operator takes every tensor)
                bias = layer.bias if layer.bias is not None else layer.weight.new_zeros(layer.out_channels)
                norm = layers[i + 1] if i + 1 < len(layers) and isinstance(layers[i + 1], nn.LayerNorm) else None
                per_layer.append(
                    (layer.weight, bias, *((norm.weight, norm.bias) if norm is not None else (None, None)))
                )
                eps.append(norm.eps if norm is not None else 0.0)
        params = kernels.ops.flat_params(per_layer)
        geometry = self.geometry
        out = kernels.conv_stack(hwc, geometry, eps, params)
        out = out.view(n, self.drawn_size, self.drawn_size, geometry[-1][1]).permute(0, 3, 1, 2)
        return self.deconv[-1](out) if isinstance(self.deconv[-1], nn.Sigmoid) else out

    def _centre(self, h: torch.Tensor) -> torch.Tensor:
        """The centre ``out_shape`` of the drawn images (a view; ``h`` itself when nothing is cropped)."""
        size = self.out_shape[-1]
        if size == self.drawn_size:
            return h
        return h[..., self.crop : self.crop + size, self.crop : self.crop + size]


BACKENDS = ("auto", "native", "torch", "plain")
_log = logging.getLogger("ssm_ms")


def auto_path(device_type: str, simd: str | None) -> str:
    """The path backend ``"auto"`` takes, ``"native"`` or ``"torch"``, for a tensor on a ``device_type`` device
    (``"cpu"``, ``"cuda"``, ...) on a CPU with the vector unit ``simd`` (what
    :func:`ssm_ms.nets.native.build.cpu_simd` says: ``"avx512"``, ``"avx2"``, ``"avx2-128"`` or ``None``): the native
    kernels on a CPU with AVX-512 or full-width AVX2, the torch path otherwise. Why, with the measurements:
    :class:`ConvDecoder`'s ``backend``. (``"native"`` here is a preference: the decoder still takes the torch path
    where the kernels cannot run.)"""
    return "native" if device_type == "cpu" and simd in ("avx512", "avx2") else "torch"


SIMD_NAMES = {
    "avx512": "AVX-512",
    "avx2": "AVX2 with FMA, no AVX-512",
    "avx2-128": "AVX2 run as two 128-bit halves (AMD Zen 1 or Zen+), no AVX-512",
    None: "neither AVX-512 nor AVX2 with FMA",
}


@functools.cache
def _say_choice(simd: str | None) -> None:
    """Log once per process what backend ``"auto"`` runs on this CPU (logger ``ssm_ms``, shown by ``cli.py``)."""
    path = "the native kernels" if auto_path("cpu", simd) == "native" else "the torch path"
    _log.info("ConvDecoder backend 'auto': %s on this CPU (%s)", path, SIMD_NAMES[simd])


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
