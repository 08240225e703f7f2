"""What an LSTM's training needs of the machine's memory, checked before the first step.

Training an ``nn.LSTM`` on CPU keeps, for the backward, its gates and states at every step of every sequence: the
peak grows with batch x steps x hidden units. Measured for torch 2.13's CPU LSTM (the peak resident memory of a
forward and backward, ``tests/test_memory.py``): 62-64 bytes per sequence, step and unit for a one-layer LSTM, whatever
its input width, and 45-48 more for each further layer or direction. At the paper's Lorenz size (batches of 40 pieces
of 10,000 steps, 1024 units) that is ~26 GB: on a 24 GiB machine the kernel's OOM killer stopped such a run during its
first step, with no message of ours. :func:`check_lstm_memory` refuses it before it starts, naming the batch that
would fit. The estimate is a lower bound (below every measurement, and it leaves out the data, the other layers and
the rest of the process), compared with the memory available when the fit starts: a run it refuses would not have
fitted beside what the machine holds then. Not checked on GPUs (cuDNN keeps less; the device's allocator reports an
overflow as an error, not a kill)."""

from __future__ import annotations

import torch
from torch import nn

# bytes per (sequence, step, hidden unit), forward and backward on CPU: an LSTM's first layer (one direction), and
# each further layer or direction; each just below what was measured
LSTM_FIRST_BYTES = 60
LSTM_FURTHER_BYTES = 45


def available_memory() -> int | None:
    """The memory this machine can give a process now, in bytes (``MemAvailable``; ``None`` where not Linux)."""
    try:
        with open("/proc/meminfo") as info:
            return next(int(line.split()[1]) * 1024 for line in info if line.startswith("MemAvailable:"))
    except (OSError, StopIteration, ValueError):
        return None


def lstm_units(module: nn.Module) -> int:
    """Hidden units over every ``nn.LSTM`` in ``module``, each counted per layer and direction."""
    return sum(
        m.hidden_size * m.num_layers * (2 if m.bidirectional else 1) for m in module.modules() if isinstance(m, nn.LSTM)
    )


def lstm_training_bytes(module: nn.Module, batch: int, steps: int) -> int:
    """A lower bound of what training the LSTMs of ``module`` on ``batch`` sequences of ``steps`` steps takes at its
    peak, on CPU."""
    per_step = 0
    for m in module.modules():
        if isinstance(m, nn.LSTM):
            streams = m.num_layers * (2 if m.bidirectional else 1)
            per_step += m.hidden_size * (LSTM_FIRST_BYTES + LSTM_FURTHER_BYTES * (streams - 1))
    return per_step * batch * steps


def check_lstm_memory(
    module: nn.Module, batch: int, steps: int, device: torch.device, what: str, processes: int = 1
) -> None:
    """Refuse (:class:`ValueError`, naming a batch that fits) to train the LSTMs of ``module`` on ``batch``
    sequences of ``steps`` steps where their need alone exceeds the memory this machine has available;
    ``processes``: as many copies training side by side on this machine, each on its own batch (a trainer's
    ``num_devices``: on CPU, DDP runs one process per device; off CPU nothing is checked)."""
    available = available_memory()
    need = lstm_training_bytes(module, batch, steps) * processes
    if torch.device(device).type != "cpu" or available is None or need <= available:
        return
    fits = int(0.8 * available // (need / batch))  # a fifth left for the rest: data, the other layers
    each = f" in each of {processes} processes" if processes > 1 else ""
    fix = (
        f"give batches of at most {fits} (data.init_args.batch_size), shorter training sequences, or a machine with "
        "more memory"
        if fits
        else "even one sequence does not fit: give shorter training sequences, or a machine with more memory"
    )
    raise ValueError(
        f"{what} needs at least {_size(need)} to train on batches of {batch} sequences of {steps} steps{each} "
        f"({lstm_units(module)} LSTM units), more than the {_size(available)} of memory this machine has available: "
        f"{fix}"
    )


def _size(n: float) -> str:
    if n >= 1e8:
        return f"{n / 1e9:.{0 if n >= 10e9 else 1}f} GB"
    return f"{n / 1e6:.0f} MB" if n >= 1e6 else f"{n / 1e3:.0f} kB"
