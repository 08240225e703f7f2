"""What a fit prints: Lightning's advertisements and the LeafSpec deprecation dropped, its other lines kept; in a log
file, progress as plain lines."""

from __future__ import annotations

import io
import logging
import subprocess
import sys
import warnings

import lightning.pytorch as pl
from lightning.pytorch.callbacks import Timer

from ssm_ms.progress import RunProgressBar
from ssm_ms.runtime.console import quiet_lightning
from tests.conftest import ROOT, RotationDataModule, fast_trainer, rotation_model

ADVERTISEMENT = "Tip: For seamless cloud"
LEAFSPEC = "isinstance(treespec, LeafSpec)"


def test_a_fit_to_a_file_prints_what_a_user_can_act_on(tmp_path):
    """``python cli.py fit ... > run.log 2>&1``, as long runs are started: neither Lightning's advertisements nor the
    LeafSpec deprecation is in the output, Lightning's other lines are, and the progress is one plain line per
    epoch (no bar redrawn with carriage returns)."""
    data = tmp_path / "osc.npz"
    make = [sys.executable, str(ROOT / "examples" / "make_oscillator_data.py"), "--out", str(data), "--n", "40"]
    subprocess.run(make, check=True, capture_output=True, timeout=120)
    command = [sys.executable, str(ROOT / "cli.py"), "fit", "--config", str(ROOT / "configs" / "oscillator.yaml")]
    command += ["--trainer.max_epochs", "1", "--trainer.limit_train_batches", "2", "--trainer.limit_val_batches", "1"]
    command += ["--trainer.logger.init_args.save_dir", str(tmp_path / "runs"), "--data.init_args.train_path", str(data)]
    log = tmp_path / "run.log"
    with open(log, "w") as out:
        proc = subprocess.run(command, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT, timeout=300)
    text = log.read_text()
    assert proc.returncode == 0, text[-3000:]
    assert ADVERTISEMENT not in text
    assert LEAFSPEC not in text
    assert "`Trainer.fit` stopped: `max_epochs=1` reached." in text  # Lightning's other output stays
    assert "GPU available:" in text
    assert "\r" not in text
    assert [line.split("  ")[0] for line in text.splitlines() if line.startswith("epoch ")] == ["epoch 0/1"]


def test_only_the_advertisements_and_the_leafspec_warning_are_dropped(monkeypatch):
    """The filter on the logger of Lightning's rank_zero_info drops the two tips and nothing else it logs; the warning
    filter ignores the LeafSpec deprecation in any category and no other warning. Twice is the same as once."""
    log = logging.getLogger("lightning.pytorch.utilities.rank_zero")
    monkeypatch.setattr(log, "filters", [])
    seen = []

    class Keep(logging.Handler):
        def emit(self, record):
            seen.append(record.getMessage())

    handler = Keep()
    log.addHandler(handler)
    monkeypatch.setattr(log, "level", logging.INFO)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            quiet_lightning()
            quiet_lightning()
            from lightning.pytorch.utilities.rank_zero import rank_zero_info

            rank_zero_info("💡 Tip: For seamless cloud logging and experiment tracking, try installing [litlogger]")
            rank_zero_info("💡 Tip: For seamless cloud uploads and versioning, try installing [litmodels]")
            rank_zero_info("`Trainer.fit` stopped: `max_epochs=1` reached.")
            for category in (FutureWarning, DeprecationWarning, UserWarning):
                warnings.warn(
                    "`isinstance(treespec, LeafSpec)` is deprecated, use ... instead.", category, stacklevel=1
                )
            warnings.warn("`isinstance(x, Other)` is deprecated", FutureWarning, stacklevel=1)
    finally:
        log.removeHandler(handler)
    assert seen == ["`Trainer.fit` stopped: `max_epochs=1` reached."]
    assert [str(w.message) for w in caught] == ["`isinstance(x, Other)` is deprecated"]
    assert len(log.filters) == 1


class Tick(pl.Callback):
    """A fake clock for the bar, ``seconds`` later at the start of every training batch (validation takes none)."""

    def __init__(self, seconds: float):
        self.now, self.seconds = 0.0, seconds

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        self.now += self.seconds


def fit_with_lines(tmp_path, monkeypatch, bar: RunProgressBar, max_epochs: int, tick=None, **trainer) -> list[str]:
    """The lines a tiny fit writes to a stdout that is not a terminal (a StringIO): 12 trajectories, 3 batches an
    epoch, 20 s a batch on the fake clock, a validation every epoch and a sanity check."""
    tick = tick or Tick(20.0)
    bar._clock = lambda: tick.now
    stdout = io.StringIO()
    monkeypatch.setattr(sys, "stdout", stdout)
    dm = RotationDataModule(data_dir=str(tmp_path / "data"), n_train=12, batch_size=4, val_trajectories=2)
    fast_trainer(
        tmp_path, max_epochs, callbacks=[tick, bar], enable_progress_bar=True, num_sanity_val_steps=1, **trainer
    ).fit(rotation_model(), dm)
    assert "\r" not in stdout.getvalue()
    return stdout.getvalue().splitlines()


def head(line: str) -> list[str]:
    """A progress line's fields before the metrics (``train/loss 0.1``, ...)."""
    return [field for field in line.split("  ") if not field.startswith(("train/", "val/"))]


def test_a_fit_writes_one_line_per_epoch_where_stdout_is_not_a_terminal(tmp_path, monkeypatch):
    """``mode="auto"`` on a StringIO: no bar, one line at each epoch's end (epochs longer than ``interval``), and one
    within it once 30 s have passed
    since the last line (after its second batch, 40 s in); no line for the sanity check or validation. The time to
    go at an epoch's end: the epochs left at the pace of 60 s an epoch; within the first one, its pace so far (40 s
    for 2 of 3 batches: 60 s) for the 3 1/3 epochs left, 200 s."""
    lines = fit_with_lines(tmp_path, monkeypatch, RunProgressBar(interval=30), max_epochs=4)
    assert [head(line) for line in lines] == [
        ["epoch 0/4", "batch 2/3", "40 s", "~3 min to go"],
        ["epoch 0/4", "60 s", "~3 min to go"],  # 3 epochs of 60 s
        ["epoch 1/4", "batch 2/3", "40 s", "~2 min to go"],  # 2 1/3 epochs: 140 s
        ["epoch 1/4", "60 s", "~2 min to go"],
        ["epoch 2/4", "batch 2/3", "40 s", "~80 s to go"],  # 1 1/3 epochs
        ["epoch 2/4", "60 s", "~60 s to go"],
        ["epoch 3/4", "batch 2/3", "40 s", "~20 s to go"],
        ["epoch 3/4", "60 s"],  # nothing left to go
    ]
    for end in lines[1::2]:  # the bar's metrics, this epoch's validation included
        assert "  train/loss " in end and "  val/rollout_mse " in end


def test_fast_epochs_write_a_line_every_interval_and_the_last_one(tmp_path, monkeypatch):
    """Epochs of 3 s (3 batches of 1 s) with ``interval`` 10 s: the first epoch's line, then the first epoch ending
    10 s or more after the last written one (epochs 0, 4, 8 end at 3, 15, 27 s), and the last epoch's (9, at 30 s)."""
    lines = fit_with_lines(tmp_path, monkeypatch, RunProgressBar(interval=10), max_epochs=10, tick=Tick(1.0))
    assert [line.split("  ")[0] for line in lines] == ["epoch 0/10", "epoch 4/10", "epoch 8/10", "epoch 9/10"]


def test_under_a_time_budget_the_time_to_go_is_what_is_left_of_it(tmp_path, monkeypatch):
    """``trainer.max_time`` of 130 s, no max_epochs: the time to go is the budget's time left (the Timer's elapsed
    time the fake clock's), 70 s after the first epoch, 10 s after the second; the Timer stops the run in the third
    (at 140 s, after its first batch), whose end line has nothing left to go. With max_epochs too, the smaller of the
    two estimates."""
    tick = Tick(20.0)
    monkeypatch.setattr(Timer, "time_elapsed", lambda self, stage="train": tick.now)
    bar = RunProgressBar(mode="lines", interval=50)  # no line within the epochs of 60 s, one at each end
    lines = fit_with_lines(tmp_path, monkeypatch, bar, max_epochs=-1, tick=tick, max_time={"seconds": 130})
    assert [head(line) for line in lines] == [
        ["epoch 0", "60 s", "~70 s to go"],
        ["epoch 1", "60 s", "~10 s to go"],
        ["epoch 2", "20 s"],
    ]
    bar = RunProgressBar(mode="bar")
    bar._durations.extend([60.0, 60.0])
    assert bar.describe(5, 10, budget=None) == "Epoch 5/10, ~5 min to go"  # 5 epochs of 60 s
    assert bar.describe(5, 10, budget=200.0) == "Epoch 5/10, ~3 min to go"  # the budget's 200 s: less
    assert bar.describe(5, 10, budget=1000.0) == "Epoch 5/10, ~5 min to go"
    assert bar.describe(5, -1, budget=200.0) == "Epoch 5, ~3 min to go"
    assert bar.describe(5, -1, budget=None) == "Epoch 5"
