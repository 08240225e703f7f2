"""What trained SSMs draw of their own training trajectories: each rolled out from its first shooting node.

Run from the repository root::

    python studies/ssm_rollouts/ssm_rollouts.py --ssm runs/quad/<version>/checkpoints/last.ckpt pretrained/quad.ckpt \\
        --data-config configs/data/quad.yaml [--trajectories 4] [--out studies/ssm_rollouts/ssm_rollouts_quad.md]

The picture TensorBoard shows during training (``val/reconstruction``), for several checkpoints of the same data side
by side, kept as a file: for ``--trajectories`` training trajectories evenly spaced over the data config's training
set (its cache, generated there if missing: the nodes belong to those trajectories), the first shooting node is
rolled out by ``f`` over the whole trajectory and drawn by ``g`` (the SSM's ``validation_step``), and compared with
the clean frames. This is the fit of what the SSM trained on, not a forecast of unseen sequences: it shows what f and
g have learned to draw (e.g. the bends of the quadruple pendulum's chain), apart from any encoder. Writes a table
(MSE against the clean frames, over the first and second half of the frames and all of them; SSIM over all) and, per SSM, a figure
(rows: measured, clean, the SSM's rollout) beside ``--out``.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np
import torch
from PIL import Image

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from benchmarks.report import provenance, write  # noqa: E402
from experiments.configs import build_datamodule  # noqa: E402
from ssm_ms.drawing import reconstruction_grid  # noqa: E402
from ssm_ms.forecasting.metrics import ssim_per_sequence  # noqa: E402
from ssm_ms.loading import load_ssm  # noqa: E402


def rollouts(ssm_path: str, item: dict[str, torch.Tensor]) -> tuple[torch.Tensor, int]:
    """The SSM's rollout of each trajectory of ``item`` from its first node (``[B, T, ...]``) and its trained epochs."""
    model, checkpoint = load_ssm(ssm_path)
    model.eval()
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # validation_step logs, and no trainer is attached
        out = model.validation_step(item, 0)
    return out["y_hat"], int(checkpoint.get("epoch", -1)) + 1


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ssm", nargs="+", required=True, help="SSM checkpoints trained on --data-config's data")
    parser.add_argument("--data-config", default="configs/data/quad.yaml")
    parser.add_argument("--trajectories", type=int, default=4)
    parser.add_argument("--out", default="studies/ssm_rollouts/ssm_rollouts_quad.md")
    opts = parser.parse_args(argv)
    for path in (*opts.ssm, opts.data_config):
        if not Path(path).is_file():
            sys.exit(f"error: {path} does not exist (run from the repository root)")
    try:
        dm = build_datamodule(opts.data_config)
    except ValueError as e:
        sys.exit(f"error: {e}")
    dm.prepare_data()
    train = dm.load("train")
    index = np.unique(np.linspace(0, len(train) - 1, opts.trajectories).round().astype(np.int64)).tolist()
    item = train.__getitems__(index)
    if "y_clean" not in item or item["y"].dim() != 5:
        sys.exit("error: --data-config must hold images with clean copies (the pendulum, quad data sets)")
    clean = item["y_clean"]
    t = clean.shape[1]
    halves = {f"frames 1-{t // 2}": slice(0, t // 2), f"frames {t // 2 + 1}-{t}": slice(t // 2, t), "all": slice(0, t)}
    out = Path(opts.out)
    rows = []
    for i, path in enumerate(opts.ssm):
        y_hat, epochs = rollouts(path, item)
        err = {k: (y_hat[:, s] - clean[:, s]).pow(2).mean().item() for k, s in halves.items()}
        err["SSIM, all"] = ssim_per_sequence(y_hat.clamp(0, 1), clean).mean().item()
        grid = reconstruction_grid(item["y"], y_hat, clean, len(index), 10)
        pixels = (grid.clamp(0, 1)[0].numpy() * 255).astype(np.uint8)
        figure = out.with_name(f"{out.stem}_{i}.png")
        figure.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(pixels).resize((pixels.shape[1] * 2, pixels.shape[0] * 2), Image.NEAREST).save(figure)
        rows.append(
            f"| `{path}` | {epochs} | " + " | ".join(f"{v:.4f}" for v in err.values()) + f" | `{figure.name}` |"
        )
        print(rows[-1], flush=True)
    lines = [
        "# What the SSMs draw of their own training trajectories, from the first shooting node",
        "",
        *provenance("studies/ssm_rollouts/ssm_rollouts.py", argv),
        f"- Data: `{opts.data_config}`, training trajectories {index} (of {len(train)}), {t} frames each; each SSM's "
        "first node of each, rolled out by f over all the frames and drawn by g (its validation rollout)",
        "- Scores: MSE against the clean frames (lower is better), and SSIM (the test protocol's; higher is better: "
        "it sees shapes where per-pixel errors barely do); figures: per trajectory the measured frames, the clean "
        "ones and the SSM's, every tenth of the sequence",
        "",
        "| SSM | epochs trained | " + " | ".join(f"MSE, {k}" for k in halves) + " | SSIM, all | figure |",
        "|---|---:|" + "---:|" * (len(halves) + 1) + "---|",
        *rows,
    ]
    write(out, lines)


if __name__ == "__main__":
    main()
