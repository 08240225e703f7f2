"""``ssm_ms.runtime.perf.configure_allocator``: freed heap memory stays with the process, even above 2 GiB.

Each case runs in its own interpreter (the allocator's settings are process-wide). It frees three heap blocks
of 900 MB (each below the 1 GiB mmap threshold, so they come from the heap's top; their pages are never touched,
so no physical memory is used) and reads the program break (``sbrk(0)``) before and after: glibc gives the free
top back by lowering the break. With the largest trim threshold ``mallopt`` accepts (2 GiB, what ssm-ms set
before) the 2.7 GB are given back; with ``configure_allocator()`` they are kept. (With glibc's defaults blocks of
this size are mmap-ed, not taken from the heap.)
"""

from __future__ import annotations

import ctypes.util
import json
import os
import platform
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

SCRIPT = r"""
import ctypes, ctypes.util, json, sys
mode = sys.argv[1]
from ssm_ms.runtime.perf import configure_allocator
if mode == "ours":
    applied = configure_allocator()
else:  # "trim 2 GiB"
    applied = configure_allocator(trim_threshold=2**31 - 1)
libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
libc.sbrk.restype, libc.sbrk.argtypes = ctypes.c_void_p, [ctypes.c_ssize_t]
blocks = [libc.malloc(900_000_000) for _ in range(3)]
assert all(blocks), "malloc failed"
grown = libc.sbrk(0)
for b in blocks:
    libc.free(b)
after = libc.sbrk(0)
print(json.dumps({"applied": applied, "given_back": grown - after, "from_heap": all(b < grown for b in blocks)}))
"""

pytestmark = pytest.mark.skipif(
    platform.system() != "Linux" or platform.libc_ver()[0] != "glibc" or not ctypes.util.find_library("c"),
    reason="the allocator settings are glibc's",
)


def run(mode: str) -> dict:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop("SSM_MS_MALLOC_TUNING", None)
    out = subprocess.run(
        [sys.executable, "-c", SCRIPT, mode], env=env, cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_freed_heap_top_above_2_gib_is_kept():
    ours = run("ours")
    assert ours["applied"] and ours["from_heap"]
    assert ours["given_back"] == 0


def test_with_the_largest_trim_threshold_the_heap_top_is_given_back():
    """The check above can fail: with trimming merely raised to 2 GiB, glibc lowers the break by the freed blocks."""
    other = run("trim 2 GiB")
    assert other["applied"] and other["from_heap"]
    assert other["given_back"] >= 2_700_000_000 - 1_000_000
