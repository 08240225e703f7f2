"""What an SSM's decoder ``g`` can draw, against what the pipeline's states make it draw.

Run from the repository root::

    python studies/decoder_reach/decoder_reach.py --encoder pretrained/quad_encoder.ckpt --data-config configs/data/quad.yaml \\
        [--sequences 8] [--steps 600] [--rollout] [--out studies/decoder_reach/decoder_reach_quad.md]

On the first ``--sequences`` test sequences of the data config (generated in a temporary folder, with 40 training
sequences for the mean frame), the encoder's forecast (its estimate of the given frames, then ``f``'s prediction,
decoded by ``g``) is compared with the clean frames, beside the same frozen ``g`` drawing from codes fitted freely
to each clean frame (an oracle: one state per frame, Adam, lr 0.05 in units of the states' spread, ``--steps``
steps started at the pipeline's own state of that frame, the best step kept) and the mean training frame. The free
codes are a local fit, so their error bounds from above what ``g`` can draw of the truth: where they draw the frames
far better than the pipeline's states, ``g`` is not what loses the picture, the states are (the encoder's estimate,
or ``f``'s rollout). (Fitted to the noisy frames instead, the codes draw the noise too.) With ``--rollout``, two more
columns: one state per sequence at its first frame, rolled out by ``f`` and drawn by ``g``, fitted (the same way,
through ``f`` and ``g``, on the SSM's own loss, started at the pipeline's state of the first frame) to the given
frames alone (state inference done by optimisation: how far the forecast from such a state goes), and to all the
frames (what ``f`` and ``g`` together can draw of the whole sequence: where it draws the predicted frames well and the
given-frames fit does not, the given frames do not determine the state's future). Data without clean frames (Moving
MNIST: none are noisy) are compared with the frames as measured. Writes a table and a figure (rows: the clean frames,
the model's first predicted frames, ``g`` from the free codes) beside ``--out``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from benchmarks.report import provenance, write  # noqa: E402
from experiments.configs import build_datamodule  # noqa: E402
from ssm_ms.inference.encoder_module import StateEncoderModule  # noqa: E402
from ssm_ms.training.shooting import decode, loss_function, rollout  # noqa: E402


def fitted_codes(draw, frames: torch.Tensor, start: torch.Tensor, steps: int, loss=F.mse_loss) -> torch.Tensor:
    """``draw(z)`` for codes ``z [N, d]`` fitted to ``frames`` (what ``draw`` outputs) by Adam on ``loss`` (``draw``
    frozen), started at ``start``, each coordinate moved in units of its spread over ``start`` (the states' own scale);
    the drawing of the step with the lowest loss, so never worse than ``start``'s."""
    scale = start.std(0, keepdim=True).clamp_min(1e-6)
    delta = torch.zeros_like(start, requires_grad=True)
    opt = torch.optim.Adam([delta], lr=0.05)
    best, best_loss = None, float("inf")
    for _ in range(steps + 1):
        drawn = draw(start + scale * delta)
        value = loss(drawn, frames)
        if value.item() < best_loss:
            best, best_loss = drawn.detach(), value.item()
        opt.zero_grad()
        value.backward()
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
    parser.add_argument("--rollout", action="store_true", help="also fit one state per sequence through f and g")
    parser.add_argument("--out", default="studies/decoder_reach/decoder_reach_quad.md")
    opts = parser.parse_args(argv)
    torch.manual_seed(0)

    for path in (opts.encoder, opts.data_config):
        if not Path(path).is_file():
            sys.exit(
                f"error: {path} does not exist (run from the repository root; --encoder takes an encoder stage's "
                "checkpoint, --data-config a file of configs/data/)"
            )
    enc = StateEncoderModule.load_from_checkpoint(opts.encoder, map_location="cpu").eval()
    enc.requires_grad_(False)
    f, g, d = enc.ssm.f, enc.ssm.g, enc.ssm.hparams.state_dim
    k = enc.hparams.n_filter
    with tempfile.TemporaryDirectory() as tmp:
        try:
            dm = build_datamodule(opts.data_config, n_train=40, n_test=opts.sequences, data_dir=tmp)
        except ValueError as e:
            sys.exit(f"error: {e}")
        dm.prepare_data()
        item = dm.load("test").__getitems__(list(range(opts.sequences)))
        train = dm.load("train").__getitems__(list(range(40)))
    truth = "clean" if "y_clean" in item else "measured"  # data without noise (Moving MNIST) have no clean copy
    y, clean = item["y"], item.get("y_clean", item["y"])
    mean = train.get("y_clean", train["y"]).mean(dim=(0, 1))
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
        *provenance("studies/decoder_reach/decoder_reach.py", argv),
        f"- Model: the encoder `{opts.encoder}` over its SSM; data: `{opts.data_config}`, the first "
        f"{opts.sequences} test sequences, {k} frames given",
        f"- Free codes: one {d}-d state per frame fitted to the {truth} frame, the frozen g, Adam lr 0.05 in units of "
        f"the states' spread, {opts.steps} steps from the pipeline's own state of the frame, the best step kept (a "
        "local fit: an upper bound on the error of what g can draw)",
    ]
    columns = ["the model (encoder, then f)", "g from free codes"]
    drawn = {}  # columns with one drawing of every frame [N, T, *obs]
    if opts.rollout:
        whole, fit = y.shape[1], loss_function(enc.ssm.hparams.loss)
        start = forecast.states[:, 0]

        def through_f(s: torch.Tensor) -> torch.Tensor:
            return decode(g, rollout(f, s, whole))

        given = "f from one state fitted to the given frames"
        drawn[given] = fitted_codes(through_f, y, start, opts.steps, lambda a, b: fit(a[:, :k], b[:, :k]))
        drawn["f from one state fitted to all frames"] = fitted_codes(through_f, clean, start, opts.steps, fit)
        columns += list(drawn)
        lines.append(
            f"- One state per sequence at its first frame, rolled out by f and drawn by g, fitted on the SSM's loss "
            f"({enc.ssm.hparams.loss}) the same way from the pipeline's state of the first frame: to the {k} given "
            f"frames as measured (inference by optimisation), or to all {whole} {truth} frames (what f and g can draw "
            "of the whole sequence)"
        )
    columns.append("the mean training frame")
    lines += [
        "",
        f"MSE against the {truth} frames (lower is better):",
        "",
        "| frames | " + " | ".join(columns) + " |",
        "|---|" + "---:|" * len(columns),
    ]
    picture = None
    for label, (model_frames, span) in parts.items():
        truth_frames = clean[:, span].reshape(-1, *obs)
        free = fitted_codes(g, truth_frames, forecast.states[:, span].reshape(-1, d), opts.steps)
        own = model_frames.reshape(-1, *obs)
        candidates = [own, free, *(a[:, span].reshape(-1, *obs) for a in drawn.values()), mean.expand_as(own)]
        mse = [F.mse_loss(a, truth_frames).item() for a in candidates]
        lines.append(f"| {label} | " + " | ".join(f"{v:.5f}" for v in mse) + " |")
        if picture is None and "first 5 predicted" in label:
            pick = list(range(0, len(truth_frames), max(1, len(truth_frames) // 8)))
            picture = np.concatenate([strip(t, pick) for t in (truth_frames, own, free)], 0)
    figure = Path(opts.out).with_suffix(".png")
    lines += [
        "",
        f"Figure `{figure.name}`: the {truth} frames, the model's first predicted frames, g from the free codes.",
    ]
    write(opts.out, lines)
    image = Image.fromarray((np.clip(picture, 0, 1) * 255).astype(np.uint8))
    image.resize((image.width * 2, image.height * 2), Image.NEAREST).save(figure)


if __name__ == "__main__":
    main()
