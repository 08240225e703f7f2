"""The progress bar of a whole fit: Lightning's bar, its description also saying how long the run has to go.

Lightning's bar counts the batches of the epoch under way (``Epoch 445: 44%|...``); the paper's fits run for 1000
epochs, hours to days on CPU, in several sessions. :class:`RunProgressBar` adds the epoch count and the time the
remaining epochs take at the pace of the last ones: ``Epoch 445/1000, ~3.9 h to go``. The pace is the time between
the starts of consecutive epochs (training, validation, checkpoints: all an epoch costs), the median of the last
``window`` epochs of this process (a resumed run starts counting again): an epoch that spans a pause (the process
stopped while something else used the cores) or a slow first epoch does not inflate the estimate for the next
``window`` epochs, as a mean would. ``cli.py`` puts it in place of Lightning's bar whenever a config has a progress
bar and names none of its own.
"""

from __future__ import annotations

import statistics
import time
from collections import deque

import lightning.pytorch as pl
from lightning.pytorch.callbacks import TQDMProgressBar


class RunProgressBar(TQDMProgressBar):
    """Lightning's ``TQDMProgressBar``, the training bar described as ``Epoch e/max_epochs, ~T to go``.

    Args:
        window: how many of the last epochs' durations make the pace (their median).
        refresh_rate: as ``TQDMProgressBar``'s.
    """

    def __init__(self, window: int = 10, refresh_rate: int = 1):
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        super().__init__(refresh_rate=refresh_rate)
        self._durations: deque[float] = deque(maxlen=window)
        self._started: float | None = None
        self._clock = time.monotonic

    def on_train_epoch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        super().on_train_epoch_start(trainer, pl_module)
        now = self._clock()
        if self._started is not None:
            self._durations.append(now - self._started)
        self._started = now
        self.train_progress_bar.set_description(self.describe(trainer.current_epoch, trainer.max_epochs))

    def describe(self, epoch: int, max_epochs: int | None) -> str:
        """``Epoch e`` (0-based, as Lightning's), ``/max_epochs`` where the run has one, the time still to go."""
        if max_epochs is None or max_epochs < 0:
            return f"Epoch {epoch}"
        text = f"Epoch {epoch}/{max_epochs}"
        if not self._durations:
            return text
        left = statistics.median(self._durations) * (max_epochs - epoch)
        return f"{text}, ~{duration(left)} to go"


def duration(seconds: float) -> str:
    """``45 s``, ``12 min``, ``3.9 h``, ``2.5 days``."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.0f} min"
    if seconds < 48 * 3600:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 86400:.1f} days"
