"""A Lightning fit with this project's console (progress, quiet warnings, the package log), a checkpoint every
epoch and a TensorBoard logger: what :func:`ssm_ms.fit` and :meth:`ssm_ms.SSM.fit_encoder` run."""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from datetime import timedelta
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
from lightning.pytorch import LightningDataModule
from lightning.pytorch.loggers import TensorBoardLogger
from lightning.pytorch.trainer.states import TrainerStatus

from ssm_ms.checkpointing import EpochCheckpoint
from ssm_ms.cli import show_package_log
from ssm_ms.progress import RunProgressBar
from ssm_ms.runtime.console import quiet_lightning

_DURATION = re.compile(r"^\s*([0-9]*\.?[0-9]+)\s*(s|sec|min|m|h|d)\s*$")
_UNIT_SECONDS = {"s": 1, "sec": 1, "m": 60, "min": 60, "h": 3600, "d": 86400}


def parse_duration(value: float | str | timedelta) -> timedelta:
    """A training budget: seconds, a ``timedelta``, ``"90s"``, ``"12min"``, ``"1.5h"`` or Lightning's
    ``"DD:HH:MM:SS"``."""
    if isinstance(value, timedelta):
        seconds = value.total_seconds()
    elif isinstance(value, (int, float)):
        seconds = float(value)
    else:
        text = str(value)
        match = _DURATION.match(text)
        if match:
            seconds = float(match.group(1)) * _UNIT_SECONDS[match.group(2)]
        elif re.fullmatch(r"\d+:\d{1,2}:\d{1,2}:\d{1,2}", text.strip()):
            days, hours, minutes, secs = (int(p) for p in text.strip().split(":"))
            seconds = ((days * 24 + hours) * 60 + minutes) * 60 + secs
        else:
            raise ValueError(f"time must be seconds, '12min', '1.5h', '90s' or 'DD:HH:MM:SS', got {value!r}")
    if not math.isfinite(seconds) or seconds <= 0:
        raise ValueError(f"time must be a positive duration, got {value!r}")
    return timedelta(seconds=seconds)


def train(
    module: pl.LightningModule,
    data: LightningDataModule,
    epochs: int | None = None,
    *,
    time: float | str | timedelta | None = None,
    name: str = "ssm",
    save_dir: str | Path = "runs",
    callbacks: Sequence[pl.Callback] = (),
    ckpt_path: str | Path | None = None,
    **trainer_options: Any,
) -> pl.Trainer:
    """A Lightning fit with this project's console, checkpoints and logger."""
    if epochs is None and time is None:
        raise ValueError("give a training budget: epochs=..., time=... (e.g. '12min'), or both")
    if epochs is not None and (int(epochs) != epochs or epochs < 1):
        raise ValueError(f"epochs must be a whole number >= 1, got {epochs!r}")
    budget = None if time is None else parse_duration(time)
    quiet_lightning()
    show_package_log()
    options = {
        "accelerator": "auto",
        "devices": 1,
        "log_every_n_steps": 5,
        "check_val_every_n_epoch": 10,
        **trainer_options,
    }
    if "logger" not in options:
        options["logger"] = TensorBoardLogger(save_dir=str(save_dir), name=name)
    elif options["logger"] is False:
        options.setdefault("default_root_dir", str(Path(save_dir) / name))
    callbacks = [EpochCheckpoint(), *callbacks]
    if options.get("enable_progress_bar", True):
        callbacks.append(RunProgressBar())
    trainer = pl.Trainer(
        max_epochs=-1 if epochs is None else int(epochs), max_time=budget, callbacks=callbacks, **options
    )
    try:
        trainer.fit(module, datamodule=data, ckpt_path=None if ckpt_path is None else str(ckpt_path))
    except SystemExit:
        if trainer.state.status == TrainerStatus.INTERRUPTED:  # Lightning's answer to Ctrl-C
            last = getattr(trainer.checkpoint_callback, "last_model_path", "")
            resume = f"; resume with fit(..., ckpt_path={str(last)!r})" if last else ""
            raise KeyboardInterrupt(f"training interrupted at epoch {trainer.current_epoch}{resume}") from None
        raise
    return trainer
