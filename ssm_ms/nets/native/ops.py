"""The native kernels as PyTorch custom operators (``torch.ops.ssm_ms.conv_stack`` and its backward): the
ConvDecoder's stack of transposed convolutions, layer norms and ReLUs after its stem, float32 on CPU, one sample at a
time in cache (the C source: ``conv_stack.c``)."""

from __future__ import annotations

import ctypes
from collections.abc import Sequence

import torch

from ssm_ms.nets.native.build import ConvStackArgs, check, library, threads
from ssm_ms.runtime.private import has_forward_tangent, in_functorch_transform

NATIVE_SCRATCH = 1 << 18  # floats (1 MiB): what one sample of the native kernels may use, about a core's L2 cache


# The kernels as two PyTorch custom operators, so that torch.compile, torch.export and torch.jit.trace see an
# operator with a schema, a fake (meta) implementation and an autograd formula, not a Python function calling
# ctypes. ``geometry`` is flat: ``(C_in, C_out, kernel, stride, H_in, W_in)`` per layer, 6 integers each.


def _layers(geometry: Sequence[int]) -> list[tuple[int, ...]]:
    return [tuple(geometry[i : i + 6]) for i in range(0, len(geometry), 6)]


# The operators' parameter order, in one place: per layer the ConvTranspose2d's weight and bias, then, for all but
# the last layer, the LayerNorm's weight and bias. The decoder flattens its modules' tensors with
# :func:`flat_params`; the operators read them back, and return their gradients, with :func:`layer_params`.


def flat_params(per_layer: Sequence[Sequence[torch.Tensor | None]]) -> list[torch.Tensor]:
    """``[(weight, bias, norm_weight, norm_bias), ...]`` (the last layer's norm tensors ``None``) as the operators'
    flat parameter list."""
    last = len(per_layer) - 1
    return [t for i, group in enumerate(per_layer) for t in (group[:2] if i == last else group)]


def layer_params(layers, params: Sequence) -> list[tuple]:
    """The inverse of :func:`flat_params` for a stack of ``layers``: per layer ``(weight, bias, norm_weight,
    norm_bias)``, the last layer's norm entries ``None``."""
    expected = 4 * len(layers) - 2
    if len(params) != expected:
        raise ValueError(f"{len(params)} parameters for a stack of {len(layers)} layers: expected {expected}")
    groups = [tuple(params[i : i + 4]) for i in range(0, expected - 2, 4)]
    return [*groups, (params[-2], params[-1], None, None)]


def _out_size(layers) -> int:
    c_in, c_out, k, s, h, w = layers[-1]
    return ((h - 1) * s + k) * ((w - 1) * s + k) * c_out


def _geo(layers) -> ctypes.Array:
    """The layers' sizes as the kernels read them: ``int64 [L][6]`` (a ctypes array, not a tensor: under fake tensors,
    as in torch.compile's tracing, a tensor has no memory to read)."""
    return (ctypes.c_int64 * (6 * len(layers)))(*[v for layer in layers for v in layer])


def _saved_size(layers) -> int:
    """Floats the forward saves per sample for the backward (each layer norm's input), as the kernels count it."""
    return int(library().conv_stack_size(len(layers), _geo(layers), 0))


def _call(fn, layers, pointers, eps, x, saved, stats, **fields) -> None:
    """One kernel call: a :class:`ConvStackArgs` of the fields both directions share and ``fields`` (the rest, as
    addresses or integers); the ctypes arrays it points to live until the call returns."""
    geo, eps_arr = _geo(layers), (ctypes.c_float * len(layers))(*eps)
    args = ConvStackArgs(
        layers=len(layers),
        geo=ctypes.addressof(geo),
        params=ctypes.addressof(pointers),
        eps=ctypes.addressof(eps_arr),
        rows=x.shape[0],
        x=x.data_ptr(),
        saved=saved.data_ptr(),
        stats=stats.data_ptr(),
        **fields,
    )
    check(fn(ctypes.byref(args)))


def _fresh(t: torch.Tensor) -> torch.Tensor:
    """A contiguous copy: an operator's outputs may not be views of one another."""
    return t.clone(memory_format=torch.contiguous_format)


@torch.library.custom_op("ssm_ms::conv_stack", mutates_args=(), device_types="cpu")
def conv_stack_op(
    x: torch.Tensor, geometry: list[int], eps: list[float], params: list[torch.Tensor]
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A ConvDecoder's transposed convolutions, each but the last followed by ``LayerNorm((C, H, W))`` and a ReLU,
    one sample at a time in cache (float32, CPU).

    ``x [N, S S C]`` is the stem's output as pixel-major rows; ``geometry`` the layers' sizes (flat, 6 per layer);
    ``eps`` the layer norms' epsilons (any value for the last layer); ``params`` per layer the ConvTranspose2d's
    weight and bias and, for all but the last, the LayerNorm's weight and bias, as the modules hold them. Returns
    the last layer's output as pixel-major rows ``[N, H W C]``, and what the backward reads: each layer norm's input
    ``[N, saved]`` and its statistics ``[N, 2 (L - 1)]``."""
    layers = _layers(geometry)
    lib = library()
    packed, pointers, _, _ = _pack(layers, params)
    n = x.shape[0]
    x = x.contiguous()
    out = x.new_empty(n, _out_size(layers))
    saved = x.new_empty(n, _saved_size(layers))
    stats = x.new_empty(n, 2 * (len(layers) - 1))
    _call(lib.conv_stack_forward, layers, pointers, eps, x, saved, stats, out=out.data_ptr())
    del packed  # held until the call returned: the kernels read the copies through ``pointers``
    return out, saved, stats


@conv_stack_op.register_fake
def _(x, geometry, eps, params):
    layers = _layers(geometry)
    n = x.shape[0]
    return x.new_empty(n, _out_size(layers)), x.new_empty(n, _saved_size(layers)), x.new_empty(n, 2 * (len(layers) - 1))


@torch.library.custom_op("ssm_ms::conv_stack_backward", mutates_args=(), device_types="cpu")
def conv_stack_backward_op(
    x: torch.Tensor,
    saved: torch.Tensor,
    stats: torch.Tensor,
    grad: torch.Tensor,
    geometry: list[int],
    eps: list[float],
    params: list[torch.Tensor],
) -> list[torch.Tensor]:
    """Gradients of :func:`conv_stack_op`'s first output: ``[dx, d(each param)...]``, shaped as ``x`` and the
    parameters. Per-thread partial parameter gradients, summed in order: the same bits run to run for
    a given thread count."""
    layers = _layers(geometry)
    lib = library()
    packed, pointers, goff, gsize = _pack(layers, params)
    n = x.shape[0]
    count = max(1, min(threads(), n))
    grads = x.new_zeros(count, gsize)
    dx = x.new_empty(x.shape)
    goff_arr = (ctypes.c_int64 * (4 * len(goff)))(*[o for offsets in goff for o in offsets])
    x, grad = x.contiguous(), grad.contiguous()  # held: the kernels read their memory
    _call(
        lib.conv_stack_backward,
        layers,
        pointers,
        eps,
        x,
        saved,
        stats,
        dout=grad.data_ptr(),
        dx=dx.data_ptr(),
        grads=grads.data_ptr(),
        goff=ctypes.addressof(goff_arr),
        gsize=gsize,
        threads=count,
    )
    del packed
    total = grads.sum(0)
    per_layer = []
    for (c_in, c_out, k, s, h, w), offsets in zip(layers, goff):
        o_w, o_b, o_g, o_be = offsets
        d_w = _fresh(total[o_w : o_w + c_in * k * k * c_out].view(k, k, c_out, c_in).permute(3, 2, 0, 1))
        d_b = _fresh(total[o_b : o_b + c_out])
        d_g = d_be = None
        if o_g >= 0:
            hw = ((h - 1) * s + k, (w - 1) * s + k)
            size = hw[0] * hw[1] * c_out
            d_g = _fresh(total[o_g : o_g + size].view(*hw, c_out).permute(2, 0, 1))
            d_be = _fresh(total[o_be : o_be + size].view(*hw, c_out).permute(2, 0, 1))
        per_layer.append((d_w, d_b, d_g, d_be))
    return [dx, *flat_params(per_layer)]


@conv_stack_backward_op.register_fake
def _(x, saved, stats, grad, geometry, eps, params):
    return [torch.empty_like(x)] + [torch.empty_like(p, memory_format=torch.contiguous_format) for p in params]


def _setup_context(ctx, inputs, output):
    x, geometry, eps, params = inputs
    _, saved, stats = output
    ctx.save_for_backward(x, saved, stats, *params)
    ctx.geometry, ctx.eps = geometry, eps
    ctx.mark_non_differentiable(saved, stats)
    ctx.set_materialize_grads(False)  # no zero gradients for saved and stats (the pendulum's saved: 132 MB a step)


def _backward(ctx, grad, _grad_saved, _grad_stats):
    x, saved, stats, *params = ctx.saved_tensors
    dx, *dparams = conv_stack_backward_op(x, saved, stats, grad, ctx.geometry, ctx.eps, params)
    return dx, None, None, dparams


conv_stack_op.register_autograd(_backward, setup_context=_setup_context)


def _pack(geometry, params):
    """The kernels' copies of the parameters, per layer ``w [C_in, k k C_out]`` ((c; a, b, c2) order), its transpose,
    the bias, and the LayerNorm's weight and bias in ``H W C`` order; their addresses; each layer's gradient offsets
    ``(w, bias, gamma, beta)`` in a row of the kernels' gradient buffer (-1: none), and that row's length."""
    packed: list[torch.Tensor | None] = []
    goff: list[tuple[int, int, int, int]] = []
    size = 0
    for (c_in, c_out, k, _, _, _), (weight, bias, gamma, beta) in zip(geometry, layer_params(geometry, params)):
        w = weight.detach().permute(0, 2, 3, 1).reshape(c_in, k * k * c_out).contiguous()
        packed += [w, w.t().contiguous(), bias.detach().contiguous()]
        o_w, o_b = size, size + w.numel()
        size += w.numel() + c_out
        if gamma is not None:
            packed += [gamma.detach().permute(1, 2, 0).contiguous(), beta.detach().permute(1, 2, 0).contiguous()]
            goff.append((o_w, o_b, size, size + gamma.numel()))
            size += 2 * gamma.numel()
        else:
            packed += [None, None]
            goff.append((o_w, o_b, -1, -1))
    return packed, _pointers(packed), goff, size


def _pointers(packed):
    """The ``void *[5 L]`` array of the packed parameters' addresses (NULL for ``None``)."""
    return (ctypes.c_void_p * len(packed))(*[None if t is None else t.data_ptr() for t in packed])


def applies(h: torch.Tensor) -> bool:
    """Whether the native kernels can run on ``h`` (the stem's output): a float32 tensor on CPU (the fake tensors
    torch.compile and torch.export trace with included: they record the operator), outside autocast and
    outside ``torch.func`` transforms and forward-mode AD (the operators have a backward, no forward-mode formula and
    no batching rule), with the kernels compiled."""
    if h.device.type != "cpu" or h.dtype != torch.float32 or torch.is_autocast_enabled("cpu"):
        return False
    if torch.compiler.is_compiling():  # torch.compile's tracing (fake tensors): it records the operator
        return True
    if in_functorch_transform(h) or has_forward_tangent(h):
        return False
    return library() is not None


def conv_stack(x: torch.Tensor, geometry, eps, params) -> torch.Tensor:
    """``torch.ops.ssm_ms.conv_stack`` on the stem's output ``x [N, S S C]`` (pixel-major rows), ``geometry`` one
    ``(C_in, C_out, kernel, stride, H_in, W_in)`` per layer: the last layer's output rows."""
    flat = [int(v) for layer in geometry for v in layer]
    return torch.ops.ssm_ms.conv_stack(x, flat, [float(e) for e in eps], list(params))[0]


def scratch_floats(geometry) -> int | None:
    """Floats of one sample's scratch in the kernels for a stack of ``geometry`` (``(C_in, C_out, kernel, stride,
    H_in, W_in)`` per layer), as the kernels count it; ``None`` without the kernels."""
    lib = library()
    if lib is None:
        return None
    layers = [tuple(layer) for layer in geometry]
    return int(lib.conv_stack_size(len(layers), _geo(layers), 1))
