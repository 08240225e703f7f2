"""What a figure was measured on: used by the results files and the benchmarks."""

from __future__ import annotations

import os
import platform
import socket


def cpu_model() -> str:
    """The CPU's model name (from /proc/cpuinfo on Linux), else what ``platform`` knows."""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown CPU"


def describe() -> str:
    """``host: N cores, CPU, GPU, torch version`` in one line."""
    import torch

    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "no GPU"
    return f"{socket.gethostname()}: {os.cpu_count()} cores, {cpu_model()}, {gpu}, torch {torch.__version__}"
