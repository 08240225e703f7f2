"""Pretrained checkpoints: a training checkpoint stripped to what inference needs.

    python -m ssm_ms.pretrained runs/pendulum/<version>/checkpoints/last.ckpt pretrained/pendulum.ckpt
    python -m ssm_ms.pretrained runs/pendulum_encoder/<version>/checkpoints/last.ckpt \\
        pretrained/pendulum_encoder.ckpt --ssm-checkpoint pretrained/pendulum.ckpt \
        --results-dir runs/pretrained --half

What is dropped: the optimizer states, the learning-rate schedulers, the loops' progress and the callbacks'
states (a stripped checkpoint tests, predicts and exports; it does not resume training). What is kept: the
weights (``state_dict``), the hyperparameters that rebuild the module, the DataModule's saved state (its
generator parameters), Lightning's version, epoch and step.

``--ssm-checkpoint`` rewrites the path an encoder or filter checkpoint records for its SSM (a training
run's ``runs/...`` path does not exist in a fresh clone), so ``--ckpt_path`` of the stripped file loads
the pretrained SSM beside it. ``--results-dir`` sets where a test of the stripped file writes its results
and figures (``--ckpt_path`` restores the checkpoint's own settings over the command line's, so a
pretrained model would otherwise rewrite the committed ``results/`` files it came from). ``--half`` stores the large floating-point tensors (at least
:data:`HALF_MIN_NUMEL` values: the encoder's 1024-unit LSTM) in float16, halving the file; they load
back into the module's float32 parameters (rounded to float16's 11 significant bits, a relative error of
at most 2**-11); the results file of a pretrained model says how much that moves the test scores.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import torch

from ssm_ms.checkpointing import read_checkpoint

DROPPED = ("optimizer_states", "lr_schedulers", "loops", "callbacks")
HALF_MIN_NUMEL = 1 << 16
HALF_KEY = "ssm_ms_float16"  # names of the tensors stored in float16 (for whoever reads the file)


def strip(
    ckpt: dict[str, Any], ssm_checkpoint: str | None = None, half: bool = False, results_dir: str | None = None
) -> dict[str, Any]:
    """A copy of a Lightning checkpoint dict without training state (see the module doc)."""
    out = {key: value for key, value in ckpt.items() if key not in DROPPED}
    state = dict(out["state_dict"])
    if half:
        narrowed = [k for k, v in state.items() if v.is_floating_point() and v.numel() >= HALF_MIN_NUMEL]
        for key in narrowed:
            state[key] = state[key].to(torch.float16)
        out[HALF_KEY] = narrowed
    out["state_dict"] = state
    hparams = dict(out.get("hyper_parameters") or {})
    if ssm_checkpoint is not None:
        if "ssm_checkpoint" not in hparams:
            raise ValueError("--ssm-checkpoint is for encoder / filter checkpoints; this one records no SSM")
        hparams["ssm_checkpoint"] = str(ssm_checkpoint)
    if results_dir is not None:
        if "results_dir" not in hparams:
            raise ValueError("--results-dir is for forecasters (encoder, filter, baseline); this checkpoint writes no results")
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
    parser.add_argument("--half", action="store_true", help=f"large tensors (>= {HALF_MIN_NUMEL} values) in float16")
    opts = parser.parse_args(argv)
    try:
        ckpt = read_checkpoint(opts.source, "source")
        out = strip(ckpt, opts.ssm_checkpoint, opts.half, opts.results_dir)
    except (OSError, ValueError) as err:  # CheckpointError is a ValueError
        parser.exit(2, f"error: {err}\n")
    Path(opts.target).parent.mkdir(parents=True, exist_ok=True)
    torch.save(out, opts.target)
    size = Path(opts.target).stat().st_size
    print(f"{opts.target}: {size / 1e6:.2f} MB (from {Path(opts.source).stat().st_size / 1e6:.2f} MB)")


if __name__ == "__main__":
    main()
