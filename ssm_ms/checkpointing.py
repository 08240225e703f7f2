"""Checkpoints: ``last.ckpt`` at the end of every training epoch, and reading a checkpoint safely.

Lightning's ``ModelCheckpoint(every_n_epochs=1)`` saves after validation whenever a validation loop
exists, so with ``check_val_every_n_epoch: 10`` a crash loses up to ten epochs. :class:`EpochCheckpoint`
saves at the end of every *training* epoch, whatever the validation cadence, and never saves a
half-finished epoch (an interrupted or crashed run keeps the last completed one, which resumes as if
uninterrupted). Every shipped config that trains uses it.

A :class:`~ssm_ms.module.MultipleShootingModule`'s checkpoint holds more than Lightning's: the functions of the last
section write and read it (its data state, last fit term, seed and, built in Python, its networks) and refuse a
checkpoint of another configuration; the module's checkpoint hooks call them, :func:`ssm_ms.loading.load_ssm` loads
one.
"""

from __future__ import annotations

import hashlib
import io
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


# ---------------------------------------------------------------------------- a MultipleShootingModule's checkpoint
# Beside Lightning's: the data state of a model saved without its DataModule, the last epoch's fit term, the seed
DATA_STATE_KEY = "data_state"
FIT_MSE_KEY = "fit_mse"
SEED_KEY = "seed"  # the seed its fit ran with (seed_everything; None: none set)
# Hyperparameters that fix the shapes of the parameters: a checkpoint must agree on them.
STRUCTURAL_HPARAMS = (
    "state_dim",
    "num_trajectories",
    "n_nodes",
    "f",
    "g",
    "node_optimizer",
    "constraint",
    "node_encoder",
)
NETWORKS = ("f", "g", "node_encoder")  # the modules a model built in Python carries in its checkpoints


def holds_ssm(checkpoint: Mapping[str, Any]) -> bool:
    """Whether a checkpoint holds a ``MultipleShootingModule``: its shooting nodes, free (a table) or amortised (an
    encoder)."""
    state = checkpoint.get("state_dict", {}) if isinstance(checkpoint, Mapping) else {}
    return "nodes.weight" in state or any(k.startswith("node_encoder.") for k in state)


def datamodule_state(checkpoint: Mapping[str, Any]) -> tuple[str, dict] | None:
    """``(key, state)`` of the DataModule saved in a checkpoint (normalisation and data identity)."""
    for key, value in checkpoint.items():
        if isinstance(value, dict) and "generator_params" in value and "name" in value:
            return key, value
    return None


def write_ssm_extras(
    checkpoint: dict[str, Any],
    fit_mse: float | None,
    seed: int | None,
    data_state: dict[str, Any] | None,
    networks: dict[str, Any] | None,
) -> None:
    """Add to an SSM's checkpoint its last epoch's fit term, its fit's seed, its data state where the checkpoint was
    saved without its DataModule, and ``networks`` (``{name: module}`` of :data:`NETWORKS`) where it was built in
    Python (``None``: built by the CLI, its config names them), so that the checkpoint reloads on its own."""
    if fit_mse is not None:
        checkpoint[FIT_MSE_KEY] = fit_mse
    if seed is not None:
        checkpoint[SEED_KEY] = seed
    if data_state is not None and datamodule_state(checkpoint) is None:  # saved without its DataModule
        checkpoint[DATA_STATE_KEY] = data_state
    if networks is not None:
        buffer = io.BytesIO()  # as bytes: the checkpoint itself stays loadable with weights_only=True
        torch.save(networks, buffer)
        checkpoint["networks"] = buffer.getvalue()


def ssm_extras(checkpoint: Mapping[str, Any]) -> dict[str, Any]:
    """What an SSM's checkpoint holds of it beyond its weights and hyperparameters, those it has of ``data_state``
    (its DataModule's or its own), ``fit_mse`` and ``seed``: the names of the model's attributes."""
    extras: dict[str, Any] = {}
    saved_data = datamodule_state(checkpoint)
    if saved_data is not None:
        extras["data_state"] = saved_data[1]
    if checkpoint.get(FIT_MSE_KEY) is not None:
        extras["fit_mse"] = float(checkpoint[FIT_MSE_KEY])
    if checkpoint.get(SEED_KEY) is not None:
        extras["seed"] = int(checkpoint[SEED_KEY])
    return extras


def saved_networks(checkpoint: Mapping[str, Any]) -> dict[str, Any]:
    """``{name: module}`` of the networks pickled in the checkpoint of a model built in Python (empty: none). Unpickled
    with ``weights_only=False``: for a file the caller trusts."""
    if "networks" not in checkpoint:
        return {}
    networks = torch.load(io.BytesIO(checkpoint["networks"]), map_location="cpu", weights_only=False)
    return {name: networks.get(name) for name in NETWORKS}


def keep_network_config(hparams: dict[str, Any], checkpoint: Mapping[str, Any]) -> None:
    """Built by the CLI, f and g are in the saved config: keep it in ``hparams`` (Lightning rebuilds the module
    outside the CLI, where they would be dropped), so that a re-saved checkpoint still describes them."""
    saved = checkpoint.get("hyper_parameters", {})
    if isinstance(saved.get("f"), Mapping) and "f" not in hparams:
        for key in ("_class_path", "_instantiator", *NETWORKS):
            if key in saved:
                hparams[key] = saved[key]


def refuse_baseline(checkpoint: Mapping[str, Any]) -> None:
    """A baseline's checkpoint given where an SSM's belongs: one message naming it."""
    if checkpoint.get("forecaster"):
        raise ValueError(
            f"the checkpoint is a {checkpoint['forecaster']}'s (a baseline), not an SSM's: resume an SSM from "
            "the last.ckpt of its own run (python cli.py fit --config configs/<experiment>.yaml)"
        )


def _structure(value: Any) -> Any:
    """What of a hyperparameter must match between a checkpoint and a run (a network: its class)."""
    if isinstance(value, Mapping):
        return value.get("class_path", value.get("_class_path", dict(value)))
    return value


def check_configuration(checkpoint: Mapping[str, Any], hparams: Mapping[str, Any], own: Mapping[str, Any]) -> None:
    """Refuse a checkpoint of another configuration than the model's (its ``hparams`` and ``own`` state dict) with a
    message that says what differs."""
    state = checkpoint.get("state_dict", {})
    problems = []
    saved = checkpoint.get("hyper_parameters", {})
    for key in STRUCTURAL_HPARAMS:
        if key in saved and key in hparams and _structure(saved[key]) != _structure(hparams[key]):
            problems.append(f"{key}: checkpoint {_structure(saved[key])!r}, this run {_structure(hparams[key])!r}")
    for key, value in state.items():
        if key in own and tuple(own[key].shape) != tuple(value.shape):
            problems.append(f"{key}: checkpoint shape {tuple(value.shape)}, this model {tuple(own[key].shape)}")
    missing = sorted(set(own) - set(state))
    unexpected = sorted(set(state) - set(own))
    if missing:
        problems.append(f"missing from the checkpoint: {missing[:8]}")
    if unexpected:
        problems.append(f"not in this model: {unexpected[:8]}")
    if problems:
        raise ValueError(
            "the checkpoint was trained with another configuration:\n  - "
            + "\n  - ".join(problems)
            + "\nResume with the config saved beside the checkpoint (config.yaml in its run folder), "
            "or start a fresh run without --ckpt_path."
        )
