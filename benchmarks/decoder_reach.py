"""What an SSM's decoder ``g`` can draw, against what the pipeline's states make it draw.

Run from the repository root::

    python benchmarks/decoder_reach.py --encoder pretrained/quad_encoder.ckpt --data-config configs/data/quad.yaml \\
        [--sequences 8] [--steps 600] [--out benchmarks/results/decoder_reach_quad.md]

On the first ``--sequences`` test sequences of the data config (generated in a temporary folder, with 40 training
sequences for the mean frame), the encoder's forecast (its estimate of the given frames, then ``f``'s prediction,
decoded by ``g``) is compared with the clean frames, beside the same frozen ``g`` drawing from codes fitted freely
to each clean frame (an oracle: one state per frame, Adam, lr 0.05 in units of the states' spread, ``--steps``
steps started at the pipeline's own state of that frame, the best step kept) and the mean training frame. The free
codes are a local fit, so their error bounds from above what ``g`` can draw of the truth: where they draw the frames
far better than the pipeline's states, ``g`` is not what loses the picture, the states are (the encoder's estimate,
or ``f``'s rollout). (Fitted to the noisy frames instead, the codes draw the noise too.) Writes a table and a figure
(rows: the clean frames, the model's first predicted frames, ``g`` from the free codes) beside ``--out``.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
import yaml
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.report import provenance, write  # noqa: E402
from ssm_ms.inference.encoder_module import StateEncoderModule  # noqa: E402


def fitted_codes(g: torch.nn.Module, frames: torch.Tensor, start: torch.Tensor, steps: int) -> torch.Tensor:
    """``g(z)`` for codes ``z [N, d]`` fitted to ``frames [N, *obs]`` by Adam on the squared error (``g`` frozen),
    started at ``start``, each coordinate moved in units of its spread over ``start`` (the states' own scale); the
    codes of the step with the lowest error, so never worse than ``start``'s."""
    scale = start.std(0, keepdim=True).clamp_min(1e-6)
    delta = torch.zeros_like(start, requires_grad=True)
    opt = torch.optim.Adam([delta], lr=0.05)
    best, best_loss = None, float("inf")
    for _ in range(steps + 1):
        drawn = g(start + scale * delta)
        loss = torch.nn.functional.mse_loss(drawn, frames)
        if loss.item() < best_loss:
            best, best_loss = drawn.detach(), loss.item()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return best


def strip(frames: torch.Tensor, pick: list[int]) -> np.ndarray:
    """The first channel of ``frames[pick]`` side by side."""
    return np.concatenate([frames[i, 0].numpy() for i in pick], axis=1)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--encoder", default="pretrained/quad_encoder.ckpt", help="an encoder stage's checkpoint")
    parser.add_argument("--data-config", default="configs/data/quad.yaml")
    parser.add_argument("--sequences", type=int, default=8)
    parser.add_argument("--steps", type=int, default=600, help="Adam steps of the free codes")
    parser.add_argument("--out", default="benchmarks/results/decoder_reach_quad.md")
    opts = parser.parse_args(argv)
    torch.manual_seed(0)

    for path in (opts.encoder, opts.data_config):
        if not Path(path).is_file():
            sys.exit(
                f"error: {path} does not exist (run from the repository root; --encoder takes an encoder stage's "
                "checkpoint, --data-config a file of configs/data/)"
            )
    enc = StateEncoderModule.load_from_checkpoint(opts.encoder, map_location="cpu").eval()
    g, d = enc.ssm.g.requires_grad_(False), enc.ssm.hparams.state_dim
    k = enc.hparams.n_filter
    spec = yaml.safe_load(Path(opts.data_config).read_text())
    module, name = spec["class_path"].rsplit(".", 1)
    with tempfile.TemporaryDirectory() as tmp:
        args = {**spec["init_args"], "n_train": 40, "n_test": opts.sequences, "data_dir": tmp}
        dm = getattr(importlib.import_module(module), name)(**args)
        dm.prepare_data()
        item = dm.load("test").__getitems__(list(range(opts.sequences)))
        train = dm.load("train").__getitems__(list(range(40)))
    if "y_clean" not in item:
        sys.exit(f"error: the data of {opts.data_config} hold no clean frames ('y_clean'): this measure needs them")
    y, clean = item["y"], item["y_clean"]
    mean = train["y_clean"].mean(dim=(0, 1))
    with torch.no_grad():
        forecast = enc.forecast(y[:, :k], y.shape[1] - k)
    obs = tuple(y.shape[2:])
    parts = {
        f"the last 10 given frames ({k - 9}-{k})": (forecast.filtered[:, k - 10 :], slice(k - 10, k)),
        f"the first 5 predicted ({k + 1}-{k + 5})": (forecast.predicted[:, :5], slice(k, k + 5)),
        f"all {y.shape[1] - k} predicted": (forecast.predicted, slice(k, y.shape[1])),
    }
    lines = [
        "# What g can draw, against what the pipeline's states make it draw",
        "",
        *provenance("benchmarks/decoder_reach.py", argv),
        f"- Model: the encoder `{opts.encoder}` over its SSM; data: `{opts.data_config}`, the first "
        f"{opts.sequences} test sequences, {k} frames given",
        f"- Free codes: one {d}-d state per frame fitted to the clean frame, the frozen g, Adam lr 0.05 in units of "
        f"the states' spread, {opts.steps} steps from the pipeline's own state of the frame, the best step kept (a "
        "local fit: an upper bound on the error of what g can draw)",
        "",
        "MSE against the clean frames (lower is better):",
        "",
        "| frames | the model (encoder, then f) | g from free codes | the mean training frame |",
        "|---|---:|---:|---:|",
    ]
    picture = None
    for label, (model_frames, span) in parts.items():
        truth = clean[:, span].reshape(-1, *obs)
        free = fitted_codes(g, truth, forecast.states[:, span].reshape(-1, d), opts.steps)
        own = model_frames.reshape(-1, *obs)
        mse = [torch.nn.functional.mse_loss(a, truth).item() for a in (own, free, mean.expand_as(truth))]
        lines.append(f"| {label} | {mse[0]:.5f} | {mse[1]:.5f} | {mse[2]:.5f} |")
        if picture is None and "first 5 predicted" in label:
            pick = list(range(0, len(truth), max(1, len(truth) // 8)))
            picture = np.concatenate([strip(t, pick) for t in (truth, own, free)], 0)
    figure = Path(opts.out).with_suffix(".png")
    lines += [
        "",
        f"Figure `{figure.name}`: the clean frames, the model's first predicted frames, g from the free codes.",
    ]
    write(opts.out, lines)
    image = Image.fromarray((np.clip(picture, 0, 1) * 255).astype(np.uint8))
    image.resize((image.width * 2, image.height * 2), Image.NEAREST).save(figure)


if __name__ == "__main__":
    main()
