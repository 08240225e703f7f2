"""Pretrained checkpoints: a training checkpoint stripped to what inference needs.

    python -m ssm_ms.pretrained runs/pendulum/<version>/checkpoints/last.ckpt pretrained/pendulum.ckpt
    python -m ssm_ms.pretrained runs/pendulum_encoder/<version>/checkpoints/last.ckpt \\
        pretrained/pendulum_encoder.ckpt --ssm-checkpoint pretrained/pendulum.ckpt \
        --results-dir runs/pretrained --weights int8

What is dropped: the optimizer states, the learning-rate schedulers, the loops' progress and the callbacks'
states but the record of how the file was chosen (a stripped checkpoint tests, predicts and exports; it does not
resume training). What is kept: the weights (``state_dict``), the hyperparameters that rebuild the module, the
DataModule's saved state (its generator parameters), Lightning's version, epoch and step, and of the callbacks the
``ModelCheckpoint``'s score of the kept epoch and the ``Timer``'s elapsed time (:data:`KEPT_CALLBACKS`: what a
benchmark's results file says of the fit).

``--ssm-checkpoint`` rewrites the path an encoder or filter checkpoint records for its SSM (a training
run's ``runs/...`` path does not exist in a fresh clone), so ``--ckpt_path`` of the stripped file loads
the pretrained SSM beside it; the SSM's weights then leave the file (they are that SSM file's: stored
once), once that file is checked to hold them, and the file records the SSM's
:func:`~ssm_ms.checkpointing.state_digest`, which loading checks
(:meth:`ssm_ms.inference.ssm_forecaster.SSMForecaster.on_load_checkpoint`). ``--results-dir`` sets where a
test of the stripped file writes its results and figures (``--ckpt_path`` restores the checkpoint's own
settings over the command line's, so a pretrained model would otherwise rewrite the committed
``results/`` files it came from).

``--weights`` sets how the large floating-point tensors (at least :data:`NARROW_MIN_NUMEL` values: the
encoder's 1024-unit LSTM) are stored: ``float32`` (as trained), ``float16`` (half the size;
rounded to float16's 11 significant bits, a relative error of at most 2**-11) or ``int8`` (a quarter; one
float32 scale per row, ``max |row| / 127``, so each weight moves by at most half a step, ``max |row| / 254``;
a 1-D tensor is one row). Without ``--weights`` a file keeps its source's storage (:func:`stored_as`): a
training checkpoint stays float32, an int8 file stripped again (say, to record another ``--ssm-checkpoint``)
stays int8, its integers unchanged. They load back into the module's float32 parameters
(:func:`ssm_ms.checkpointing.restore_float_weights`); the results file of a pretrained model says how much
that moves the test scores.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import torch

from ssm_ms.checkpointing import INT8_KEY, SSM_DIGEST_KEY, read_checkpoint, restore_float_weights, state_digest

DROPPED = frozenset({"optimizer_states", "lr_schedulers", "loops", "callbacks"})
KEPT_CALLBACKS = ("ModelCheckpoint", "Timer")  # callback states kept (their keys start so): the kept epoch's record
NARROW_MIN_NUMEL = 1 << 16  # tensors this large or larger are stored as --weights says
HALF_KEY = "ssm_ms_float16"  # names of the tensors stored in float16 (for whoever reads the file)
WEIGHTS = ("float32", "float16", "int8")
SSM_PREFIX = "ssm."  # a forecaster's SSM (SSMForecaster.ssm) within its state_dict


def _row_absmax(w: torch.Tensor) -> torch.Tensor:
    """The largest ``|w|`` of each row (first dimension; a 1-D or 0-D tensor is one row), shaped to broadcast."""
    return w.abs().amax(dim=tuple(range(1, w.ndim)) if w.ndim > 1 else tuple(range(w.ndim)), keepdim=True)


def quantize_rows(weight: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``weight`` as int8 and one float32 scale per row (first dimension; a 1-D tensor is one row), shaped to
    broadcast: ``q * scale`` is within ``max |row| / 254`` of every weight of its row (an all-zero row gets
    scale 1 and stays exact)."""
    w = weight.detach().to(torch.float32)
    scale = _row_absmax(w) / 127
    scale = torch.where(scale > 0, scale, torch.ones_like(scale))
    return torch.round(w / scale).clamp(-127, 127).to(torch.int8), scale


def _same(trained: torch.Tensor, stored: torch.Tensor) -> bool:
    """``stored`` is ``trained`` up to a stripped file's rounding (within 1/200 of each row's largest value:
    float16 and int8 storage are; the weights of another training run are not)."""
    if stored.shape != trained.shape:
        return False
    if not trained.is_floating_point():
        return torch.equal(stored, trained)
    return bool(((stored.to(torch.float32) - trained).abs() <= _row_absmax(trained) / 200).all())


def _without_ssm(state: dict[str, torch.Tensor], ssm_checkpoint: str) -> tuple[dict[str, torch.Tensor], str]:
    """A forecaster's weights without its SSM's, and the digest of the SSM file ``ssm_checkpoint`` that supplies
    them on loading; refused unless that file holds this forecaster's SSM (up to its own storage's rounding)."""
    ssm_state = read_checkpoint(ssm_checkpoint, "--ssm-checkpoint")["state_dict"]
    own = {key[len(SSM_PREFIX) :]: value for key, value in state.items() if key.startswith(SSM_PREFIX)}
    differs = sorted(set(own) ^ set(ssm_state)) or [
        key for key, value in own.items() if not _same(value, ssm_state[key])
    ]
    if differs:
        raise ValueError(
            f"--ssm-checkpoint {ssm_checkpoint} does not hold the SSM this forecaster was trained with (it differs "
            f"in {differs[0]}): give the stripped file of that SSM's own run"
        )
    kept = {key: value for key, value in state.items() if not key.startswith(SSM_PREFIX)}
    return kept, state_digest(ssm_state)


def stored_as(ckpt: dict[str, Any]) -> str:
    """How a checkpoint dict, as read from its file (int8 weights not yet restored), stores its large tensors:
    one of :data:`WEIGHTS`."""
    return "int8" if ckpt.get(INT8_KEY) else "float16" if ckpt.get(HALF_KEY) else "float32"


def strip(
    ckpt: dict[str, Any],
    ssm_checkpoint: str | None = None,
    weights: str | None = None,
    results_dir: str | None = None,
) -> dict[str, Any]:
    """A copy of a Lightning checkpoint dict without training state, its large tensors stored as ``weights``
    says (``None``: as ``ckpt`` stores them; see the module doc). ``ckpt`` is as read from its file."""
    weights = stored_as(ckpt) if weights is None else weights
    if weights not in WEIGHTS:
        raise ValueError(f"weights must be one of {', '.join(WEIGHTS)}, got {weights!r}")
    out = restore_float_weights({key: value for key, value in ckpt.items() if key not in DROPPED | {HALF_KEY}})
    kept = {
        key: {k: v for k, v in value.items() if k in ("best_model_score", "time_elapsed")}
        | ({"best_model_path": ""} if key.startswith("ModelCheckpoint") else {})
        for key, value in (ckpt.get("callbacks") or {}).items()
        if key.startswith(KEPT_CALLBACKS)
    }  # ModelCheckpoint's restore (--ckpt_path) needs a best_model_path: the training run's path means nothing here
    if kept:
        out["callbacks"] = kept
    state = {
        key: value.to(torch.float32) if key in ckpt.get(HALF_KEY, ()) else value
        for key, value in out["state_dict"].items()
    }  # every weight in float32 before it is narrowed again
    if ssm_checkpoint is not None and any(key.startswith(SSM_PREFIX) for key in state):
        state, out[SSM_DIGEST_KEY] = _without_ssm(state, ssm_checkpoint)
    narrowed = [k for k, v in state.items() if v.is_floating_point() and v.numel() >= NARROW_MIN_NUMEL]
    if weights == "float16":
        for key in narrowed:
            state[key] = state[key].to(torch.float16)
        out[HALF_KEY] = narrowed
    elif weights == "int8":
        out[INT8_KEY] = {}
        for key in narrowed:
            state[key], out[INT8_KEY][key] = quantize_rows(state[key])
    out["state_dict"] = state
    hparams = dict(out.get("hyper_parameters") or {})
    if ssm_checkpoint is not None:
        if "ssm_checkpoint" not in hparams:
            raise ValueError("--ssm-checkpoint is for encoder / filter checkpoints; this one records no SSM")
        hparams["ssm_checkpoint"] = str(ssm_checkpoint)
    if results_dir is not None:
        if "results_dir" not in hparams:
            raise ValueError(
                "--results-dir is for forecasters (encoder, filter, baseline); this checkpoint writes no results"
            )
        hparams["results_dir"] = str(results_dir)
        if hparams.get("figures_dir"):
            hparams["figures_dir"] = str(Path(results_dir) / "figures")
    out["hyper_parameters"] = hparams
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("source", help="a training checkpoint (last.ckpt)")
    parser.add_argument("target", help="where the stripped checkpoint goes")
    parser.add_argument("--ssm-checkpoint", help="the path the stripped encoder / filter records for its SSM")
    parser.add_argument("--results-dir", help="where a test of the stripped forecaster writes results (and figures/)")
    parser.add_argument(
        "--weights",
        choices=WEIGHTS,
        help=f"how tensors of >= {NARROW_MIN_NUMEL} values are stored (default: as in the source; "
        "float32 for a training checkpoint)",
    )
    opts = parser.parse_args(argv)
    try:
        ckpt = read_checkpoint(opts.source, "source", restore=False)
        out = strip(ckpt, opts.ssm_checkpoint, opts.weights, opts.results_dir)
    except (OSError, ValueError) as err:  # CheckpointError is a ValueError
        parser.exit(2, f"error: {err}\n")
    Path(opts.target).parent.mkdir(parents=True, exist_ok=True)
    torch.save(out, opts.target)
    size = Path(opts.target).stat().st_size
    print(f"{opts.target}: {size / 1e6:.2f} MB (from {Path(opts.source).stat().st_size / 1e6:.2f} MB)")


if __name__ == "__main__":
    main()
