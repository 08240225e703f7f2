"""What a figure was measured on: used by the results files and the benchmarks."""

from __future__ import annotations

import os
import platform
import socket
import time


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


SHARED_CORES = 0.25  # other processes' average CPU use above which a benchmark's machine counts as shared


def _busy_seconds() -> float | None:
    """CPU seconds the whole machine has been busy (user, nice, system, irq, softirq: /proc/stat), or None."""
    try:
        with open("/proc/stat") as fh:
            fields = fh.readline().split()
        user, nice, system, _idle, _iowait, irq, softirq = (int(v) for v in fields[1:8])
        return (user + nice + system + irq + softirq) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


def _own_seconds() -> float:
    """CPU seconds of this process and of its children that have exited and been waited for."""
    import resource

    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


class CpuWatch:
    """How busy other processes kept the machine while a benchmark ran: the machine's busy CPU time (/proc/stat)
    less this process's and its finished children's (``getrusage``), per second of wall time, since construction.

    A load average lags by minutes (one benchmark right after another reads as "shared"); this counts what
    others actually ran. Call :meth:`others` after the benchmark's worker processes have exited and been waited
    for (a worker still running counts as another process). Linux only: ``None`` elsewhere.
    """

    def __init__(self) -> None:
        self._busy0, self._own0, self._t0 = _busy_seconds(), _own_seconds(), time.monotonic()

    def others(self) -> float | None:
        """Average number of cores kept busy by other processes (``None`` where /proc/stat is missing)."""
        busy, wall = _busy_seconds(), time.monotonic() - self._t0
        if busy is None or self._busy0 is None or wall <= 0:
            return None
        return max(0.0, (busy - self._busy0 - (_own_seconds() - self._own0)) / wall)


def quiet_note(others: float | None) -> str:
    """One sentence for a results file: what :meth:`CpuWatch.others` measured and what it means for the figures."""
    if others is None:
        return "other processes' CPU use during the run: not measured (no /proc/stat here)"
    head = (
        f"other processes kept {others:.2f} cores busy on average during the run (/proc/stat less this "
        "benchmark's own processes)"
    )
    if others > SHARED_CORES:
        return (
            head + ": the machine was shared with other jobs, so absolute figures are slower than on a quiet "
            "machine; the same-round ratios are the comparison"
        )
    return head + ": the machine was otherwise quiet"
