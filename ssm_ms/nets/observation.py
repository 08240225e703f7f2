"""Observation models ``g``: states ``[N, state_dim]`` -> measurements ``[N, *obs_shape]``.

Any ``nn.Module`` with that contract works as ``g``.
"""

from __future__ import annotations

import ctypes
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from ssm_ms.nets import native

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
            float rounding), where one sample's scratch fits in :data:`NATIVE_SCRATCH` floats
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
        if self.native and native_applies(h) and self.native_fits:
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
        lib = native.library()
        if lib is None:
            return None
        geo = torch.tensor(self._geometry(), dtype=torch.int64)  # held: the call reads its memory
        return int(lib.conv_stack_size(geo.shape[0], geo.data_ptr(), 1))

    @property
    def native_fits(self) -> bool:
        """Whether :meth:`native_scratch` is at most :data:`NATIVE_SCRATCH` floats: true for the pendulum and
        quadruple-pendulum decoders, not for Moving MNIST's (512 and 256 channels: oneDNN's batched convolutions are
        the faster way there)."""
        scratch = self.native_scratch()
        return scratch is not None and scratch <= NATIVE_SCRATCH

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
        out = _ConvStack.apply(hwc, geometry, tuple(eps), *params)
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


def layer_norm_channels_last(ln: nn.LayerNorm, h: torch.Tensor, relu: bool = False) -> torch.Tensor:
    """``ln`` over ``(C, H, W)`` of a channels-last ``h [N, C, H, W]``, without a layout conversion.

    The statistics of a sample do not depend on the order of its elements, so the sample is
    normalised as its ``(H, W, C)`` memory order (a view) with the affine parameters permuted alike.
    ``relu=True`` applies a ReLU to the result, in place on the flat ``[N, H W C]`` layer-norm output
    (which the layer norm's backward does not need): in place on the ``[N, C, H, W]`` *view* instead,
    autograd would rebuild the view's gradient as a contiguous NCHW copy and run the ReLU's backward
    across two memory layouts (the pendulum decoder's step: 0.34 s of its 0.67 s on one core).
    """
    n, c, height, width = h.shape
    flat = h.permute(0, 2, 3, 1).reshape(n, height * width * c)
    weight = ln.weight.permute(1, 2, 0).reshape(-1) if ln.weight is not None else None
    bias = ln.bias.permute(1, 2, 0).reshape(-1) if ln.bias is not None else None
    out = F.layer_norm(flat, (flat.shape[1],), weight, bias, ln.eps)
    if relu:
        out = torch.relu_(out)
    return out.view(n, height, width, c).permute(0, 3, 1, 2)


def _phase_forward(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, stride: int) -> torch.Tensor:
    """``F.conv_transpose2d(x, weight, bias, stride)`` (no padding) as one stride-1 convolution and one copy.

    Output pixel ``s j + p`` (phase ``p < s``) sums the taps ``k = p + s t`` over the inputs ``j - t``,
    ``t < T = ceil(kernel / s)``: per phase a ``T x T`` convolution. The ``s^2`` phases are the output
    channels of one ``Conv2d(C_in, s^2 C_out, T, padding=T-1)`` (its weight gathered from ``weight``,
    taps beyond the kernel zero), then copied, interleaved and cropped to ``(H - 1) s + kernel``, into
    a channels-last result.
    """
    c_in, c_out, k, _ = weight.shape
    s, t = stride, -(-k // stride)
    w = F.pad(weight, (0, s * t - k, 0, s * t - k)).view(c_in, c_out, t, s, t, s).flip(2, 4)
    w = w.permute(3, 5, 1, 0, 2, 4).reshape(s * s * c_out, c_in, t, t)  # output channel (p_y, p_x, c_out)
    b = None if bias is None else bias.repeat(s * s)
    y = F.conv2d(x, w, b, padding=t - 1)
    n, _, rows_in, cols_in = y.shape
    phases = y.permute(0, 2, 3, 1).reshape(n, rows_in, cols_in, s, s, c_out)  # a view when channels-last
    height, width = (x.shape[2] - 1) * s + k, (x.shape[3] - 1) * s + k
    out = y.new_empty(n, height, width, c_out)
    whole, rest = divmod(width, s)
    for p in range(s):
        dst = out[:, p::s]  # the output rows of phase p
        rows = dst.shape[1]
        dst[:, :, : whole * s].view(n, rows, whole, s, c_out).copy_(phases[:, :rows, :whole, p])
        if rest:
            dst[:, :, whole * s :].copy_(phases[:, :rows, whole, p, :rest])
    return out.permute(0, 3, 1, 2)


class _ConvTranspose(torch.autograd.Function):
    """A transposed convolution whose forward is a stride-1 convolution (:func:`_phase_forward`).

    On CPU, oneDNN's transposed-convolution forward is the slow direction (several times slower than its
    adjoint, a strided convolution, for the pendulum decoder's layers: see ``ONEDNN_VERBOSE=1``). The
    backward is that of the transposed
    convolution itself: the input gradient is ``conv2d(grad, weight, stride)`` (the fast direction), the
    weight gradient that convolution's weight gradient with the roles of ``x`` and ``grad`` swapped.
    Forward-mode AD (``jvp``) is supported, so ``ssm_ms.analysis.jacobian`` works through it.
    """

    @staticmethod
    def forward(x, weight, bias, stride):
        return _phase_forward(x, weight, bias, stride)

    @staticmethod
    def setup_context(ctx, inputs, output):
        x, weight, bias, stride = inputs
        ctx.save_for_backward(x, weight)
        ctx.save_for_forward(x, weight)
        ctx.stride, ctx.has_bias = stride, bias is not None

    @staticmethod
    def backward(ctx, grad):
        x, weight = ctx.saved_tensors
        s = ctx.stride
        grad_x = grad_w = grad_b = None
        if ctx.needs_input_grad[0]:
            grad_x = F.conv2d(grad, weight, stride=s)
        if ctx.needs_input_grad[1]:
            grad_w = torch.ops.aten.convolution_backward(
                x, grad, weight, None, [s, s], [0, 0], [1, 1], False, [0, 0], 1, [False, True, False]
            )[1]
        if ctx.has_bias and ctx.needs_input_grad[2]:
            grad_b = channel_sum(grad)
        return grad_x, grad_w, grad_b, None

    @staticmethod
    def jvp(ctx, x_t, weight_t, bias_t, _):
        return _linear_jvp(_phase_forward, ctx, x_t, weight_t, bias_t)


def channel_sum(grad: torch.Tensor) -> torch.Tensor:
    """``grad.sum((0, 2, 3))`` of ``[N, C, H, W]``; for a channels-last ``grad`` as a sum over the batch of its
    ``[N, H W C]`` rows, then over pixels: contiguous column sums, ~2.5x faster on CPU than the reduction
    over the strided dimensions (the pendulum decoder's 100 MB bias gradient: 7 ms instead of 17-25 ms)."""
    n, c = grad.shape[:2]
    if grad.dim() != 4 or not grad.is_contiguous(memory_format=torch.channels_last) or c == 1:
        return grad.sum((0, 2, 3))
    return grad.permute(0, 2, 3, 1).reshape(n, -1).sum(0).view(-1, c).sum(0)


def _gemm_forward(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, stride: int) -> torch.Tensor:
    """``F.conv_transpose2d(x, weight, bias, stride)`` (no padding) as one matrix product and ``k^2`` shifted adds.

    Every input pixel ``(i, j)`` contributes ``x[:, :, i, j] @ weight[:, :, a, b]`` to output pixel
    ``(s i + a, s j + b)``: the product ``[N H W, C_in] @ [C_in, k k C_out]`` gives all of them at once, and
    each tap ``(a, b)`` is added, as a strided slice, into a channels-last result. Worth it where those
    products are no larger than the input (``k^2 C_out <= C_in``, e.g. a decoder's last, image-drawing layer).
    """
    n, c_in, h, w = x.shape
    _, c_out, k, _ = weight.shape
    s = stride
    cols = x.permute(0, 2, 3, 1).reshape(n * h * w, c_in) @ weight.permute(0, 2, 3, 1).reshape(c_in, k * k * c_out)
    cols = cols.view(n, h, w, k, k, c_out)
    out = cols.new_zeros(n, (h - 1) * s + k, (w - 1) * s + k, c_out)
    if bias is not None:
        out += bias
    for a in range(k):
        for b in range(k):
            out[:, a : a + s * (h - 1) + 1 : s, b : b + s * (w - 1) + 1 : s] += cols[:, :, :, a, b]
    return out.permute(0, 3, 1, 2)


class _ConvTransposeGemm(_ConvTranspose):
    """A transposed convolution computed by :func:`_gemm_forward`, with the matching backward: the output
    gradient's ``k^2`` tap slices gathered into contiguous planes, then two matrix products (input and weight
    gradients). On the pendulum decoder's last layer (12 -> 1 channels, kernel 2, 4000 images of 23x23):
    forward 24 ms instead of oneDNN's 45 ms, backward 29 ms instead of 32 ms, one core. What is saved for
    backward and tangents is :class:`_ConvTranspose`'s."""

    @staticmethod
    def forward(x, weight, bias, stride):
        return _gemm_forward(x, weight, bias, stride)

    @staticmethod
    def backward(ctx, grad):
        x, weight = ctx.saved_tensors
        n, c_in, h, w = x.shape
        _, c_out, k, _ = weight.shape
        s, rows = ctx.stride, n * h * w
        g = grad.permute(0, 2, 3, 1)  # [N, H, W, C_out]
        planes = grad.new_empty(k, k, n, h, w, c_out)
        for a in range(k):
            for b in range(k):
                planes[a, b] = g[:, a : a + s * (h - 1) + 1 : s, b : b + s * (w - 1) + 1 : s]
        cols = planes.view(k * k, rows, c_out).permute(1, 0, 2).reshape(rows, k * k * c_out)  # a view for C_out = 1
        w_mat = weight.permute(0, 2, 3, 1).reshape(c_in, k * k * c_out)
        grad_x = grad_w = grad_b = None
        if ctx.needs_input_grad[0]:
            grad_x = (cols @ w_mat.t()).view(n, h, w, c_in).permute(0, 3, 1, 2)
        if ctx.needs_input_grad[1]:
            x_mat = x.permute(0, 2, 3, 1).reshape(rows, c_in)
            grad_w = (cols.t() @ x_mat).t().reshape(c_in, k, k, c_out).permute(0, 3, 1, 2)
        if ctx.has_bias and ctx.needs_input_grad[2]:
            grad_b = channel_sum(grad)
        return grad_x, grad_w, grad_b, None

    @staticmethod
    def jvp(ctx, x_t, weight_t, bias_t, _):
        return _linear_jvp(_gemm_forward, ctx, x_t, weight_t, bias_t)


def _linear_jvp(forward, ctx, x_t, weight_t, bias_t):
    """Tangent of ``forward(x, weight, bias, stride)``, bilinear in ``(x, weight)`` plus ``bias``."""
    x, weight = ctx.saved_tensors
    out = None
    if x_t is not None:
        out = forward(x_t, weight, None, ctx.stride)
    if weight_t is not None:
        part = forward(x, weight_t, None, ctx.stride)
        out = part if out is None else out + part
    if bias_t is not None:
        out = out + bias_t.view(1, -1, 1, 1)
    return out


def conv_transpose2d(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, stride: int) -> torch.Tensor:
    """``F.conv_transpose2d(x, weight, bias, stride)`` (no padding, square stride), fast on CPU.

    On CPU (same values up to float rounding): a layer whose taps are no larger than its input
    (``k^2 C_out <= C_in``) goes through :class:`_ConvTransposeGemm`, other strided layers through
    :class:`_ConvTranspose`; the rest (stride 1: a plain convolution with a flipped kernel, no gain measured)
    and other devices (cuDNN's transposed convolutions are fine) use ``F.conv_transpose2d`` itself.
    """
    c_in, c_out, k, _ = weight.shape
    if x.device.type != "cpu":
        return F.conv_transpose2d(x, weight, bias, stride)
    if k * k * c_out <= c_in:
        function = _ConvTransposeGemm
    elif stride > 1:
        function = _ConvTranspose
    else:
        return F.conv_transpose2d(x, weight, bias, stride)
    if torch.is_autocast_enabled("cpu"):  # as autocast runs a convolution: in its dtype, forward and backward
        dtype = torch.get_autocast_dtype("cpu")
        with torch.autocast("cpu", enabled=False):
            return function.apply(x.to(dtype), weight.to(dtype), None if bias is None else bias.to(dtype), stride)
    return function.apply(x, weight, bias, stride)


NATIVE_SCRATCH = 1 << 18  # floats (1 MiB): what one sample of the native kernels may use, about a core's L2 cache


class _ConvStack(torch.autograd.Function):
    """A ConvDecoder's transposed convolutions, each but the last followed by ``LayerNorm((C, H, W))`` and a ReLU,
    through the native kernels of :mod:`ssm_ms.nets.native` (float32, CPU), one sample at a time in cache.

    ``x [N, S S C]`` is the stem's output as pixel-major rows; ``geometry`` holds ``(C_in, C_out, kernel, stride,
    H_in, W_in)`` per layer, ``eps`` the layer norms' epsilons (any value for the last layer), ``params`` per layer
    the ConvTranspose2d's weight and bias (or ``None``), and for all but the last the LayerNorm's weight and bias.
    Returns the last layer's output as pixel-major rows ``[N, H W C]``. The maps are pixel-major inside the kernels,
    the LayerNorm parameters permuted alike; the forward saves each layer norm's input, the backward normalises it
    again. Same values as the torch-only path up to float rounding; first-order gradients only (forward-mode AD
    takes the torch-only path: see :func:`native_applies`).
    """

    @staticmethod
    def forward(ctx, x, geometry, eps, *params):
        lib = native.library()
        packed, pointers, goff, gsize = _pack(geometry, params)
        n, last = x.shape[0], geometry[-1]
        out_size = ((last[4] - 1) * last[3] + last[2]) * ((last[5] - 1) * last[3] + last[2]) * last[1]
        x = x.contiguous()
        geo = torch.tensor(geometry, dtype=torch.int64)
        out = x.new_empty(n, out_size)
        saved = x.new_empty(n, lib.conv_stack_size(len(geometry), geo.data_ptr(), 0))
        stats = x.new_empty(n, 2 * (len(geometry) - 1))
        eps_arr = (ctypes.c_float * len(geometry))(*eps)
        native.check(lib.conv_stack_forward(len(geometry), geo.data_ptr(), pointers, eps_arr, x.data_ptr(),
                                            out.data_ptr(), saved.data_ptr(), stats.data_ptr(), n))
        ctx.save_for_backward(x, saved, stats, *packed)
        ctx.geometry, ctx.eps, ctx.goff, ctx.gsize = geometry, eps, goff, gsize
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        x, saved, stats, *packed = ctx.saved_tensors
        lib = native.library()
        geometry = ctx.geometry
        n = x.shape[0]
        pointers = _pointers(packed)
        count = max(1, min(native.threads(), n))
        grads = x.new_zeros(count, ctx.gsize)
        dx = x.new_empty(x.shape)
        geo = torch.tensor(geometry, dtype=torch.int64)
        goff = torch.tensor(ctx.goff, dtype=torch.int64)
        eps_arr = (ctypes.c_float * len(geometry))(*ctx.eps)
        grad = grad.contiguous()
        native.check(lib.conv_stack_backward(len(geometry), geo.data_ptr(), pointers, eps_arr, x.data_ptr(),
                                             saved.data_ptr(), stats.data_ptr(), grad.data_ptr(), dx.data_ptr(),
                                             grads.data_ptr(), goff.data_ptr(), ctx.gsize, n, count))
        total = grads.sum(0)
        out: list[torch.Tensor | None] = []
        for layer, (c_in, c_out, k, s, h, w) in enumerate(geometry):
            o_w, o_b, o_g, o_be = ctx.goff[4 * layer : 4 * layer + 4]
            out.append(total[o_w : o_w + c_in * k * k * c_out].view(k, k, c_out, c_in).permute(3, 2, 0, 1))
            out.append(total[o_b : o_b + c_out] if o_b >= 0 else None)
            if layer < len(geometry) - 1:
                hw = ((h - 1) * s + k, (w - 1) * s + k)
                size = hw[0] * hw[1] * c_out
                out.append(total[o_g : o_g + size].view(*hw, c_out).permute(2, 0, 1))
                out.append(total[o_be : o_be + size].view(*hw, c_out).permute(2, 0, 1))
        return (dx, None, None, *out)


def _pack(geometry, params):
    """The kernels' copies of the parameters, per layer ``w [C_in, k k C_out]`` ((c; a, b, c2) order), its transpose,
    the bias, and the LayerNorm's weight and bias in ``H W C`` order; their addresses; each layer's gradient offsets
    ``(w, bias, gamma, beta)`` in a row of the kernels' gradient buffer (-1: none), and that row's length."""
    packed: list[torch.Tensor | None] = []
    goff: list[int] = []
    size, i = 0, 0
    for layer, (c_in, c_out, k, _, _, _) in enumerate(geometry):
        weight, bias = params[i], params[i + 1]
        w = weight.detach().permute(0, 2, 3, 1).reshape(c_in, k * k * c_out).contiguous()
        packed += [w, w.t().contiguous(), None if bias is None else bias.detach().contiguous()]
        goff += [size, -1 if bias is None else size + w.numel()]
        size += w.numel() + (0 if bias is None else c_out)
        i += 2
        if layer < len(geometry) - 1:
            gamma, beta = params[i], params[i + 1]
            packed += [gamma.detach().permute(1, 2, 0).contiguous(), beta.detach().permute(1, 2, 0).contiguous()]
            goff += [size, size + gamma.numel()]
            size += 2 * gamma.numel()
            i += 2
        else:
            packed += [None, None]
            goff += [-1, -1]
    return packed, _pointers(packed), goff, size


def _pointers(packed):
    """The ``void *[5 L]`` array of the packed parameters' addresses (NULL for ``None``)."""
    return (ctypes.c_void_p * len(packed))(*[None if t is None else t.data_ptr() for t in packed])


def native_applies(h: torch.Tensor) -> bool:
    """Whether the native kernels can run on ``h`` (the stem's output): a plain float32 tensor on CPU, outside
    autocast, forward-mode AD (``torch.func`` transforms or dual tensors) and tracing (``torch.compile``,
    ``torch.export``, ``torch.jit.trace``: a graph cannot record a call through ctypes), with the kernels compiled."""
    if h.device.type != "cpu" or h.dtype != torch.float32 or torch.is_autocast_enabled("cpu"):
        return False
    if type(h) is not torch.Tensor or torch.compiler.is_compiling() or torch.jit.is_tracing():
        return False
    if torch._C._functorch.is_functorch_wrapped_tensor(h):
        return False
    if torch.autograd.forward_ad._current_level >= 0 and torch.autograd.forward_ad.unpack_dual(h).tangent is not None:
        return False
    return native.library() is not None


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


class LinearReadout(nn.Linear):
    """``g(x) = W x + b`` for vector measurements, its size taken from the data unless given.

    With ``out_features=None`` the layer has no parameters until the model hands it the data's
    measurement shape (:meth:`adopt_measurement_shape`, called by ``MultipleShootingModule.setup``
    before the optimizer exists); the model then records the size in its hyperparameters, so the run's
    ``hparams.yaml`` and checkpoints name it and reload without the data. It is an ``nn.Linear``: the
    Kalman filters use its matrix for an exact update.

    Args:
        state_dim: input dimension.
        out_features: number of measured channels; ``None``: the data's.
        bias: learn ``b``.
    """

    def __init__(self, state_dim: int, out_features: int | None = None, bias: bool = True):
        if out_features is not None and out_features < 1:
            raise ValueError(f"LinearReadout out_features must be >= 1 (or null: the data's), got {out_features}")
        super().__init__(state_dim, out_features or 1, bias)
        self.sized = out_features is not None
        if not self.sized:  # no parameters to train or save until the data say how many channels
            self.out_features = 0
            self.weight = nn.Parameter(self.weight.new_empty(0, state_dim))
            if bias:
                self.bias = nn.Parameter(self.bias.new_empty(0))

    def adopt_measurement_shape(self, obs_shape: Sequence[int]) -> dict[str, int]:
        """Size the layer for measurements of ``obs_shape`` if it was left unsized; returns the init
        arguments it fixed (``{}`` if none)."""
        obs_shape = tuple(int(s) for s in obs_shape)
        if len(obs_shape) != 1:
            raise ValueError(
                f"LinearReadout draws vectors, but the measurements have shape {list(obs_shape)}: use a ConvDecoder "
                "for images"
            )
        if self.sized:
            return {}
        self.out_features, self.sized = obs_shape[0], True
        self.weight = nn.Parameter(self.weight.new_empty(self.out_features, self.in_features))
        if self.bias is not None:
            self.bias = nn.Parameter(self.bias.new_empty(self.out_features))
        self.reset_parameters()
        return {"out_features": self.out_features}

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.sized:
            raise ValueError(
                "LinearReadout has out_features null (the data's) but has not seen the data yet: train it with a "
                "DataModule, or give out_features"
            )
        return super().forward(x)
