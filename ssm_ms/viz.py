"""Pictures of what the model does: image grids, time-series figures, and the TensorBoard callback.

No torchvision: grids are assembled with plain tensor ops; figures use matplotlib's object API
(no pyplot state, any backend).
"""

from __future__ import annotations

from collections.abc import Sequence

import lightning.pytorch as pl
import numpy as np
import torch
from lightning.pytorch.callbacks import Callback
from matplotlib.figure import Figure


def image_grid(rows: Sequence[torch.Tensor], pad: int = 1, pad_value: float = 1.0) -> torch.Tensor:
    """Tile rows of frames into one image.

    Args:
        rows: each ``[F, C, H, W]`` (F frames of one row; all rows the same shape).
    Returns:
        ``[C, R*(H+pad)+pad, F*(W+pad)+pad]`` with values clamped to [0, 1].
    """
    r = torch.stack([row.detach().float().cpu() for row in rows])  # [R, F, C, H, W]
    n_rows, n_cols, c, h, w = r.shape
    out = torch.full((c, n_rows * (h + pad) + pad, n_cols * (w + pad) + pad), pad_value)
    for i in range(n_rows):
        for j in range(n_cols):
            top, left = pad + i * (h + pad), pad + j * (w + pad)
            out[:, top : top + h, left : left + w] = r[i, j]
    return out.clamp(0, 1)


def frame_indices(t: int, max_frames: int) -> list[int]:
    """Evenly spaced frame indices (every ``ceil(t / max_frames)``-th frame)."""
    stride = max(1, -(-t // max_frames))
    return list(range(0, t, stride))


def reconstruction_grid(
    y: torch.Tensor,
    y_hat: torch.Tensor,
    y_clean: torch.Tensor | None = None,
    max_trajectories: int = 4,
    max_frames: int = 10,
) -> torch.Tensor:
    """For each trajectory a row of measured frames (and clean frames), then the model's frames.

    ``y``, ``y_hat``, ``y_clean``: ``[B, T, C, H, W]``.
    """
    cols = frame_indices(y.shape[1], max_frames)
    rows = []
    for b in range(min(max_trajectories, len(y))):
        rows.append(y[b, cols])
        if y_clean is not None:
            rows.append(y_clean[b, cols])
        rows.append(y_hat[b, cols])
    return image_grid(rows)


def series_figure(
    y: torch.Tensor,
    y_hat: torch.Tensor,
    y_clean: torch.Tensor | None = None,
    max_trajectories: int = 3,
    title: str = "",
) -> Figure:
    """Vector measurements over time: measured (dots), clean (thin), model (line); one panel per trajectory.

    ``y``, ``y_hat``, ``y_clean``: ``[B, T, D]`` (every component is drawn).
    """
    n = min(max_trajectories, len(y))
    fig = Figure(figsize=(8, 2.2 * n), constrained_layout=True)
    axes = fig.subplots(n, 1, squeeze=False)[:, 0]
    t = np.arange(y.shape[1])
    for b, ax in enumerate(axes):
        for d in range(y.shape[2]):
            color = f"C{d}"
            ax.plot(t, y[b, :, d].detach().cpu().numpy(), ".", ms=2, color=color, alpha=0.4, label=f"y[{d}] measured")
            if y_clean is not None:
                ax.plot(t, y_clean[b, :, d].detach().cpu().numpy(), "-", lw=0.8, color="k", alpha=0.6,
                        label=f"y[{d}] clean")
            ax.plot(t, y_hat[b, :, d].detach().cpu().numpy(), "-", lw=1.4, color=color, label=f"y[{d}] model")
        ax.set_ylabel(f"trajectory {b}")
    axes[0].legend(loc="upper right", fontsize=7, ncol=3)
    axes[-1].set_xlabel("time step")
    if title:
        fig.suptitle(title)
    return fig


def tensorboard_writer(trainer: pl.Trainer):
    """The SummaryWriter of the trainer's first TensorBoard logger, or None."""
    for logger in trainer.loggers:
        exp = getattr(logger, "experiment", None)
        if exp is not None and hasattr(exp, "add_image") and hasattr(exp, "add_figure"):
            return exp
    return None


class ReconstructionLogger(Callback):
    """Every few epochs, draw ground truth against the model's full-length rollout in TensorBoard.

    Uses what ``validation_step`` returns for its first batch (``y``, ``y_hat``, optional
    ``y_clean``): the training trajectories of the validation subset, rolled out from their first
    shooting node over their whole length. Images go to ``val/reconstruction`` (rows: measured,
    clean when known, model; one column per ``T / max_frames`` frames), vectors to a figure.

    Args:
        every_n_epochs: log when ``epoch % every_n_epochs == 0`` (and at the last epoch).
        max_trajectories: trajectories drawn.
        max_frames: frames per row for images.
    """

    def __init__(self, every_n_epochs: int = 10, max_trajectories: int = 4, max_frames: int = 10):
        if every_n_epochs < 1:
            raise ValueError(f"every_n_epochs must be >= 1, got {every_n_epochs}")
        self.every_n_epochs = every_n_epochs
        self.max_trajectories = max_trajectories
        self.max_frames = max_frames

    def _due(self, trainer: pl.Trainer) -> bool:
        epoch = trainer.current_epoch
        last = trainer.max_epochs is not None and epoch == trainer.max_epochs - 1
        return epoch % self.every_n_epochs == 0 or last

    def on_validation_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0) -> None:
        if batch_idx != 0 or trainer.sanity_checking or not isinstance(outputs, dict) or not self._due(trainer):
            return
        writer = tensorboard_writer(trainer)
        if writer is None:
            return
        y, y_hat, y_clean = outputs["y"], outputs["y_hat"], outputs.get("y_clean")
        step = trainer.global_step
        if y.dim() == 5:
            grid = reconstruction_grid(y, y_hat, y_clean, self.max_trajectories, self.max_frames)
            writer.add_image("val/reconstruction", grid, step)
        elif y.dim() == 3:
            fig = series_figure(y, y_hat, y_clean, self.max_trajectories, title=f"epoch {trainer.current_epoch}")
            writer.add_figure("val/reconstruction", fig, step)
