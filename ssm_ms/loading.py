"""A trained :class:`~ssm_ms.module.MultipleShootingModule` read from its checkpoint file (:func:`load_ssm`): what
the forecasters, closed-loop control, export, the studies and the benchmarks start from. What the file holds beside
Lightning's, and the checks of one, are :mod:`ssm_ms.checkpointing`'s."""

from __future__ import annotations

import contextvars
import os
from pathlib import Path

import torch

from ssm_ms.checkpointing import holds_ssm, read_checkpoint
from ssm_ms.module import MultipleShootingModule


def load_ssm(path: str | os.PathLike, map_location: str | torch.device = "cpu") -> tuple[MultipleShootingModule, dict]:
    """Load a trained ``MultipleShootingModule`` (and the raw checkpoint, for its data statistics)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(
            f"the SSM checkpoint {path} does not exist: train the model first (python cli.py fit --config "
            "configs/<experiment>.yaml) and set model.init_args.ssm_checkpoint to its checkpoints/last.ckpt"
        )
    checkpoint = read_checkpoint(path, "the SSM checkpoint")  # weights_only: a foreign file runs no code
    if not holds_ssm(checkpoint):
        kind = checkpoint.get("forecaster") if isinstance(checkpoint, dict) else None
        what = (
            f"a checkpoint of the {kind} baseline"
            if kind
            else "not a checkpoint of a MultipleShootingModule (no shooting nodes in it)"
        )
        raise ValueError(
            f"{path} is {what}: ssm_checkpoint takes the last.ckpt of an SSM run "
            "(python cli.py fit --config configs/<experiment>.yaml)"
        )
    # LightningCLI hands a module it builds its hyperparameters through a context variable; the SSM loaded
    # here, during that construction, must not pick them up: load it in an empty context.
    model = contextvars.Context().run(
        MultipleShootingModule.load_from_checkpoint, path, map_location=map_location, weights_only=False
    )
    model.freeze()
    return model, checkpoint
