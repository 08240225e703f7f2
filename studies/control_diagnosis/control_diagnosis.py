"""Where a learned pendulum SSM fails a swing-up: its state estimate and its predictions along successful episodes.

Run from the repository root::

    python studies/control_diagnosis/control_diagnosis.py --ssm-checkpoint runs/pendulum_torque/<version>/checkpoints/last.ckpt \\
        [--encoder-checkpoint runs/pendulum_torque_encoder/<version>/checkpoints/last.ckpt] \
        [--config configs/pendulum_torque_control.yaml] [--out studies/control_diagnosis/control_diagnosis.md]

The controller of ``--config`` plans on the true model with the true state (the upper bound) from the config's
episode starts (``--episodes-of learned``: on the learned model itself, from its estimator's state, as in the closed
loop); its episodes' frames and torques are recorded. Along them, the learned model's estimator (the UKF
with the config's settings, or the encoder of ``--encoder-checkpoint``) reads the frames and torques, and from each
estimated state ``f`` predicts ``k`` steps
ahead under the torques that were applied. Each is read as an angle the way the planner reads it (the distilled angle
of the ink the decoder draws) and compared with the simulator's true angle, binned by how far the pendulum is from
upright. A model fit for control reads the angle well (the estimate) and keeps it over the planner's horizon (the
predictions), above all near upright, where it must catch the pendulum.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from benchmarks.report import provenance, write  # noqa: E402
from experiments.configs import build_datamodule, load_config  # noqa: E402
from ssm_ms.control.cost import upright_error  # noqa: E402
from ssm_ms.control.module import ClosedLoop  # noqa: E402

BANDS = ((0.0, 0.5), (0.5, 1.5), (1.5, 2.5), (2.5, np.pi + 1e-9))  # rad from upright
STEPS = (1, 5, 10)


def wrap(a: np.ndarray) -> np.ndarray:
    return np.abs(np.arctan2(np.sin(a), np.cos(a)))


def closed_loop(config: dict, **changes) -> tuple[ClosedLoop, object]:
    """The config's data module (test split) and ClosedLoop with ``changes`` to its arguments, set up."""
    dm = build_datamodule(config)
    dm.prepare_data()
    dm.setup("test")
    args = {k: v for k, v in config["model"]["init_args"].items() if k != "ssm_checkpoint"}
    loop = ClosedLoop(**{**args, **changes})
    loop.attach(dm)
    return loop, dm


def episodes(loop: ClosedLoop, dm, count: int) -> tuple[list, torch.Tensor, np.ndarray]:
    """``loop``'s episodes (:meth:`ClosedLoop.episodes`: the true model planning on the true state, or a learned
    model on its estimator's state) from the first ``count`` starts of ``dm``'s test split: measurements ``[T+1]``
    of ``[B, ...]``, torques ``[B, T, 1]``, true angles ``[B, T+1]``."""
    start = next(iter(dm.test_dataloader()))["state"][:count, 0].double().numpy()
    run = loop.episodes(start)
    return run["measurements"], run["inputs"], run["states"][..., 0].double().numpy()


@torch.no_grad()
def diagnose(loop: ClosedLoop, frames: list, inputs: torch.Tensor) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """Angles read from the estimates ``[B, T+1]`` and from the ``k``-step predictions (NaN past the end)."""
    periods = inputs.shape[1]
    estimator = loop.estimator()
    means = [estimator.start(frames[0])]
    for t in range(periods):
        means.append(estimator.next(inputs[:, t], frames[t + 1]))

    def angle(x: torch.Tensor) -> np.ndarray:
        sc = loop.features(x)
        return torch.atan2(sc[:, 0], sc[:, 1]).double().numpy()  # (sin, cos) of the angle from hanging

    read = np.stack([angle(m) for m in means], 1)
    ahead = {}
    for k in STEPS:
        out = np.full_like(read, np.nan)
        for t in range(periods + 1 - k):
            x = means[t]
            for j in range(k):
                x = loop.f(x, inputs[:, t + j])
            out[:, t + k] = angle(x)
        ahead[k] = out
    return read, ahead


def table(truth: np.ndarray, columns: dict[str, np.ndarray]) -> list[str]:
    """Mean absolute angle error of each column (angles ``[B, T+1]``, NaN: none) against ``truth``, by band and
    over all frames."""
    from_up = upright_error(torch.from_numpy(truth)).numpy()
    rows = [
        "| true angle from upright (rad) | share of frames | " + " | ".join(columns) + " |",
        "|---|---:|" + "---:|" * len(columns),
    ]
    for lo, hi in BANDS:
        band = (from_up >= lo) & (from_up < hi)
        cells = [f"{np.nanmean(wrap(angles - truth)[band]):.3f}" for angles in columns.values()]
        name = f"{lo:g} to {hi:.1f}" if hi < np.pi else f"{lo:g} and above"
        rows.append(f"| {name} | {band.mean():.2f} | " + " | ".join(cells) + " |")
    cells = [f"{np.nanmean(wrap(angles - truth)):.3f}" for angles in columns.values()]
    rows.append("| all frames | 1.00 | " + " | ".join(cells) + " |")
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ssm-checkpoint", required=True)
    parser.add_argument("--encoder-checkpoint", help="estimate with this encoder instead of the UKF")
    parser.add_argument("--config", default="configs/pendulum_torque_control.yaml")
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument(
        "--episodes-of",
        choices=["true", "learned"],
        default="true",
        help="whose controller drives the episodes: the true model's (default) or the learned model's own",
    )
    parser.add_argument("--out", default="studies/control_diagnosis/control_diagnosis.md")
    opts = parser.parse_args(argv)
    if not Path(opts.ssm_checkpoint).is_file():
        sys.exit(
            f"no SSM checkpoint at {opts.ssm_checkpoint}: train one first "
            "(python cli.py fit --config configs/pendulum_torque.yaml)"
        )
    config = load_config(opts.config)
    torch.manual_seed(0)
    try:
        learned, dm = closed_loop(
            config, ssm_checkpoint=opts.ssm_checkpoint, encoder_checkpoint=opts.encoder_checkpoint
        )
    except ValueError as e:  # e.g. an encoder of another SSM, or none at the path
        sys.exit(str(e))
    driver = learned if opts.episodes_of == "learned" else closed_loop(config, true_model=True)[0]
    frames, inputs, truth = episodes(driver, dm, opts.episodes)
    up = upright_error(torch.from_numpy(truth[:, -20:])).numpy()
    read, ahead = diagnose(learned, frames, inputs)
    images = torch.stack([learned.camera(y) for y in frames], 1)  # [B, T+1, 1, H, W]
    sc = learned.ink_angle(images.flatten(0, 1)).view(*images.shape[:2], 2)
    columns = {
        "the frame's own ink": torch.atan2(sc[..., 0], sc[..., 1]).double().numpy(),
        "estimate": read,
        **{f"{k} step{'s' * (k > 1)} ahead": ahead[k] for k in STEPS},
    }
    lines = [
        "# A learned pendulum SSM along "
        + ("the true-model controller's swing-ups" if opts.episodes_of == "true" else "its own controller's episodes"),
        "",
        *provenance("studies/control_diagnosis/control_diagnosis.py", argv),
        f"- Episodes: {len(truth)} from `{opts.config}`'s starts, planned "
        + ("on the true model with the true state " if opts.episodes_of == "true" else "on the learned model itself ")
        + (
            f"({np.mean((up < learned.tolerance).all(1)):.0%} upright over the last 2 s); along them the learned "
            f"model's {learned.estimator_name} reads the frames and the applied torques, and f predicts k steps ahead "
            "from each estimate under the same torques. Mean absolute angle error (rad) of what the planner reads (the "
            "distilled angle of the decoder's ink) against the true angle, by the true angle's distance from upright; "
            "beside it, the angle of the ink of the noisy frame seen, read alone (no model)."
        ),
        f"- Distilled angle readout's own error on the model's states (mean squared error of sin, cos; held out): {learned.distill_error:.3f}",
        "",
        *table(truth, columns),
        "",
    ]
    write(opts.out, lines)


if __name__ == "__main__":
    main()
