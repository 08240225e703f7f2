"""The ConvDecoder's one switch, ``backend``: names checked, ``"auto"`` deciding its path from the device and the
CPU's instruction set alone (no timing, nothing written: a frozen decoder on a fresh home directory runs), and the
same values from every path."""

from __future__ import annotations

import pytest
import torch

from ssm_ms.nets import ConvDecoder, decoder, native
from ssm_ms.nets.native import build
from tests.test_native import NATIVE_NODE, _graph_names

SPEC = dict(preset=None, stem_channels=8, stem_size=3, layers=[[6, 5, 3], [5, 3, 2], [1, 2, 1]])


def ran_native(g: ConvDecoder, x: torch.Tensor) -> bool:
    return NATIVE_NODE in _graph_names(g(x.requires_grad_()))


def test_backend_names_are_checked():
    with pytest.raises(ValueError, match=r"backend must be one of \['auto', 'native', 'torch', 'plain'\], got 'fast'"):
        ConvDecoder(4, "pendulum", backend="fast")


def test_every_backend_draws_the_same_images(decoder_path):
    """The plain NCHW layers in float64 as the reference; the backend under test in float32; and ``"auto"``, whichever
    path it takes here, gives the explicit path's images and gradients (input and every parameter) up to rounding."""
    torch.manual_seed(0)
    ref = ConvDecoder(5, **SPEC, backend="plain").double()
    g = ConvDecoder(5, **SPEC, backend=decoder_path)
    g.load_state_dict(ref.state_dict())
    x = torch.randn(7, 5)
    assert ran_native(g, x.clone()) == (decoder_path == "native")
    torch.testing.assert_close(g(x).double(), ref(x.double()), rtol=1e-5, atol=1e-5)
    auto = ConvDecoder(5, **SPEC)
    auto.load_state_dict(ref.state_dict())
    weight = torch.rand(7, *g.out_shape)
    results = []
    for dec in (g, auto):
        xg = x.clone().requires_grad_()
        out = dec(xg)
        results.append((out.detach(), *torch.autograd.grad((out * weight).sum(), [xg, *dec.parameters()])))
    names = ["output", "x", *(name for name, _ in g.named_parameters())]
    for name, got, want in zip(names, results[1], results[0]):
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5, msg=lambda m, n=name: f"{n}: {m}")


def test_auto_is_a_rule_of_the_device_and_the_vector_unit():
    """The native kernels on a CPU with AVX-512 (faster there: Xeon, Zen 4, Zen 5) or full-width AVX2 (Zen 3), the
    torch path where AVX2 runs as two 128-bit halves (the kernels lost on Zen 1), on a CPU with neither, and on any
    other device whatever the CPU."""
    assert decoder.auto_path("cpu", "avx512") == "native"
    assert decoder.auto_path("cpu", "avx2") == "native"
    assert decoder.auto_path("cpu", "avx2-128") == "torch"
    assert decoder.auto_path("cpu", None) == "torch"
    for device in ("cuda", "mps", "xpu", "meta"):
        for simd in ("avx512", "avx2", "avx2-128", None):
            assert decoder.auto_path(device, simd) == "torch"


CPUINFO = """processor\t: 0
vendor_id\t: {vendor}
cpu family\t: {family}
model\t\t: {model}
model name\t: some CPU
flags\t\t: fpu sse2 {flags}

processor\t: 1
vendor_id\t: {vendor}
flags\t\t: fpu
"""


@pytest.mark.parametrize(
    "vendor, family, model, flags, want",
    [
        ("AuthenticAMD", 23, 1, "avx2 fma", "avx2-128"),  # Zen 1 (the EPYC measured)
        ("AuthenticAMD", 23, 8, "avx2 fma", "avx2-128"),  # Zen+
        ("AuthenticAMD", 21, 101, "avx2 fma", "avx2-128"),  # Excavator, before Zen
        ("AuthenticAMD", 23, 49, "avx2 fma", "avx2"),  # Zen 2 (Rome): full-width units
        ("AuthenticAMD", 25, 1, "avx2 fma", "avx2"),  # Zen 3 (Milan, measured)
        ("AuthenticAMD", 25, 17, "avx2 fma avx512f", "avx512"),  # Zen 4
        ("GenuineIntel", 6, 85, "avx2 fma avx512f", "avx512"),
        ("GenuineIntel", 6, 60, "avx2 fma", "avx2"),  # Haswell
        ("GenuineIntel", 6, 42, "avx", None),
        ("AuthenticAMD", 23, 1, "avx2", None),  # no FMA: the kernels need it
    ],
)
def test_cpu_simd_reads_the_first_processors_flags_vendor_and_model(
    tmp_path, monkeypatch, vendor, family, model, flags, want
):
    """``cpu_simd`` from a written /proc/cpuinfo: only the first processor's lines count (the second's flags would
    say none)."""
    path = tmp_path / "cpuinfo"
    path.write_text(CPUINFO.format(vendor=vendor, family=family, model=model, flags=flags))
    real_open = open
    monkeypatch.setattr("builtins.open", lambda f, *a, **k: real_open(path if f == "/proc/cpuinfo" else f, *a, **k))
    build.cpu_simd.cache_clear()
    try:
        assert build.cpu_simd() == want
    finally:
        monkeypatch.undo()
        build.cpu_simd.cache_clear()


def test_auto_follows_the_cpus_instruction_set(needs_native, monkeypatch):
    """The CPU-feature probe (ssm_ms.nets.native.build.cpu_simd) decides, read through at each forward; an explicit
    backend is not second-guessed."""
    x = torch.randn(3, 5)
    monkeypatch.setattr(build, "cpu_simd", lambda: "avx512")
    assert ran_native(ConvDecoder(5, **SPEC), x.clone())
    monkeypatch.setattr(build, "cpu_simd", lambda: "avx2")
    assert ran_native(ConvDecoder(5, **SPEC), x.clone())
    monkeypatch.setattr(build, "cpu_simd", lambda: "avx2-128")
    assert not ran_native(ConvDecoder(5, **SPEC), x.clone())
    assert ran_native(ConvDecoder(5, **SPEC, backend="native"), x.clone())  # asked for by name: runs there too
    monkeypatch.setattr(build, "cpu_simd", lambda: None)
    assert not ran_native(ConvDecoder(5, **SPEC), x.clone())
    monkeypatch.undo()
    assert build.cpu_simd() in (
        "avx512",
        "avx2",
        "avx2-128",
    )  # the kernels build here: the real probe names one of them


def test_auto_does_not_probe_the_cpu_for_another_devices_tensors(monkeypatch):
    def probe():
        raise AssertionError("the CPU was probed for a tensor on another device")

    monkeypatch.setattr(build, "cpu_simd", probe)
    g = ConvDecoder(5, **SPEC).to("meta")  # a device other than the CPU, without a GPU
    assert g(torch.randn(3, 5, device="meta")).shape == (3, 1, 24, 24)


def test_a_frozen_auto_decoder_runs_on_a_fresh_home_and_writes_nothing(monkeypatch, tmp_path):
    """The encoder stage freezes the SSM (``requires_grad_(False)``): ``cli.py test`` of an encoder on a machine whose
    cache held no backend choice failed in g's first forward, when ``auto`` timed both paths' gradients with respect
    to the parameters. Now nothing is timed and choosing a path writes nothing under the home directory."""
    built = native.library() is not None  # the kernels' own build cache is not a backend choice: built before
    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    monkeypatch.delenv("SSM_MS_CACHE", raising=False)
    assert native.cache_dir() == home / ".cache" / "ssm_ms"
    torch.manual_seed(0)
    g = ConvDecoder(10, "pendulum").requires_grad_(False)
    with torch.inference_mode():  # what ``test`` runs under
        assert g(torch.randn(1, 10)).shape == (1, 1, 24, 24)
    x = torch.randn(4, 10, requires_grad=True)  # the encoder's states, trained through the frozen g
    out = g(x)
    (grad,) = torch.autograd.grad(out.square().sum(), [x])
    assert grad.shape == x.shape and all(p.grad is None for p in g.parameters())
    want_native = built and decoder.auto_path("cpu", build.cpu_simd()) == "native"
    assert (NATIVE_NODE in _graph_names(out)) == want_native
    assert not list(home.rglob("*")), "choosing a backend wrote under HOME"


def test_a_traced_forward_takes_the_torch_path(needs_native, monkeypatch):
    """torch.export traces with fake tensors: auto takes the torch path there; a real forward then follows the rule."""
    monkeypatch.setattr(build, "cpu_simd", lambda: "avx512")
    g = ConvDecoder(5, **SPEC).eval()
    program = torch.export.export(g, (torch.randn(3, 5),))
    assert "ssm_ms.conv_stack" not in str(program.graph)
    assert ran_native(g, torch.randn(3, 5))


def test_auto_without_the_kernels_runs_torch(monkeypatch):
    monkeypatch.setattr(build, "cpu_simd", lambda: "avx512")  # the rule says native, but nothing is built
    monkeypatch.setattr(build, "_state", {"lib": None, "reason": "no C compiler", "key": None})
    assert not ran_native(ConvDecoder(5, **SPEC), torch.randn(3, 5))


def test_native_tests_fail_instead_of_skipping_where_the_kernels_are_required(monkeypatch):
    from tests.conftest import REQUIRE_NATIVE_ENV, native_or_skip

    monkeypatch.setattr(build, "_state", {"lib": None, "reason": "no C compiler", "key": None})
    monkeypatch.delenv(REQUIRE_NATIVE_ENV, raising=False)
    with pytest.raises(pytest.skip.Exception, match="native kernels unavailable: no C compiler"):
        native_or_skip()
    monkeypatch.setenv(REQUIRE_NATIVE_ENV, "1")
    with pytest.raises(pytest.fail.Exception, match="no C compiler.*SSM_MS_REQUIRE_NATIVE=1"):
        native_or_skip()
