"""The LSTM memory check (ssm_ms.runtime.memory): its estimate against the peak a real LSTM's training takes,
measured in a fresh process."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from ssm_ms.runtime import memory

MEASURE = """
import sys, torch
from ssm_ms.runtime.perf import configure_allocator
configure_allocator()  # as cli.py
def status(key):  # kB in /proc/self/status
    return next(int(l.split()[1]) for l in open("/proc/self/status") if l.startswith(key + ":"))
b, t, i, h, layers = map(int, sys.argv[1:])
lstm = torch.nn.LSTM(i, h, num_layers=abs(layers), batch_first=True, bidirectional=layers < 0)
lstm(torch.randn(1, 2, i))[0].sum().backward()  # the libraries' own first-use allocations, before the baseline
x = torch.randn(b, t, i)
before = status("VmRSS")
open("/proc/self/clear_refs", "w").write("5")  # the peak (VmHWM) starts again from here
lstm(x)[0].sum().backward()
print((status("VmHWM") - before) * 1024)
"""


@pytest.mark.parametrize(
    "b, t, i, h, layers",
    [(4, 2000, 16, 512, 1), (2, 2000, 1, 256, 2), (4, 2000, 1, 512, -1)],  # -1: one bidirectional layer
)
def test_the_estimate_is_a_close_lower_bound_of_a_real_lstm_training_peak(b, t, i, h, layers):
    """Forward and backward of an nn.LSTM on CPU, in a fresh process (its peak resident memory counted from just
    before): the estimate is below the measured peak, and within 25% of it, layers and directions counted."""
    measured = int(
        subprocess.run(
            [sys.executable, "-c", MEASURE, *map(str, (b, t, i, h, layers))], capture_output=True, text=True, check=True
        ).stdout.split()[-1]
    )
    lstm = torch.nn.LSTM(i, h, num_layers=abs(layers), bidirectional=layers < 0)
    estimate = memory.lstm_training_bytes(lstm, b, t)
    assert estimate <= measured <= 1.25 * estimate, (measured, estimate)


def test_a_run_that_cannot_fit_is_refused_naming_a_batch_that_does(monkeypatch):
    net = torch.nn.Sequential(torch.nn.Linear(3, 3), torch.nn.LSTM(3, 1024))  # the LSTMs are found inside
    need = 60 * 40 * 10_000 * 1024  # the paper's Lorenz encoder: ~25 GB
    assert memory.lstm_training_bytes(net, 40, 10_000) == need
    monkeypatch.setattr(memory, "available_memory", lambda: 20_000_000_000)
    with pytest.raises(ValueError) as refused:
        memory.check_lstm_memory(net, 40, 10_000, torch.device("cpu"), "the encoder")
    assert str(refused.value) == (
        "the encoder needs at least 25 GB to train on batches of 40 sequences of 10000 steps (1024 LSTM units), more "
        "than the 20 GB of memory this machine has available: give batches of at most 26 (data.init_args.batch_size), "
        "shorter training sequences, or a machine with more memory"
    )  # 26 = 0.8 * 20e9 / (60 * 10,000 * 1024)
    memory.check_lstm_memory(net, 32, 10_000, torch.device("cpu"), "the encoder")  # 19.7 GB: not refused
    with pytest.raises(
        ValueError, match=r"batches of 17 sequences of 10000 steps in each of 2 processes .* at most 13 "
    ):
        memory.check_lstm_memory(net, 17, 10_000, torch.device("cpu"), "the encoder", processes=2)  # 2 x 10.4 GB
    memory.check_lstm_memory(net, 40, 10_000, torch.device("meta"), "the encoder")  # not a CPU: not checked
    monkeypatch.setattr(memory, "available_memory", lambda: 10**8)
    with pytest.raises(ValueError, match="even one sequence does not fit: give shorter training sequences"):
        memory.check_lstm_memory(net, 40, 10_000, torch.device("cpu"), "the encoder")
