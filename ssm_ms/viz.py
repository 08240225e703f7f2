"""The training-time TensorBoard callbacks: :class:`ReconstructionLogger` (ground truth against the model's
rollout, every few epochs) and :class:`ShootingPictureLogger` (the multiple-shooting picture before and after
training), :func:`tensorboard_writer`, which finds the trainer's TensorBoard writer, and
:func:`shooting_predictions`, the sub-trajectories of a model's shooting nodes that picture draws.

What they draw, and every other picture (mosaics, GIFs, Lorenz and training-curve figures), is in
:mod:`ssm_ms.drawing`.
"""

from __future__ import annotations

import lightning.pytorch as pl
import torch
from lightning.pytorch.callbacks import Callback

from ssm_ms.drawing import figure_to_image, reconstruction_grid, series_figure, shooting_figure
from ssm_ms.module import MultipleShootingModule
from ssm_ms.nets.sensors import by_stream
from ssm_ms.training import checks
from ssm_ms.training.shooting import decode, rollout


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
    clean when known, model; one column per ``T / max_frames`` frames), vectors to a figure; several sensors one
    picture per stream, ``val/reconstruction/<stream>``.

    Args:
        every_n_epochs: log at the first validation, then at the first validation after each further
            ``every_n_epochs`` epochs of training (and at the last epoch). Validation runs only every
            ``check_val_every_n_epoch`` epochs (after epochs 9, 19, ... for 10), so the picture follows the
            validations rather than asking for epochs that have none. ``None`` (default): ``PICTURES`` pictures
            over the run, every ``trainer.max_epochs // PICTURES`` epochs (at least 1; every 10 where the run
            has no epoch count, e.g. under a time budget), so that a config and its shorter twin share one list.
        max_trajectories: trajectories drawn.
        max_frames: frames per row for images.
    """

    PICTURES = 20

    def __init__(self, every_n_epochs: int | None = None, max_trajectories: int = 4, max_frames: int = 10):
        if every_n_epochs is not None and every_n_epochs < 1:
            raise ValueError(f"every_n_epochs must be >= 1, got {every_n_epochs}")
        self.every_n_epochs = every_n_epochs
        self.max_trajectories = max_trajectories
        self.max_frames = max_frames
        self._drawn_window = -1  # the last window of every_n_epochs trained epochs drawn (after a resume: none)

    def _due(self, trainer: pl.Trainer) -> bool:
        epoch, max_epochs = trainer.current_epoch, trainer.max_epochs
        last = max_epochs is not None and epoch == max_epochs - 1
        every = self.every_n_epochs
        if every is None:
            every = max(1, max_epochs // self.PICTURES) if max_epochs is not None and max_epochs > 0 else 10
        window = (epoch + 1) // every  # whole windows trained by the end of this epoch
        if window > self._drawn_window or last:
            self._drawn_window = window
            return True
        return False

    def on_validation_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0) -> None:
        if batch_idx != 0 or trainer.sanity_checking or not isinstance(outputs, dict) or not self._due(trainer):
            return
        writer = tensorboard_writer(trainer)
        if writer is None:
            return
        step, layout = trainer.global_step, getattr(trainer.datamodule, "sensor_layout", None)
        streams = by_stream(layout, outputs["y"], outputs["y_hat"], outputs.get("y_clean"))
        for name, (y, y_hat, y_clean) in streams.items():  # several sensors: one picture per stream
            tag = "val/reconstruction" + (f"/{name}" if name else "")
            if y.dim() == 5:
                grid = reconstruction_grid(y, y_hat, y_clean, self.max_trajectories, self.max_frames)
                writer.add_image(tag, grid, step)
            elif y.dim() == 3:
                fig = series_figure(y, y_hat, y_clean, self.max_trajectories, title=f"epoch {trainer.current_epoch}")
                writer.add_figure(tag, fig, step)


class ShootingPictureLogger(Callback):
    """Log the multiple-shooting picture before and after training (TensorBoard ``shooting/before``,
    ``shooting/after``).

    At ``on_fit_start`` (after the model's setup and any checkpoint restore, so the nodes exist) and at
    ``on_fit_end`` it takes the first ``n_trajectories`` of the first validation batch
    (``trainer.datamodule.val_dataloader()``: training trajectories, so their nodes exist) and draws
    :func:`shooting_figure` for each, stacked into one image. Only vector data (``y [B, T, D]``) are
    drawn; image data log nothing (a sub-trajectory of images has no line to draw). Without a
    TensorBoard logger, or without validation data, it does nothing.

    Args:
        n_trajectories: trajectories drawn (one figure each, stacked vertically).
    """

    def __init__(self, n_trajectories: int = 2):
        if n_trajectories < 1:
            raise ValueError(f"n_trajectories must be >= 1, got {n_trajectories}")
        self.n_trajectories = n_trajectories

    @staticmethod
    def _first_val_batch(trainer: pl.Trainer):
        loader = None
        dm = getattr(trainer, "datamodule", None)
        if dm is not None and hasattr(dm, "val_dataloader"):
            try:
                loader = dm.val_dataloader()
            except (NotImplementedError, RuntimeError):  # a DataModule without validation data
                loader = None
        if loader is None:
            loader = getattr(trainer, "val_dataloaders", None)
        if isinstance(loader, (list, tuple)):
            loader = loader[0] if loader else None
        if loader is None:
            return None
        try:
            return next(iter(loader))
        except StopIteration:
            return None

    def _log(self, trainer: pl.Trainer, pl_module, when: str) -> None:
        if not trainer.is_global_zero:
            return
        writer = tensorboard_writer(trainer)
        if writer is None:
            return
        batch = self._first_val_batch(trainer)
        if not isinstance(batch, dict) or "y" not in batch or "index" not in batch or batch["y"].dim() != 3:
            return
        k = self.n_trajectories
        index, y = batch["index"][:k], batch["y"][:k]
        preds = shooting_predictions(pl_module, index, y=y, u=batch["u"][:k] if "u" in batch else None)
        y = y[:, pl_module.history :]  # amortised nodes: the pieces cover the window after the history
        n = y.shape[1] // pl_module.n_nodes
        images = []
        for b in range(len(index)):
            fig = shooting_figure(y[b], preds[b], n, title=f"trajectory {int(index[b])}, {when} training")
            images.append(figure_to_image(fig))
        writer.add_image(f"shooting/{when}", torch.cat(images, dim=1), trainer.global_step)
        writer.flush()

    def on_fit_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._log(trainer, pl_module, "before")

    def on_fit_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._log(trainer, pl_module, "after")


@torch.no_grad()
def shooting_predictions(
    model: MultipleShootingModule,
    index: torch.Tensor,
    y: torch.Tensor | None = None,
    seq_len: int | None = None,
    u: torch.Tensor | None = None,
) -> torch.Tensor:
    """``g(f^k(s_i))`` for every shooting node ``s_i`` of the model's training trajectories ``index``, ``k = 0..n``.

    Args:
        index: ``LongTensor[B]`` training-trajectory indices.
        y: measurements ``[B, T, ...]`` (only their length is used), or give ``seq_len`` instead.
        u: the trajectories' inputs ``[B, T, input_dim]`` where ``f`` takes them.

    Returns:
        ``[B, m, n + 1, *obs_shape]`` with ``n = T / m`` (entry ``k = n`` is where sub-trajectory ``i``
        ends up at the time node ``i + 1`` starts). Computed without gradients, in eval mode, on the
        model's device (what :class:`ShootingPictureLogger` draws). Amortised nodes read their
        history from ``y`` (required), and the pieces cover ``y[:, history:]``: ``n = (T - history) / m``.
    """
    if (y is None) == (seq_len is None):
        raise ValueError("give either y [B, T, ...] or seq_len to shooting_predictions")
    if model.node_encoder is not None:
        if y is None:
            raise ValueError("amortised nodes are read from the measurements: give y to shooting_predictions")
        was_training = model.training
        model.eval()
        try:
            device = model.alpha.device
            nodes, y_shot, u_shot = model.batch_nodes({"y": y.to(device), "u": None if u is None else u.to(device)})
        finally:
            model.train(was_training)
        return _piece_predictions(model, nodes, y_shot.shape[1], u_shot)
    t = int(y.shape[1]) if y is not None else int(seq_len)
    m = model.n_nodes
    if t % m != 0:
        raise ValueError(f"trajectory length T={t} is not a multiple of model.n_nodes={m}")
    return _piece_predictions(model, model.node_states(index.to(model.nodes.weight.device)), t, u)


@torch.no_grad()
def _piece_predictions(
    model: MultipleShootingModule, nodes: torch.Tensor, t: int, u: torch.Tensor | None
) -> torch.Tensor:
    """``g(f^k(s_i))``, ``k = 0..n``, of nodes ``[B, m, d]`` over pieces of ``n = t / m``
    (inputs ``u [B, t, m_u]``)."""
    m = model.n_nodes
    n = t // m
    was_training = model.training
    model.eval()
    try:
        b, _, d = nodes.shape
        checks.check_rollout_inputs(model.input_dim, None if u is None else u[:, :n], n)
        pieces = None if u is None else u.to(nodes).reshape(b * m, n, -1)
        states = rollout(model.f, nodes.reshape(b * m, d), n + 1, pieces)  # [B*m, n+1, d]
        out = decode(model.g, states, model.hparams.decode_chunk)
    finally:
        model.train(was_training)
    return out.reshape(b, m, n + 1, *out.shape[2:])
