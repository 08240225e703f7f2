"""Native CPU kernels for the ConvDecoder: compiled on first use with the system C compiler, called through ctypes.

The kernels (``conv_stack.c``: the decoder's whole stack of transposed convolutions with the layer norms and ReLUs
between them, one sample at a time in cache, forward and backward, float32) are plain C without Python or torch
headers: compiling them takes about a second. The shared library is cached under ``$SSM_MS_CACHE`` (default
``$XDG_CACHE_HOME/ssm_ms`` or ``~/.cache/ssm_ms``), keyed by the source, the compiler, its flags and this CPU's
instruction sets (it is built with ``-march=native``), so a home directory shared between machines never loads a
library built for another CPU. The rows (samples) are shared among OpenMP threads: the library links
``libgomp.so.1``, and in a process that has imported torch that is torch's own copy (same soname), so the kernels
run on torch's intra-op threads and follow ``torch.set_num_threads``. A compiler without ``-fopenmp`` counts as
none.

The kernels are written for AVX-512 (16 lanes) and AVX2 with FMA (8 lanes, smaller tiles); in plain C loops they
were slower than the torch-only path, so on other CPUs (ARM, x86 before AVX2) they are not built. Where the CPU
has neither, no C compiler is found or compiling fails, :func:`library` returns ``None`` and
:func:`unavailable_reason` says why; a decoder with backend ``"auto"`` then runs its torch path (same values). A
missing compiler or a failed build is said once, as a ``RuntimeWarning`` (the decoder may be slower than it could
be); a CPU without those instructions is not (nothing is lost). Whether the kernels are used at all is the
decoder's ``backend`` (:class:`ssm_ms.nets.ConvDecoder`): this module only builds them when asked.
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import threading
import warnings
from pathlib import Path

import torch  # noqa: F401  (loaded first: the kernels then bind torch's own libgomp, see above)

SOURCE = Path(__file__).with_name("conv_stack.c")
# the first set the compiler accepts; OpenMP is required (kernels on one thread beside torch's threaded
# convolutions were not measured, so not offered); -march=native for AVX-512 or AVX2 (the source refuses others)
FLAG_SETS = (
    ["-O3", "-march=native", "-funroll-loops", "-mtune-ctrl=use_gather", "-fopenmp"],  # GCC: hardware gathers
    ["-O3", "-march=native", "-funroll-loops", "-fopenmp"],
)
# Why the kernels need vector instructions: written in plain C loops (commit dd83305) they were slower than the
# torch-only path (pendulum decoder, 4000 frames, 2 threads, an AVX-512 Xeon: plain -O3 403 ms, plain loops built
# for AVX2 364 ms, torch-only 196 ms; the intrinsics: benchmarks/results/decoder_profile*.md), so other CPUs run
# the torch-only path, silently.
NO_SIMD = (
    "this CPU has neither AVX-512 nor AVX2 with FMA (per /proc/cpuinfo): the kernels need one of them, "
    "the torch-only path runs"
)

_lock = threading.Lock()
_state: dict[str, object] = {}


def _compiler() -> str | None:
    for name in (os.environ.get("CC"), "cc", "gcc", "clang"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


def cpu_fields() -> dict[str, str]:
    """The first processor's lines of /proc/cpuinfo as ``{key: value}`` (``flags``, ``vendor_id``, ``cpu family``,
    ``model``, ``model name``; ``Features`` and ``CPU part`` on ARM): the first processor describes them all. Empty
    where there is no /proc/cpuinfo (macOS, Windows)."""
    fields: dict[str, str] = {}
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.strip() == "" and fields:
                    break
                key, _, value = line.partition(":")
                fields.setdefault(key.strip(), value.strip())
    except OSError:
        pass
    return fields


@functools.cache
def cpu_simd() -> str | None:
    """The vector unit of this CPU that the kernels are written for: ``"avx512"`` where /proc/cpuinfo lists
    ``avx512f``; where it lists ``avx2`` and ``fma`` (and no ``avx512f``), ``"avx2"``, or ``"avx2-128"`` on an AMD
    CPU that runs each 256-bit AVX2 instruction as two 128-bit halves (family 0x17 below model 0x30: Zen 1 and
    Zen+; the families before Zen); else ``None`` (also where there is no /proc/cpuinfo: macOS, Windows). Read once
    per process (:func:`cpu_fields`)."""
    fields = cpu_fields()
    flags = set(fields.get("flags", "").split())
    if "avx512f" in flags:
        return "avx512"
    if not {"avx2", "fma"} <= flags:
        return None
    return "avx2-128" if _half_width_avx2(fields) else "avx2"


def _half_width_avx2(fields: dict[str, str]) -> bool:
    """Whether /proc/cpuinfo's ``vendor_id``, ``cpu family`` and ``model`` name an AMD CPU whose AVX2 runs as two
    128-bit halves (family 0x17 models below 0x30, Zen 1 and Zen+; Zen 2, model 0x30 on, has full-width units)."""
    if fields.get("vendor_id") != "AuthenticAMD":
        return False
    try:
        family, model = int(fields["cpu family"]), int(fields["model"])
    except (KeyError, ValueError):
        return False
    return family < 0x17 or (family == 0x17 and model < 0x30)


def _has_simd() -> bool:
    """Whether the kernels can be built for this CPU (:func:`cpu_simd` names an instruction set)."""
    return cpu_simd() is not None


def _cpu_signature() -> str:
    """The CPU's model and instruction-set flags (what ``-march=native`` compiles for)."""
    fields = cpu_fields()
    text = "".join(
        f"{key}: {fields[key]}\n" for key in ("flags", "model name", "Features", "CPU part") if key in fields
    )
    return platform.machine() + platform.processor() + text


def cache_dir() -> Path:
    if os.environ.get("SSM_MS_CACHE"):
        return Path(os.environ["SSM_MS_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "ssm_ms"


def _build() -> tuple[ctypes.CDLL | None, str | None, str | None]:
    if not _has_simd():
        return None, NO_SIMD, None
    cc = _compiler()
    if cc is None:
        return None, "no C compiler (cc, gcc or clang; or $CC) on PATH", None
    source = SOURCE.read_bytes()
    errors = []
    for flags in FLAG_SETS:
        key = hashlib.sha256(source + cc.encode() + " ".join(flags).encode() + _cpu_signature().encode()).hexdigest()
        target = cache_dir() / f"conv_stack-{key[:20]}.so"
        if not target.exists():
            try:
                target.parent.mkdir(parents=True, exist_ok=True)
                fd, tmp = tempfile.mkstemp(suffix=".so", dir=target.parent)
                os.close(fd)
                result = subprocess.run(
                    [cc, *flags, "-shared", "-fPIC", "-o", tmp, str(SOURCE), "-lm"], capture_output=True, text=True
                )
                if result.returncode != 0:
                    os.unlink(tmp)
                    lines = result.stderr.splitlines()
                    first = next((ln for ln in lines if "error" in ln), result.stderr.strip()[:200])
                    errors.append(f"{Path(cc).name} {' '.join(flags)}: {first.strip()}")
                    continue
                os.replace(tmp, target)  # atomic: a concurrent process sees the whole library or none
            except OSError as err:
                errors.append(f"cannot write {target.parent}: {err}")
                break
        try:
            lib = ctypes.CDLL(str(target))
        except OSError as err:
            errors.append(f"cannot load {target}: {err}")
            continue
        problem = _declare(lib)
        if problem is not None:
            errors.append(f"{target}: {problem}")
            continue
        return lib, None, key
    return None, "compiling the native kernels failed (" + "; ".join(errors) + ")", None


class ConvStackArgs(ctypes.Structure):
    """``conv_stack_args`` of ``conv_stack.c``: what one call of the kernels reads and writes, by name (the fields in
    the C struct's order; a library whose struct has another size is refused)."""

    _fields_ = [
        ("layers", ctypes.c_int64),
        ("geo", ctypes.c_void_p),
        ("params", ctypes.c_void_p),
        ("eps", ctypes.c_void_p),
        ("rows", ctypes.c_int64),
        ("x", ctypes.c_void_p),
        ("out", ctypes.c_void_p),
        ("saved", ctypes.c_void_p),
        ("stats", ctypes.c_void_p),
        ("dout", ctypes.c_void_p),
        ("dx", ctypes.c_void_p),
        ("grads", ctypes.c_void_p),
        ("goff", ctypes.c_void_p),
        ("gsize", ctypes.c_int64),
        ("threads", ctypes.c_int64),
    ]


def _declare(lib: ctypes.CDLL) -> str | None:
    """Declare the library's functions; the reason it cannot be used, or ``None``."""
    p, i, n = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int
    args = ctypes.POINTER(ConvStackArgs)
    lib.conv_stack_threads.argtypes, lib.conv_stack_threads.restype = [], n
    lib.conv_stack_args_size.argtypes, lib.conv_stack_args_size.restype = [], i
    lib.conv_stack_size.argtypes, lib.conv_stack_size.restype = [i, p, n], i
    lib.conv_stack_forward.argtypes, lib.conv_stack_forward.restype = [args], n
    lib.conv_stack_backward.argtypes, lib.conv_stack_backward.restype = [args], n
    if lib.conv_stack_args_size() != ctypes.sizeof(ConvStackArgs):
        return (
            f"its conv_stack_args has {lib.conv_stack_args_size()} bytes, ConvStackArgs "
            f"{ctypes.sizeof(ConvStackArgs)}: the two must list the same fields"
        )
    return None


def library() -> ctypes.CDLL | None:
    """The compiled kernels, built on the first call (``None`` where unavailable: see :func:`unavailable_reason`)."""
    with _lock:
        if "lib" not in _state:
            _state["lib"], _state["reason"], _state["key"] = _build()
            on_purpose = _state["reason"] == NO_SIMD
            if _state["lib"] is None and not on_purpose:
                warnings.warn(
                    f"ssm_ms: the decoder's native kernels are off, running the torch path: "
                    f"{_state['reason']} (a ConvDecoder with backend 'torch' does not ask for them)",
                    RuntimeWarning,
                    stacklevel=2,
                )
        return _state["lib"]  # type: ignore[return-value]


def unavailable_reason() -> str | None:
    library()
    return _state["reason"]  # type: ignore[return-value]


def library_key() -> str | None:
    """What the loaded library was built from (source, compiler, flags, CPU), as a hex digest; ``None`` without one."""
    library()
    return _state["key"]  # type: ignore[return-value]


def threads() -> int:
    """How many threads the kernels share rows among (torch's intra-op thread count)."""
    lib = library()
    return 1 if lib is None else int(lib.conv_stack_threads())


def check(status: int) -> None:
    """Raise for a kernel's non-zero return (-1: its scratch memory could not be allocated)."""
    if status == -1:
        raise MemoryError("ssm_ms native kernel: out of memory for its scratch buffers")
    if status != 0:
        raise ValueError(f"ssm_ms native kernel: bad arguments (status {status})")
