"""Checkpoints: ``last.ckpt`` at the end of every training epoch, and reading a checkpoint safely.

Lightning's ``ModelCheckpoint(every_n_epochs=1)`` saves after validation whenever a validation loop
exists, so with ``check_val_every_n_epoch: 10`` a crash loses up to ten epochs. :class:`EpochCheckpoint`
saves at the end of every *training* epoch, whatever the validation cadence, and never saves a
half-finished epoch (an interrupted or crashed run keeps the last completed one, which resumes as if
uninterrupted). Every shipped config that trains uses it.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from lightning.pytorch.callbacks import ModelCheckpoint


class EpochCheckpoint(ModelCheckpoint):
    """``last.ckpt`` (and ``epoch=N-step=M.ckpt``) written at the end of every training epoch.

    Args:
        dirpath: where to write (default: the logger's ``<save_dir>/<name>/<version>/checkpoints``).
        every_n_epochs: write every this many epochs (1: a crash loses at most the epoch under way).
    """

    def __init__(self, dirpath: str | None = None, every_n_epochs: int = 1):
        if every_n_epochs < 1:
            raise ValueError(f"every_n_epochs must be >= 1, got {every_n_epochs}")
        super().__init__(
            dirpath=dirpath,
            save_last=True,
            every_n_epochs=every_n_epochs,
            save_on_train_epoch_end=True,  # not after validation, which may run only every k epochs
            save_on_exception=False,  # keep the last *completed* epoch: a half epoch does not resume exactly
        )


INT8_KEY = "ssm_ms_int8"  # {name: per-row scales} of the weights a pretrained file stores in int8


def restore_float_weights(checkpoint: dict[str, Any]) -> dict[str, Any]:
    """Turn the int8 weights of a file written by ``python -m ssm_ms.pretrained --weights int8`` back into
    float32 (in place; a checkpoint without them is left alone), and return ``checkpoint``.

    Each such tensor ``q`` is stored with its scales shaped to broadcast (one per row): the weight is
    ``q * scale``. Every loader calls this before the weights reach a module: :func:`read_checkpoint`
    and the modules' ``on_load_checkpoint`` (Lightning's ``--ckpt_path`` and ``load_from_checkpoint``).
    """
    scales = checkpoint.pop(INT8_KEY, None)
    if scales:
        state = dict(checkpoint["state_dict"])
        for name, scale in scales.items():
            state[name] = state[name].to(torch.float32) * scale
        checkpoint["state_dict"] = state
    return checkpoint


SSM_DIGEST_KEY = "ssm_ms_ssm_digest"  # a forecaster file stored without its SSM: the digest of the SSM it needs


def state_digest(state: Mapping[str, torch.Tensor]) -> str:
    """A fingerprint of a module's weights as the module holds them (names, shapes, values; floating-point
    tensors as float32, so a file stored in float16 and the module it loads into agree)."""
    digest = hashlib.sha256()
    for name in sorted(state):
        value = state[name].detach().cpu()
        value = value.to(torch.float32) if value.is_floating_point() else value
        digest.update(f"{name}:{tuple(value.shape)}:{value.dtype}".encode())
        digest.update(value.contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()


class CheckpointError(ValueError):
    """A file given as a checkpoint cannot be read as one."""


def read_checkpoint(path: str | Path, what: str = "the checkpoint", restore: bool = True) -> dict[str, Any]:
    """Load a Lightning checkpoint's dictionary with ``weights_only=True`` (no arbitrary code runs), its int8
    weights turned back into float32 (:func:`restore_float_weights`) unless ``restore`` is false.

    Raises :class:`CheckpointError` naming the file for a missing, truncated or foreign file; never
    suggests unsafe loading.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(
            f"{what} {path} does not exist (or is not a file): give the last.ckpt of a run, "
            "e.g. runs/<name>/version_N/checkpoints/last.ckpt"
        )
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except Exception as err:
        raise CheckpointError(
            f"{what} {path} is not a readable checkpoint (truncated, or not a file written by this project's "
            f"training: {type(err).__name__}); give the last.ckpt of a completed epoch, "
            "e.g. runs/<name>/version_N/checkpoints/last.ckpt"
        ) from None
    if not isinstance(checkpoint, dict) or "state_dict" not in checkpoint:
        raise CheckpointError(
            f"{what} {path} is a torch file but not a Lightning checkpoint (no state_dict): give the last.ckpt "
            "of a run, e.g. runs/<name>/version_N/checkpoints/last.ckpt"
        )
    return restore_float_weights(checkpoint) if restore else checkpoint


def kept_score(checkpoint: Mapping[str, Any], path: str | os.PathLike | None = None) -> float | None:
    """The score a fit's ``ModelCheckpoint`` kept its best epoch by (e.g. ``val/sim_rmse``), read from a checkpoint it
    wrote; ``None`` where there is none (a fit without such a checkpoint callback), or where ``path`` (the file the
    checkpoint was read from) is not the best epoch's file that callback names (a ``last.ckpt``: the score is
    another epoch's). A stripped file (no best path recorded) keeps its score."""
    scores = [
        float(state["best_model_score"])
        for key, state in checkpoint.get("callbacks", {}).items()
        if key.startswith("ModelCheckpoint")
        and state.get("best_model_score") is not None
        and (path is None or not state.get("best_model_path") or Path(state["best_model_path"]).name == Path(path).name)
    ]
    return min(scores, default=None)
