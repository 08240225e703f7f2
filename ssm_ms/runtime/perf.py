"""Process-level settings that make CPU training fast.

On CPU, a training step of the paper's pendulum model allocates and frees activation tensors of
~100 MB (4000 decoded 24x24 frames and the decoder's feature maps) dozens of times. glibc serves
such sizes with fresh ``mmap`` pages and returns them to the system on ``free``, so every step pays
millions of page faults: measured here, 6 million minor faults and 1-2 s per step, against 0.35
million and ~0.4 s when the memory is kept for reuse (see benchmarks/results/train_step.md).
:func:`configure_allocator` tells glibc to serve large blocks from the heap and keep freed memory
(the process's resident memory then stays at its peak). ``cli.py`` calls it; call it yourself at the
start of a Python training script. ``SSM_MS_MALLOC_TUNING=0`` disables it.

Trimming is switched off, not merely raised: glibc gives the top of the heap back whenever more than
``M_TRIM_THRESHOLD`` bytes lie free there, and ``mallopt`` takes an ``int``, so the highest threshold is
2 GiB. A step of the quadruple pendulum's encoder (100 frames of 48x48 for 40 trajectories) frees ~2.7 GB
of activations, more than that: with a 2 GiB threshold its heap shrank and page-faulted back every step
(140,000 page faults and 11% of a step on a quiet 2-core machine; benchmarks/results/allocator_quad_encoder.md).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
_configured: bool | None = None


def configure_allocator(mmap_threshold: int = 1 << 30, trim_threshold: int = -1) -> bool:
    """Keep large freed blocks for reuse (glibc ``mallopt``). Returns whether it applied.

    ``trim_threshold=-1`` (the default) never gives the heap's free top back to the system; blocks of at
    least ``mmap_threshold`` bytes still come from (and go back to) ``mmap``. The first call in a process
    decides: later calls return its result and change nothing.

    Does nothing (and returns False) off glibc, or when ``SSM_MS_MALLOC_TUNING=0``.
    """
    global _configured
    if _configured is not None:
        return _configured
    _configured = False
    if os.environ.get("SSM_MS_MALLOC_TUNING", "1") == "0":
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (macOS, musl, Windows)
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    _configured = bool(mallopt(M_MMAP_THRESHOLD, mmap_threshold)) and bool(mallopt(M_TRIM_THRESHOLD, trim_threshold))
    return _configured


def bf16_support(device: str | object = "cpu") -> tuple[bool, str]:
    """Whether ``device`` runs bfloat16 natively, and if not, why (one sentence for an error message).

    CPU: the AVX512-BF16 or AMX instructions (without them PyTorch emulates bfloat16 through float32,
    slower than float32 itself). CUDA: ``torch.cuda.is_bf16_supported()`` (compute capability >= 8.0).
    """
    import torch

    from ssm_ms.runtime.private import cpu_bf16_native

    device = torch.device(device)
    if device.type == "cuda":
        if torch.cuda.is_available() and torch.cuda.is_bf16_supported(including_emulation=False):
            return True, ""
        return False, "this GPU has no native bfloat16 support (it needs compute capability 8.0 or newer)"
    if device.type == "cpu":
        if cpu_bf16_native():
            return True, ""
        return False, (
            "this CPU has no native bfloat16 instructions (AVX512-BF16 or AMX): PyTorch would emulate "
            "bfloat16 through float32, slower than float32 itself"
        )
    return False, f"bfloat16 support on {device.type!r} devices is not known to ssm-ms"


def check_precision(precision: str | int, device: str | object) -> None:
    """Refuse ``trainer.precision`` in bfloat16 (``bf16-mixed``, ``bf16-true``) where ``device`` lacks it natively.

    Raises ``ValueError`` naming the machine's problem and the fix (``trainer.precision: 32``): a bfloat16
    run on such a device would be slower than float32, for no gain in memory that matters here.
    """
    if not str(precision).startswith("bf16"):
        return
    ok, why = bf16_support(device)
    if not ok:
        raise ValueError(f"trainer.precision={precision} asks for bfloat16, but {why}: use trainer.precision: 32")
