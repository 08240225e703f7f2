"""The ConvDecoder's torch-only CPU path: transposed convolutions and layer norms on channels-last feature maps.

Same values as torch's own NCHW layers up to float rounding, faster on CPU (oneDNN convolves channels-last maps
fastest, and its transposed-convolution forward is the slow direction: see :class:`_ConvTranspose`). Every function
has a backward and a forward-mode tangent, so ``torch.func`` transforms work through them.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


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
