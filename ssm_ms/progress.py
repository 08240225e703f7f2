"""The progress of a whole fit: Lightning's bar on a terminal, plain lines in a log file, both saying how long the run
has to go.

Lightning's bar counts the batches of the epoch under way (``Epoch 445: 44%|...``); the paper's fits run for 1000
epochs, hours to days on CPU, in several sessions. :class:`RunProgressBar` adds the epoch count and the time the
remaining epochs take at the pace of the last ones: ``Epoch 445/1000, ~3.9 h to go``. The pace is the time between
the starts of consecutive epochs (training, validation, checkpoints: all an epoch costs), the median of the last
``window`` epochs of this process (a resumed run starts counting again): an epoch that spans a pause (the process
stopped while something else used the cores) or a slow first epoch does not inflate the estimate for the next
``window`` epochs, as a mean would. Under a time budget (``trainer.max_time``: Lightning's ``Timer``) the time to go
is the smaller of that estimate and the budget's time left, the budget alone where the run has no ``max_epochs``.

A bar redraws itself with carriage returns, hundreds of times an epoch: in a file (``python cli.py fit ... > run.log
2>&1``) that is one unreadable line per epoch. Where the output is not a terminal the bar writes plain lines instead,
one per training epoch, at most one every ``interval`` seconds (fast epochs: a few lines a minute; a long epoch: one
every ``interval`` within it too), the first and the last epoch always. ``cli.py`` puts it in place of
Lightning's bar whenever a config has a progress bar and names none of its own.
"""

from __future__ import annotations

import statistics
import sys
import time
from collections import deque
from typing import Any, Literal

import lightning.pytorch as pl
from lightning.pytorch.callbacks import Timer, TQDMProgressBar

MODES = ("auto", "bar", "lines")


class RunProgressBar(TQDMProgressBar):
    """Lightning's ``TQDMProgressBar``, the training bar described as ``Epoch e/max_epochs, ~T to go``; or plain lines.

    The time to go is the remaining epochs at the pace of the last ``window`` (the median of their durations), or the
    time left of the fit's time budget (``trainer.max_time``) where that is less; the budget's alone where the run has
    no ``max_epochs``.

    In ``lines`` mode nothing is redrawn: a training epoch ends with one line on stdout, flushed, such as
    ``epoch 12/300  1.4 s  ~7 min to go  train/loss 0.0123  val/rollout_mse 0.0456`` (the epoch as Lightning counts
    it, from 0; what it took; the time to go, where some is left; the metrics Lightning's bar shows), unless the
    last epoch's line is less than ``interval`` seconds old (the first and the last epoch's are always written), and an
    epoch longer than ``interval`` seconds also writes ``epoch 12/300  batch 120/400  52 s  ...`` at most once every
    ``interval`` seconds. Validation, the sanity check, test and predict write nothing;
    :meth:`~lightning.pytorch.core.LightningModule.print` prints as plain ``print``.

    Args:
        window: how many of the last epochs' durations make the pace (their median).
        refresh_rate: as ``TQDMProgressBar``'s (0 shows nothing, bar or lines).
        mode: ``"bar"`` (Lightning's bar, redrawn in place), ``"lines"`` (the lines above) or ``"auto"``: lines where
            stdout is not a terminal when the fit starts (redirected to a file, a pipe), the bar where it is.
        interval: in ``lines`` mode, the least time in seconds between two lines.
    """

    def __init__(
        self,
        window: int = 10,
        refresh_rate: int = 1,
        mode: Literal["auto", "bar", "lines"] = "auto",
        interval: float = 15.0,
    ):
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        if mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, got {mode!r}")
        if interval < 0:
            raise ValueError(f"interval must be >= 0 seconds, got {interval}")
        super().__init__(refresh_rate=refresh_rate)
        self.mode = mode
        self.interval = float(interval)
        self._lines = mode == "lines"
        self._durations: deque[float] = deque(maxlen=window)
        self._started: float | None = None
        self._last_line: float | None = None  # when the last line was written
        self._last_end: float | None = None  # when the last epoch's end line was written
        self._unwritten: tuple[int, float, float] | None = None  # an epoch's end not written: (epoch, time, duration)
        self._clock = time.monotonic

    # ---------------------------------------------------------------- bar or lines
    def setup(self, trainer: pl.Trainer, pl_module: pl.LightningModule, stage: str) -> None:
        super().setup(trainer, pl_module, stage)
        self._lines = self.mode == "lines" or (self.mode == "auto" and not _isatty(sys.stdout))

    @property
    def is_enabled(self) -> bool:
        """Whether the tqdm bars draw: as Lightning's, and not in ``lines`` mode."""
        return super().is_enabled and not self._lines

    @property
    def writes_lines(self) -> bool:
        """Whether this process writes the lines: ``lines`` mode, enabled (rank zero, ``refresh_rate`` > 0)."""
        return self._lines and super().is_enabled

    # ---------------------------------------------------------------- hooks
    def on_train_epoch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        super().on_train_epoch_start(trainer, pl_module)
        now = self._clock()
        if self._started is not None:
            self._durations.append(now - self._started)
        self._started = now
        budget = budget_left(trainer)
        self.train_progress_bar.set_description(self.describe(trainer.current_epoch, trainer.max_epochs, budget))

    def on_train_batch_end(
        self, trainer: pl.Trainer, pl_module: pl.LightningModule, outputs: Any, batch: Any, batch_idx: int
    ) -> None:
        super().on_train_batch_end(trainer, pl_module, outputs, batch, batch_idx)
        if not self.writes_lines or self._started is None:
            return
        total = self.total_train_batches
        done = batch_idx + 1
        now = self._clock()
        since = min(now - self._started, now - (self._last_line if self._last_line is not None else self._started))
        if done >= total or since < self.interval:
            return  # the epoch's own line follows its last batch; a short epoch writes none within it
        known = total if total != float("inf") else None
        counted = f"batch {done}/{known}" if known else f"batch {done}"
        self._write(trainer, pl_module, now, counted, done / known if known else None)

    def on_train_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        super().on_train_epoch_end(trainer, pl_module)
        if not self.writes_lines or self._started is None:
            return
        now = self._clock()
        last = trainer.max_epochs is not None and trainer.current_epoch + 1 >= trainer.max_epochs > 0
        if self._last_end is None or last or now - self._last_end >= self.interval:
            self._write(trainer, pl_module, now, None, 1.0)
            self._last_end, self._unwritten = now, None
        else:
            self._unwritten = (trainer.current_epoch, now, now - self._started)

    def on_train_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        """The last epoch's line, where the run ended early (a time budget, a stop) before it was written."""
        super().on_train_end(trainer, pl_module)
        if self.writes_lines and self._unwritten is not None:
            epoch, now, took = self._unwritten
            self._started = now - took
            self._write(trainer, pl_module, now, None, 1.0, epoch)
            self._unwritten = None

    def _write(
        self,
        trainer: pl.Trainer,
        pl_module: pl.LightningModule,
        now: float,
        counted: str | None,
        part: float | None,
        epoch: int | None = None,
    ) -> None:
        """One line on stdout: the epoch under way (or ``epoch``), ``counted`` (its batches, or None at its end), what
        it has taken, the time to go with ``part`` of the epoch done (None: not known), the bar's metrics."""
        epoch = trainer.current_epoch if epoch is None else epoch
        max_epochs = trainer.max_epochs
        took = now - self._started
        bounded = max_epochs is not None and max_epochs >= 0
        fields = [f"epoch {epoch}/{max_epochs}" if bounded else f"epoch {epoch}"]
        fields += [counted] if counted else []
        fields.append(duration(took))
        current = took / part if part else None  # what the epoch under way takes, as far as it went
        left = max_epochs - epoch - (part or 0.0) if bounded else None
        to_go = self.time_to_go(left, budget_left(trainer), current)
        fields += [f"~{duration(to_go)} to go"] if to_go else []  # none where nothing is left
        fields += [f"{key} {_number(value)}" for key, value in self.get_metrics(trainer, pl_module).items()]
        print("  ".join(fields), file=sys.stdout, flush=True)
        self._last_line = now

    # ---------------------------------------------------------------- the time to go
    def describe(self, epoch: int, max_epochs: int | None, budget: float | None = None) -> str:
        """The bar's description at the start of an epoch: ``Epoch e`` (0-based, as Lightning's), ``/max_epochs`` where
        the run has one, the time still to go (:meth:`time_to_go`, ``budget``: the time budget's seconds left)."""
        bounded = max_epochs is not None and max_epochs >= 0
        text = f"Epoch {epoch}/{max_epochs}" if bounded else f"Epoch {epoch}"
        left = self.time_to_go(max_epochs - epoch if bounded else None, budget)
        return text if left is None else f"{text}, ~{duration(left)} to go"

    def time_to_go(self, epochs_left: float | None, budget: float | None, current: float | None = None) -> float | None:
        """Seconds to go: the smaller of ``epochs_left`` epochs at the pace (the median of the last ``window`` epochs'
        durations, ``current``, the duration of the epoch under way, counting as the latest) and ``budget``, the
        seconds left of a time budget; None where neither is known."""
        recent = [*self._durations, *([current] if current is not None else [])][-self._durations.maxlen :]
        guesses = [statistics.median(recent) * epochs_left] if recent and epochs_left is not None else []
        guesses += [max(budget, 0.0)] if budget is not None else []
        return min(guesses, default=None)


def time_budget(trainer: pl.Trainer) -> tuple[float, float] | None:
    """(seconds elapsed, seconds in all) of the fit's time budget (``trainer.max_time``, kept by Lightning's
    ``Timer``, over the sessions of a resumed run); None without one."""
    for timer in (c for c in trainer.callbacks if isinstance(c, Timer)):
        left = timer.time_remaining()
        if left is not None:
            elapsed = timer.time_elapsed()
            return elapsed, elapsed + left
    return None


def budget_left(trainer: pl.Trainer) -> float | None:
    """Seconds left of the fit's time budget, None without one."""
    budget = time_budget(trainer)
    return None if budget is None else budget[1] - budget[0]


def duration(seconds: float) -> str:
    """``1.4 s``, ``45 s``, ``12 min``, ``3.9 h``, ``2.5 days``."""
    if seconds < 9.95:
        return f"{seconds:.1f} s"
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.0f} min"
    if seconds < 48 * 3600:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 86400:.1f} days"


def _number(value: Any) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def _isatty(stream: Any) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False
