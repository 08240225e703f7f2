"""The native kernels as a torch autograd function: the ConvDecoder's stack of transposed convolutions, layer norms
and ReLUs after its stem, float32 on CPU, one sample at a time in cache (the C source: ``conv_stack.c``)."""

from __future__ import annotations

import ctypes

import torch

from ssm_ms.nets.native.build import check, library, threads

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
        lib = library()
        packed, pointers, goff, gsize = _pack(geometry, params)
        n, last = x.shape[0], geometry[-1]
        out_size = ((last[4] - 1) * last[3] + last[2]) * ((last[5] - 1) * last[3] + last[2]) * last[1]
        x = x.contiguous()
        geo = torch.tensor(geometry, dtype=torch.int64)
        out = x.new_empty(n, out_size)
        saved = x.new_empty(n, lib.conv_stack_size(len(geometry), geo.data_ptr(), 0))
        stats = x.new_empty(n, 2 * (len(geometry) - 1))
        eps_arr = (ctypes.c_float * len(geometry))(*eps)
        check(lib.conv_stack_forward(len(geometry), geo.data_ptr(), pointers, eps_arr, x.data_ptr(),
                                            out.data_ptr(), saved.data_ptr(), stats.data_ptr(), n))
        ctx.save_for_backward(x, saved, stats, *packed)
        ctx.geometry, ctx.eps, ctx.goff, ctx.gsize = geometry, eps, goff, gsize
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        x, saved, stats, *packed = ctx.saved_tensors
        lib = library()
        geometry = ctx.geometry
        n = x.shape[0]
        pointers = _pointers(packed)
        count = max(1, min(threads(), n))
        grads = x.new_zeros(count, ctx.gsize)
        dx = x.new_empty(x.shape)
        geo = torch.tensor(geometry, dtype=torch.int64)
        goff = torch.tensor(ctx.goff, dtype=torch.int64)
        eps_arr = (ctypes.c_float * len(geometry))(*ctx.eps)
        grad = grad.contiguous()
        check(lib.conv_stack_backward(len(geometry), geo.data_ptr(), pointers, eps_arr, x.data_ptr(),
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


def applies(h: torch.Tensor) -> bool:
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
    return library() is not None


def conv_stack(x: torch.Tensor, geometry, eps, params) -> torch.Tensor:
    """:class:`_ConvStack` on the stem's output ``x [N, S S C]`` (pixel-major rows): the last layer's output rows."""
    return _ConvStack.apply(x, tuple(geometry), tuple(eps), *params)


def scratch_floats(geometry) -> int | None:
    """Floats of one sample's scratch in the kernels for a stack of ``geometry`` (``(C_in, C_out, kernel, stride,
    H_in, W_in)`` per layer), as the kernels count it; ``None`` without the kernels."""
    lib = library()
    if lib is None:
        return None
    geo = torch.tensor(tuple(geometry), dtype=torch.int64)  # held: the call reads its memory
    return int(lib.conv_stack_size(geo.shape[0], geo.data_ptr(), 1))
