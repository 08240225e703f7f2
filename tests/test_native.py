"""The decoder's native kernels (ssm_ms/nets/native/: build.py, ops.py, conv_stack.c) against torch's own layers.

The tests taking ``decoder_path`` (tests/conftest.py) run twice, natively and with the kernels off, so the
torch-only float32 path that every other machine runs is held to the same float64 reference."""

import warnings

import pytest
import torch

from ssm_ms.nets import ConvDecoder, native
from ssm_ms.nets.native import NATIVE_SCRATCH, build
from ssm_ms.nets.native import applies as native_applies

# (stem channels, stem size, layers, image_size): the pendulum's shape, a stride-1 first layer, a three-channel
# image, a cropped image, 16 channels (exactly one 16-lane register), maps wider than a register (80 and 70
# channels: several vectors per pixel, products of 630 columns), the quadruple pendulum's depth (three layer norms),
# one layer and no layer norm
SPECS = [
    (8, 3, [[6, 5, 3], [5, 3, 2], [1, 2, 1]], None),
    (4, 2, [[6, 3, 1], [7, 3, 2], [1, 2, 1]], None),
    (8, 3, [[6, 3, 2], [5, 3, 2], [3, 2, 1]], None),
    (8, None, [[6, 5, 3], [12, 3, 2], [1, 2, 1]], 20),
    (8, 2, [[6, 3, 2], [16, 3, 2], [3, 2, 1]], None),
    (8, 2, [[80, 3, 2], [70, 3, 2], [1, 4, 2]], None),
    (5, 3, [[6, 5, 3], [4, 3, 2], [3, 3, 2], [1, 2, 1]], None),
    (3, 4, [[2, 3, 2]], None),
]


def _pair(state_dim, stem, size, layers, image_size, drop_bias=False, backend="native"):
    torch.manual_seed(0)
    kwargs = dict(preset=None, stem_channels=stem, stem_size=size, layers=layers, image_size=image_size)
    fused = ConvDecoder(state_dim, **kwargs, backend=backend)
    with torch.no_grad():  # non-trivial LayerNorm affine parameters: a wrong element order would show
        for p in fused.parameters():
            p.add_(0.2 * torch.randn_like(p))
    plain = ConvDecoder(state_dim, **kwargs, backend="plain").double()  # torch's own layers, NCHW, float64
    if drop_bias:  # a transposed convolution without bias (not what ConvDecoder builds, but the kernels allow it)
        for dec in (fused, plain):
            dec.deconv[0].register_parameter("bias", None)
    plain.load_state_dict(fused.state_dict())
    return fused, plain


NATIVE_NODE = "GeneratedBackwardFor_ssm_ms_conv_stack_defaultBackward"  # the kernels' node in an autograd graph


def _graph_names(t: torch.Tensor) -> list[str]:
    """The class name of every node of ``t``'s autograd graph, once per node."""
    names, seen, todo = [], set(), [t.grad_fn]
    while todo:
        fn = todo.pop()
        if fn is not None and id(fn) not in seen:
            seen.add(id(fn))
            names.append(type(fn).__name__)
            todo += [nxt for nxt, _ in fn.next_functions]
    return names


def _check_against_float64(stem, size, layers, image_size, backend: str, drop_bias=False):
    """The float32 decoder with ``backend`` (``"native"``: the kernels, ``"torch"``: the channels-last path), values
    and gradients, against torch's own NCHW layers in float64."""
    fused, plain = _pair(5, stem, size, layers, image_size, drop_bias, backend)
    x = torch.randn(9, 5, requires_grad=True)
    out = fused(x)
    assert (NATIVE_NODE in _graph_names(out)) == (backend == "native")  # the path under test ran
    x64 = x.detach().double().requires_grad_()
    want = plain(x64)
    torch.testing.assert_close(out.double(), want, rtol=1e-5, atol=1e-5)
    weight = torch.randn_like(want)
    got = torch.autograd.grad((out * weight.float()).sum(), [x, *fused.parameters()])
    ref = torch.autograd.grad((want * weight).sum(), [x64, *plain.parameters()])
    names = [n for n, _ in fused.named_parameters()]
    for name, g, r in zip(["x", *names], got, ref):
        scale = r.abs().max().clamp_min(1e-3)
        assert ((g.double() - r).abs().max() / scale).item() < 2e-5, name


@pytest.mark.parametrize("stem, size, layers, image_size", SPECS)
def test_decoder_matches_torch_layers_in_float64(decoder_path, stem, size, layers, image_size):
    _check_against_float64(stem, size, layers, image_size, decoder_path)


def test_a_transposed_convolution_without_bias_matches_too(decoder_path):
    _check_against_float64(*SPECS[0], decoder_path, drop_bias=True)


def test_only_stacks_whose_sample_fits_in_cache_run_natively(needs_native):
    # one sample's scratch: the largest products (H_in W_in k^2 C_out) plus three largest layer-normed maps, counted
    # here from the layer sizes by hand: pendulum 11x11 inputs x 3x3x12 products, maps 12x23x23
    assert ConvDecoder(4, "pendulum").native_scratch() == 11 * 11 * 9 * 12 + 3 * 12 * 23 * 23 <= NATIVE_SCRATCH
    assert ConvDecoder(4, "quad").native_scratch() == 23 * 23 * 9 * 12 + 3 * 12 * 47 * 47 <= NATIVE_SCRATCH
    assert ConvDecoder(4, "pendulum").native_fits and ConvDecoder(4, "quad").native_fits
    mnist = ConvDecoder(4, "mnist")  # auto; 15x15 inputs x 3x3x256 products, maps 256x31x31: far more than an L2 cache
    assert not mnist.native_fits and 15 * 15 * 9 * 256 > NATIVE_SCRATCH
    x = torch.randn(2, 4, requires_grad=True)
    assert NATIVE_NODE not in _graph_names(mnist(x))  # the torch-only path, batched oneDNN convolutions
    assert NATIVE_NODE in _graph_names(ConvDecoder(4, "quad", backend="native")(x))
    with pytest.raises(ValueError, match="backend 'native' cannot run here: one sample of this stack needs"):
        ConvDecoder(4, "mnist", backend="native")


def test_decoder_gives_the_same_bits_twice_and_uses_every_thread_count(decoder_path):
    fused, _ = _pair(5, *SPECS[0], backend=decoder_path)
    x = torch.randn(64, 5, requires_grad=True)
    assert (NATIVE_NODE in _graph_names(fused(x))) == (decoder_path == "native")
    threads = torch.get_num_threads()
    results = []
    try:
        for n in (threads, threads, 1):
            torch.set_num_threads(n)
            out = fused(x)
            results.append((out.detach(), *torch.autograd.grad(out.square().sum(), [x, *fused.parameters()])))
    finally:
        torch.set_num_threads(threads)
    for a, b in zip(results[0], results[1]):  # same thread count: identical, run to run
        assert torch.equal(a, b)
    for a, b in zip(results[0], results[2]):  # one thread: the same up to the order of the parameter sums
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)


def test_native_path_steps_aside_where_it_cannot_run(needs_native):
    fused, plain = _pair(5, *SPECS[0])
    x = torch.randn(4, 5)
    assert native_applies(x)
    assert not native_applies(x.double())
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert not native_applies(x)
    # forward-mode AD (analysis.jacobian's fallback) runs the torch-only path: tangents match float64 torch layers
    from torch.func import jvp

    tangent = torch.randn(4, 5)
    _, got = jvp(fused, (x,), (tangent,))
    _, want = jvp(plain, (x.double(),), (tangent.double(),))
    torch.testing.assert_close(got.double(), want, rtol=1e-4, atol=1e-5)
    # ... also with tangents on the parameters only (torch.func over functional_call)
    from torch.func import functional_call

    params = {k: v.detach() for k, v in fused.named_parameters()}
    tangents = {k: torch.randn_like(v) for k, v in params.items()}
    _, got = jvp(lambda p: functional_call(fused, p, (x,)), (params,), (tangents,))
    _, want = jvp(
        lambda p: functional_call(plain, p, (x.double(),)),
        ({k: v.double() for k, v in params.items()},),
        ({k: v.double() for k, v in tangents.items()},),
    )
    torch.testing.assert_close(got.double(), want, rtol=1e-4, atol=1e-5)
    # a trace cannot record a call through ctypes: tracing runs the torch path (here the "plain" backend's NCHW
    # layers, the ones ssm_ms.export writes), so the traced graph is whole
    fused.backend = "plain"
    traced = torch.jit.trace(fused, (x,), check_trace=False)
    other = torch.randn(6, 5)
    torch.testing.assert_close(traced(other), fused(other), rtol=1e-5, atol=1e-6)
    exported = torch.export.export(fused.eval(), (x,)).module()  # fake tensors: the torch-only path too
    torch.testing.assert_close(exported(other[:4]), fused(other[:4]), rtol=1e-5, atol=1e-6)
    fused.backend = "native"
    off = ConvDecoder(5, preset=None, stem_channels=8, stem_size=3, layers=SPECS[0][2], backend="torch")
    off.load_state_dict(fused.state_dict())
    y = off(x.requires_grad_())
    assert NATIVE_NODE not in _graph_names(y)
    torch.testing.assert_close(y, fused(x), rtol=1e-5, atol=1e-6)


@pytest.fixture
def fresh_native(monkeypatch, tmp_path):
    """the kernels with no library loaded yet and its cache in tmp_path."""
    monkeypatch.setattr(build, "_state", {})
    monkeypatch.setenv("SSM_MS_CACHE", str(tmp_path))
    return tmp_path


@pytest.mark.skipif(build._compiler() is None, reason="no C compiler here")
def test_the_avx2_build_matches_torch_too(fresh_native, monkeypatch):
    """CPUs without AVX-512 but with AVX2 and FMA (AMD Zen 2/3, desktop Intel) get a build with 8-lane vectors and
    smaller tiles: it must be as right (built here with -mavx2 -mfma, which this CPU runs)."""
    flags = ""
    with open("/proc/cpuinfo") as fh:
        flags = next((line for line in fh if line.startswith("flags")), "")
    if not {"avx2", "fma"} <= set(flags.split()):
        pytest.skip("this CPU cannot run an AVX2 build")
    monkeypatch.setattr(build, "FLAG_SETS", (["-O3", "-mavx2", "-mfma", "-fopenmp"],))
    assert native.library() is not None, native.unavailable_reason()
    for spec in (SPECS[0], SPECS[4], SPECS[5], SPECS[6]):
        _check_against_float64(*spec, "native")


def test_a_cpu_without_vector_instructions_runs_the_torch_only_path_silently(fresh_native, monkeypatch):
    """In plain C the kernels were slower than the torch-only path, so such CPUs are not offered them: nothing is
    built, nothing is lost, so nothing is said."""
    monkeypatch.setattr(build, "_has_simd", lambda: False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert native.library() is None
    assert native.unavailable_reason() == build.NO_SIMD and "AVX2" in build.NO_SIMD
    assert not list(fresh_native.glob("*.so"))
    x = torch.randn(3, 5)
    assert not native_applies(x)
    fused, plain = _pair(5, *SPECS[0], backend="auto")  # the torch path, as right
    torch.testing.assert_close(fused(x).double(), plain(x.double()), rtol=1e-5, atol=1e-5)


@pytest.mark.skipif(build._compiler() is None, reason="no C compiler here")
def test_a_build_without_vector_instructions_is_refused_by_the_source(fresh_native, monkeypatch):
    monkeypatch.setattr(build, "FLAG_SETS", (["-O2", "-fopenmp"],))  # no -march=native: SSE2 only
    with pytest.warns(RuntimeWarning, match="compiling the native kernels failed"):
        assert native.library() is None
    assert "need AVX-512, or AVX2 with FMA" in native.unavailable_reason()


def test_unavailable_native_kernels_say_why(fresh_native, monkeypatch):
    monkeypatch.setattr(build, "_compiler", lambda: None)
    with pytest.warns(RuntimeWarning, match="native kernels are off.*no C compiler") as seen:
        assert native.library() is None and "no C compiler" in native.unavailable_reason()
        native.library()  # said once, not per call
    assert len(seen) == 1
    # without the kernels backend "auto" runs the torch path; "native", asked for by name, is refused with the reason
    x = torch.randn(3, 5)
    assert not native_applies(x)
    assert ConvDecoder(5, "pendulum")(x).shape == (3, 1, 24, 24)
    with pytest.raises(ValueError, match=r"backend 'native' cannot run here: no C compiler .* use backend 'auto'"):
        ConvDecoder(5, "pendulum", backend="native")


def test_a_compiler_error_is_reported_not_raised(fresh_native, monkeypatch):
    broken = fresh_native / "broken.c"
    broken.write_text("this is not C\n")
    monkeypatch.setattr(build, "SOURCE", broken)
    with pytest.warns(RuntimeWarning, match="compiling the native kernels failed"):
        assert native.library() is None
    reason = native.unavailable_reason()
    assert reason.startswith("compiling the native kernels failed") and "error" in reason
    assert not list(fresh_native.glob("*.so"))  # nothing half-written left in the cache


@pytest.mark.skipif(build._compiler() is None, reason="no C compiler here")
def test_the_cache_is_keyed_by_the_cpu(fresh_native, monkeypatch):
    assert native.library() is not None
    first = sorted(p.name for p in fresh_native.glob("*.so"))
    assert len(first) == 1
    monkeypatch.setattr(build, "_state", {})
    assert native.library() is not None  # same CPU: the cached library, nothing rebuilt
    assert sorted(p.name for p in fresh_native.glob("*.so")) == first
    monkeypatch.setattr(build, "_state", {})
    monkeypatch.setattr(build, "_cpu_signature", lambda: "another CPU flags : avx2")
    assert native.library() is not None  # another CPU (a home directory shared between machines): its own build
    assert len(list(fresh_native.glob("*.so"))) == 2


def test_the_kernels_are_a_custom_operator_that_opcheck_accepts(needs_native):
    """Schema, fake (meta) implementation, autograd registration and AOT dispatch, checked by torch.library.opcheck
    on the pendulum's layer shapes (scaled down) and on a stack with a bias-free layer and three layer norms."""
    for stem, size, layers, _ in (SPECS[0], SPECS[6]):
        dec = ConvDecoder(5, preset=None, stem_channels=stem, stem_size=size, layers=layers, backend="native")
        geometry = [v for layer in dec.geometry for v in layer]
        params, eps, mods = [], [], list(dec.deconv)
        for i, m in enumerate(mods):
            if isinstance(m, torch.nn.ConvTranspose2d):
                params += [m.weight.detach().clone().requires_grad_(), m.bias.detach().clone().requires_grad_()]
                norm = mods[i + 1] if i + 1 < len(mods) and isinstance(mods[i + 1], torch.nn.LayerNorm) else None
                if norm is not None:
                    params += [t.detach().clone().requires_grad_() for t in (norm.weight, norm.bias)]
                eps.append(norm.eps if norm else 0.0)
        x = torch.randn(6, stem * size * size, requires_grad=True)
        torch.library.opcheck(torch.ops.ssm_ms.conv_stack.default, (x, geometry, eps, params))


def test_compile_and_export_record_the_operator(needs_native):
    """torch.compile (AOT autograd, eager kernels: no C++ code generation) and torch.export trace the native backend
    as one operator, forward and backward, and match the eager decoder."""
    fused, _ = _pair(5, *SPECS[0])
    x = torch.randn(7, 5, requires_grad=True)
    want = fused(x)
    want_grads = torch.autograd.grad(want.square().sum(), [x, *fused.parameters()])
    compiled = torch.compile(fused, backend="aot_eager", fullgraph=True)
    got = compiled(x)
    got_grads = torch.autograd.grad(got.square().sum(), [x, *fused.parameters()])
    torch.testing.assert_close(got, want)
    for g, w in zip(got_grads, want_grads):
        torch.testing.assert_close(g, w)
    program = torch.export.export(fused.eval(), (x.detach(),))
    assert "ssm_ms.conv_stack" in str(program.graph)
    other = torch.randn(7, 5)
    torch.testing.assert_close(program.module()(other), fused(other))


@pytest.mark.skipif(build._compiler() is None, reason="no C compiler here")
def test_a_library_whose_argument_struct_differs_is_refused(fresh_native, monkeypatch, needs_native):
    """The kernels take one struct, declared twice (conv_stack.c, build.ConvStackArgs): were a field added to one
    only, every call would read the wrong memory, so the sizes are compared when the library loads."""
    import ctypes

    class Longer(build.ConvStackArgs):
        _fields_ = [("extra", ctypes.c_int64)]

    monkeypatch.setattr(build, "ConvStackArgs", Longer)
    monkeypatch.setattr(build, "_state", {})  # needs_native loaded it already
    with pytest.warns(RuntimeWarning, match="compiling the native kernels failed"):
        assert native.library() is None
    assert "must list the same fields" in native.unavailable_reason()


def test_the_operators_refuse_a_parameter_list_of_the_wrong_length():
    """The parameter order lives in ops.flat_params / ops.layer_params: a stack of 3 layers takes 4 + 4 + 2 tensors;
    one missing (e.g. a layer norm's bias) is refused by name, not read past."""
    from ssm_ms.nets.native import ops

    layers = [(8, 4, 3, 2, 3, 3), (4, 4, 3, 2, 7, 7), (4, 1, 4, 2, 15, 15)]
    tensors = [torch.zeros(1) for _ in range(10)]
    groups = ops.layer_params(layers, tensors)
    assert [sum(t is not None for t in g) for g in groups] == [4, 4, 2]
    assert all(a is b for a, b in zip(ops.flat_params(groups), tensors))
    with pytest.raises(ValueError, match="9 parameters for a stack of 3 layers: expected 10"):
        ops.layer_params(layers, tensors[:9])
