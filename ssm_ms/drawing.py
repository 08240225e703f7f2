"""Pictures of what the model does, as image tensors and matplotlib figures: image grids, time-series
figures, forecasting figures, the multiple-shooting picture, training curves.

Training: :func:`reconstruction_grid` / :func:`series_figure` and the multiple-shooting picture
:func:`shooting_figure` (drawn by the callbacks of :mod:`ssm_ms.viz`). Evaluation: :func:`prediction_mosaic`,
:func:`save_gif`, :func:`lorenz_prediction_figure`, :func:`attractor_figure`, :func:`loss_curves_figure`.
Files: :func:`save_png`, :func:`save_figure`.

No torchvision and no Lightning: grids are assembled with plain tensor ops; figures use matplotlib's object
API (no pyplot state, any backend); GIFs and PNGs are written with Pillow. Functions take tensors on any
device and return an image tensor ``[C, H, W]`` in [0, 1] or a ``Figure``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from PIL import Image, ImageDraw, ImageFont


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
                ax.plot(
                    t, y_clean[b, :, d].detach().cpu().numpy(), "-", lw=0.8, color="k", alpha=0.6, label=f"y[{d}] clean"
                )
            ax.plot(t, y_hat[b, :, d].detach().cpu().numpy(), "-", lw=1.4, color=color, label=f"y[{d}] model")
        ax.set_ylabel(f"trajectory {b}")
    axes[0].legend(loc="upper right", fontsize=7, ncol=3)
    axes[-1].set_xlabel("time step")
    if title:
        fig.suptitle(title)
    return fig


# ====================================================================== forecasting figures
# Everything below takes tensors on any device (detached and moved to the CPU inside) and returns an
# image tensor [C, H, W] in [0, 1] or a matplotlib Figure; writing files is left to save_png / save_figure.


def _numpy(x: torch.Tensor | np.ndarray) -> np.ndarray:
    """A float64 numpy copy of a tensor (any device / dtype) or array."""
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().to(torch.float64).numpy()
    return np.asarray(x, dtype=np.float64)


def _cpu(x: torch.Tensor) -> torch.Tensor:
    return x.detach().float().cpu()


def save_png(image: torch.Tensor, path, scale: int = 1) -> Path:
    """Write an image tensor ``[C, H, W]`` (C = 1, 3 or 4) or ``[H, W]`` with values in [0, 1] as a PNG,
    each pixel repeated ``scale`` times per axis (nearest neighbour: small frames stay readable).

    Parent folders are created. Returns the path.
    """
    if scale < 1:
        raise ValueError(f"scale must be >= 1, got {scale}")
    img = _cpu(image)
    if scale > 1:
        img = img.repeat_interleave(scale, dim=-1).repeat_interleave(scale, dim=-2)
    if img.dim() == 2:
        img = img.unsqueeze(0)
    if img.dim() != 3 or img.shape[0] not in (1, 3, 4):
        raise ValueError(f"save_png expects an image [C, H, W] with C in 1, 3, 4 (or [H, W]), got {tuple(image.shape)}")
    arr = (img.clamp(0, 1) * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(arr[..., 0] if arr.shape[2] == 1 else arr).save(path)
    return path


def save_figure(fig: Figure, path, dpi: int = 150) -> Path:
    """Write a Figure to ``path`` (format from the suffix: .png, .pdf, .svg, ...), creating parent folders."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    return path


def figure_to_image(fig: Figure) -> torch.Tensor:
    """Render a Figure with Agg (no pyplot) into an RGB tensor ``[3, H, W]`` in [0, 1]."""
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    rgba = np.asarray(canvas.buffer_rgba())
    return torch.from_numpy(rgba[..., :3].copy()).permute(2, 0, 1).float() / 255.0


# ---------------------------------------------------------------------- prediction mosaic
def prediction_columns(t: int, every: int) -> list[int]:
    """The frames a mosaic shows: ``every-1, 2*every-1, ...`` below ``t`` (every frame for ``every=1``)."""
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    cols = list(range(every - 1, t, every))
    if not cols:
        raise ValueError(f"every={every} exceeds the sequence length T={t}: choose every <= {t}")
    return cols


def prediction_mosaic(
    y_true: torch.Tensor,
    y_model: torch.Tensor,
    n_filter: int,
    every: int = 10,
    max_rows: int | None = None,
    pad: int = 1,
    separator: int = 3,
    pad_value: float = 1.0,
    separator_value: float = 0.5,
) -> torch.Tensor:
    """Ground truth over the model's belief (``t < n_filter``) then prediction, one frame in ``every``.

    Args:
        y_true, y_model: ``[T, C, H, W]`` (one sequence) or ``[B, T, C, H, W]`` (two rows per sequence).
        n_filter: number of filtering steps; frames ``t >= n_filter`` are predictions.
        every: the columns are frames ``every-1, 2*every-1, ...`` (T=100, every=10: 9, 19, ..., 99).
        max_rows: draw at most this many sequences (each two rows); ``None``: all.
        pad: pixels (of ``pad_value``) around and between frames.
        separator: width of a full-height bar of ``separator_value`` between the last filtering column
            and the first prediction column (drawn only when both kinds of columns are shown); sequences
            of a batch are further apart by ``separator`` rows of ``pad_value``.

    Layout (what the tests recompute): with ``k`` filtering columns, column ``j`` starts at
    ``x = pad + j*(W+pad) + (separator+pad if j >= k else 0)`` (the shift only when the bar is drawn),
    the bar covers ``x in [pad + k*(W+pad), pad + k*(W+pad) + separator)``, and row ``r`` (0: truth,
    1: model) of sequence ``s`` starts at ``y = pad + (2s + r)*(H+pad) + s*separator``.

    Returns:
        ``[C, H', W']`` clamped to [0, 1].
    """
    if y_true.shape != y_model.shape:
        raise ValueError(f"y_true {tuple(y_true.shape)} and y_model {tuple(y_model.shape)} must have the same shape")
    if y_true.dim() == 4:
        y_true, y_model = y_true.unsqueeze(0), y_model.unsqueeze(0)
    if y_true.dim() != 5:
        raise ValueError(
            f"prediction_mosaic expects image sequences [T, C, H, W] or [B, T, C, H, W], got {tuple(y_true.shape)}"
        )
    n_seq, t, c, h, w = y_true.shape
    if not 0 <= n_filter <= t:
        raise ValueError(f"n_filter must lie in 0..T={t}, got {n_filter}")
    if max_rows is not None:
        if max_rows < 1:
            raise ValueError(f"max_rows must be >= 1 or None, got {max_rows}")
        n_seq = min(n_seq, max_rows)
    cols = prediction_columns(t, every)
    k = sum(1 for i in cols if i < n_filter)
    bar = 0 < k < len(cols)
    shift = separator + pad if bar else 0
    width = pad + len(cols) * (w + pad) + shift
    height = pad + 2 * n_seq * (h + pad) + (n_seq - 1) * separator
    out = torch.full((c, height, width), float(pad_value))
    if bar:
        x0 = pad + k * (w + pad)
        out[:, :, x0 : x0 + separator] = separator_value
    truth, model = _cpu(y_true[:n_seq, cols]), _cpu(y_model[:n_seq, cols])
    for s in range(n_seq):
        for r, frames in enumerate((truth[s], model[s])):
            top = pad + (2 * s + r) * (h + pad) + s * separator
            for j in range(len(cols)):
                left = pad + j * (w + pad) + (shift if j >= k else 0)
                out[:, top : top + h, left : left + w] = frames[j]
    return out.clamp(0, 1)


# ---------------------------------------------------------------------- animated GIF
def save_gif(
    y_true: torch.Tensor,
    y_model: torch.Tensor,
    n_filter: int,
    path,
    fps: float = 10,
    scale: int = 4,
    margin: int = 4,
    label_height: int = 14,
) -> Path:
    """An animated GIF of one sequence: ground truth (left) beside the model's belief / prediction (right).

    Args:
        y_true, y_model: ``[T, C, H, W]`` in [0, 1], C = 1 (stored exactly as 8-bit grey) or 3 (RGB,
            quantised to a 256-colour palette by Pillow).
        n_filter: frames ``t < n_filter`` are labelled "filtering" under the model, later ones "prediction".
        path, fps, scale, margin, label_height: as :func:`save_panel_gif` (the ground truth at ``(x=margin,
            y=label_height)``, the model at ``(x=2*margin + W*scale, y=label_height)``).

    Returns:
        The path written.
    """
    if y_true.shape != y_model.shape or y_true.dim() != 4:
        raise ValueError(
            f"save_gif expects y_true and y_model of the same shape [T, C, H, W], got {tuple(y_true.shape)} "
            f"and {tuple(y_model.shape)}"
        )
    t = y_true.shape[0]
    if not 0 <= n_filter <= t:
        raise ValueError(f"n_filter must lie in 0..T={t}, got {n_filter}")
    notes = [["", "filtering" if i < n_filter else "prediction"] for i in range(t)]
    return save_panel_gif({"ground truth": y_true, "model": y_model}, path, notes, fps, scale, margin, label_height)


def save_panel_gif(
    panels: dict[str, torch.Tensor],
    path,
    notes: Sequence[Sequence[str]] | None = None,
    fps: float = 10,
    scale: int = 4,
    margin: int = 4,
    label_height: int = 14,
) -> Path:
    """An animated GIF of sequences side by side, one panel each, named by its key.

    Args:
        panels: ``{label: [T, C, H, W]}`` in [0, 1], all the same shape; C = 1 (stored exactly as 8-bit grey) or 3
            (RGB, quantised to a 256-colour palette by Pillow).
        path: the .gif to write (parent folders are created).
        notes: per frame, one text per panel written under it (the first panel's after the time step ``t = i``,
            which every frame shows, so that no two frames are identical and Pillow merges none).
        fps: frames per second (GIF stores durations in 10 ms units).
        scale: each pixel becomes a ``scale x scale`` block (nearest neighbour).
        margin, label_height: layout. Frame size ``((P+1)*margin + P*W*scale) x (2*label_height + H*scale)`` for
            ``P`` panels; panel ``j`` sits at ``(x=(j+1)*margin + j*W*scale, y=label_height)``, its label above it.

    Returns:
        The path written.
    """
    sequences = list(panels.values())
    if not sequences or any(y.shape != sequences[0].shape or y.dim() != 4 for y in sequences):
        raise ValueError(
            f"save_panel_gif expects panels of one shape [T, C, H, W], got {[tuple(y.shape) for y in sequences]}"
        )
    t, c, h, w = sequences[0].shape
    if c not in (1, 3):
        raise ValueError(f"a GIF panel draws grey (C=1) or RGB (C=3) frames, got C={c}")
    if scale < 1 or fps <= 0:
        raise ValueError(f"scale must be >= 1 and fps > 0, got scale={scale}, fps={fps}")
    if notes is not None and len(notes) != t:
        raise ValueError(f"notes must hold one entry per frame ({t}), got {len(notes)}")

    def to_uint8(y: torch.Tensor) -> np.ndarray:  # [T, C, H, W] -> [T, H*scale, W*scale(, 3)]
        a = (_cpu(y).clamp(0, 1) * 255).round().to(torch.uint8)
        a = a.repeat_interleave(scale, dim=2).repeat_interleave(scale, dim=3).permute(0, 2, 3, 1).numpy()
        return a[..., 0] if c == 1 else a

    images = [to_uint8(y) for y in sequences]
    mode, white, black = ("L", 255, 0) if c == 1 else ("RGB", (255, 255, 255), (0, 0, 0))
    n = len(images)
    size = ((n + 1) * margin + n * w * scale, 2 * label_height + h * scale)
    xs = [(j + 1) * margin + j * w * scale for j in range(n)]
    font = ImageFont.load_default()
    frames = []
    for i in range(t):
        frame = Image.new(mode, size, white)
        draw = ImageDraw.Draw(frame)
        for j, (label, image) in enumerate(zip(panels, images)):
            frame.paste(Image.fromarray(image[i]), (xs[j], label_height))
            draw.text((xs[j], 1), label, fill=black, font=font)
            note = notes[i][j] if notes is not None and j < len(notes[i]) else ""
            text = f"t = {i}" + (f"  {note}" if note else "") if j == 0 else note
            draw.text((xs[j], label_height + h * scale + 1), text, fill=black, font=font)
        frames.append(frame)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    frames[0].save(path, save_all=True, append_images=frames[1:], duration=int(round(1000 / fps)), loop=0)
    return path


# ---------------------------------------------------------------------- Lorenz
def lorenz_prediction_figure(
    y: torch.Tensor,
    y_clean: torch.Tensor | None,
    states: torch.Tensor,
    n_filter: int,
    true_state: torch.Tensor | None = None,
    dt: float = 0.005,
    measured_index: int = 0,
    window: int | None = None,
) -> Figure:
    """One panel per state component over time (seconds), filtering then prediction.

    Args:
        y, y_clean: ``[T]`` or ``[T, 1]``: measurement and noiseless measurement (original units);
            ``y_clean`` may be ``None``.
        states: ``[T, d]``: the model's inferred states for ``t < n_filter``, then its predicted states.
            Component ``measured_index`` is in measurement units (g reads it).
        n_filter: first predicted step; a dashed vertical line at ``n_filter * dt`` in every panel.
        true_state: optional ``[T, d']``: drawn faintly, on a right-hand axis of its own, in the panels of
            the unmeasured components (the latent axes of a learned model need not match them in scale or
            offset); in the measured panel the noiseless
            measurement is the true component.
        dt: seconds per step.
        measured_index: the state component the measurement reads.
        window: show only steps ``n_filter - window .. n_filter + window - 1`` (clipped to the
            sequence); ``None``: all.

    Artists carry ``gid``s: ``"model"``, ``"measurement"``, ``"noiseless"``, ``"true"``, ``"prediction_start"``.
    """
    y_np = _numpy(y)
    if y_np.ndim == 2 and y_np.shape[1] == 1:
        y_np = y_np[:, 0]
    s = _numpy(states)
    if y_np.ndim != 1 or s.ndim != 2 or len(s) != len(y_np):
        raise ValueError(
            f"expected y [T] or [T, 1] and states [T, d] of the same length, got {tuple(y.shape)} "
            f"and {tuple(states.shape)}"
        )
    t_len, d = s.shape
    if not 0 <= measured_index < d:
        raise ValueError(f"measured_index={measured_index} is not a state component (0..{d - 1})")
    if not 0 <= n_filter <= t_len:
        raise ValueError(f"n_filter must lie in 0..T={t_len}, got {n_filter}")
    clean = None
    if y_clean is not None:
        clean = _numpy(y_clean).reshape(len(y_np), -1)[:, 0]
    true = None
    if true_state is not None:
        true = _numpy(true_state)
        if true.ndim != 2 or len(true) != t_len:
            raise ValueError(f"true_state must be [T={t_len}, d], got {tuple(true_state.shape)}")
    lo, hi = 0, t_len
    if window is not None:
        if window < 1:
            raise ValueError(f"window must be >= 1 or None, got {window}")
        lo, hi = max(0, n_filter - window), min(t_len, n_filter + window)
    sel = slice(lo, hi)
    time = np.arange(t_len)[sel] * dt

    fig = Figure(figsize=(9, 2.2 * d), constrained_layout=True)
    axes = fig.subplots(d, 1, sharex=True, squeeze=False)[:, 0]
    for i, ax in enumerate(axes):
        if i == measured_index:
            ax.plot(time, y_np[sel], ".", ms=2.5, color="0.45", label="measurement", gid="measurement")
            if clean is not None:
                ax.plot(time, clean[sel], "-", lw=1.0, color="k", label="noiseless measurement", gid="noiseless")
        elif true is not None and i < true.shape[1]:
            # on its own (right) axis: a learned latent coordinate has its own scale and offset
            twin = ax.twinx()
            twin.set_label("true-state axis")
            twin.plot(time, true[sel, i], "-", lw=1.0, color="0.6", alpha=0.7, gid="true")
            twin.set_ylabel(f"true state {i} (right axis)", color="0.5", fontsize=8)
            twin.tick_params(axis="y", colors="0.5", labelsize=7)
        ax.plot(time, s[sel, i], "-", lw=1.4, color="C0" if i == measured_index else "C1", label="model", gid="model")
        ax.axvline(n_filter * dt, color="C3", ls="--", lw=1.0, label="prediction starts", gid="prediction_start")
        ax.set_ylabel(f"state {i}" + (" (measured)" if i == measured_index else " (model, left axis)"))
        ax.legend(loc="upper left", fontsize=7, ncol=4)
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(f"filtering {n_filter} steps, then prediction")
    return fig


def attractor_figure(states: torch.Tensor, title: str = "", true_states: torch.Tensor | None = None) -> Figure:
    """A thin 3-D line through ``states [N, 3]`` (e.g. f iterated from a shooting node); with
    ``true_states [M, 3]`` (or ``[R, M, 3]``: several runs) the true system's attractor beside it."""
    s = _numpy(states)
    if s.ndim != 2 or s.shape[1] != 3:
        raise ValueError(f"attractor_figure draws states [N, 3], got {tuple(states.shape)}")
    panels = [(s[None], title or "model", "C0", "attractor", "state")]
    if true_states is not None:
        t = _numpy(true_states)
        t = t[None] if t.ndim == 2 else t
        if t.ndim != 3 or t.shape[-1] != 3:
            raise ValueError(f"true_states must be [M, 3] or [R, M, 3], got {tuple(true_states.shape)}")
        panels.append((t, "the true system (test sequences)", "0.3", "true_attractor", "true state"))
    fig = Figure(figsize=(6 * len(panels), 6), constrained_layout=True)
    for i, (runs, name, color, gid, axis) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), i + 1, projection="3d")
        for run in runs:
            ax.plot(run[:, 0], run[:, 1], run[:, 2], lw=0.3, color=color, gid=gid)
        ax.set_xlabel(f"{axis} 0")
        ax.set_ylabel(f"{axis} 1")
        ax.set_zlabel(f"{axis} 2")
        ax.set_title(name)
    return fig


# ---------------------------------------------------------------------- training curves
LOSS_TAGS = ("train/fit", "train/gap")
SCHEDULE_TAGS = ("alpha", "lr")


def read_scalars(log_dir) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Every scalar in the TensorBoard event files under ``log_dir``: ``{tag: (steps, values)}``.

    Folders holding event files are read one by one (all their events, no sampling) and merged per tag
    by step; where several runs (e.g. a resumed one) logged the same step, the later write wins.
    """
    from tensorboard.backend.event_processing.event_accumulator import SCALARS, EventAccumulator

    root = Path(log_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"log folder {root} does not exist: pass the folder TensorBoard logged to")
    folders = sorted({p.parent for p in root.rglob("events.out.tfevents.*") if p.is_file()})
    if not folders:
        raise FileNotFoundError(
            f"no TensorBoard event file (events.out.tfevents.*) under {root}: pass a run's log folder "
            "(e.g. lightning_logs/version_0) or a folder above it"
        )
    merged: dict[str, dict[int, tuple[float, float]]] = {}
    for folder in folders:
        acc = EventAccumulator(str(folder), size_guidance={SCALARS: 0})
        acc.Reload()
        for tag in acc.Tags().get("scalars", []):
            per_step = merged.setdefault(tag, {})
            for ev in acc.Scalars(tag):
                if ev.step not in per_step or ev.wall_time >= per_step[ev.step][0]:
                    per_step[ev.step] = (ev.wall_time, ev.value)
    out = {}
    for tag, per_step in merged.items():
        steps = np.array(sorted(per_step), dtype=np.int64)
        out[tag] = (steps, np.array([per_step[int(k)][1] for k in steps], dtype=np.float64))
    return out


def _find_tag(scalars: dict, tag: str) -> str | None:
    for name in (tag, f"{tag}_step", f"{tag}_epoch"):
        if name in scalars:
            return name
    return None


def loss_curves_figure(log_dir) -> Figure:
    """``train/fit`` and ``train/gap`` against step (log y), and ``alpha`` / ``lr`` in a second panel.

    Reads the event files under ``log_dir`` (see :func:`read_scalars`); a tag logged as ``<tag>_step``
    is used when ``<tag>`` itself is missing. Lines carry the tag as ``gid`` and label.

    Raises:
        FileNotFoundError: no event file under ``log_dir``.
        ValueError: none of the four scalars was logged (the message lists the tags found).
    """
    scalars = read_scalars(log_dir)
    found = {tag: _find_tag(scalars, tag) for tag in LOSS_TAGS + SCHEDULE_TAGS}
    if not any(found.values()):
        raise ValueError(
            f"the event files under {log_dir} hold none of the scalars {list(LOSS_TAGS + SCHEDULE_TAGS)}; "
            f"tags found: {sorted(scalars) or 'none'}. Point loss_curves_figure at a MultipleShootingModule run"
        )
    fig = Figure(figsize=(8, 6), constrained_layout=True)
    ax_loss, ax_alpha = fig.subplots(2, 1, sharex=True)
    for i, tag in enumerate(LOSS_TAGS):
        if found[tag]:
            steps, values = scalars[found[tag]]
            ax_loss.plot(steps, values, lw=1.0, color=f"C{i}", label=tag, gid=tag)
    ax_loss.set_yscale("log")
    ax_loss.set_ylabel("loss")
    ax_loss.legend(loc="upper right", fontsize=8)
    ax_lr = ax_alpha.twinx()
    for ax, tag, color in ((ax_alpha, "alpha", "C2"), (ax_lr, "lr", "C3")):
        if found[tag]:
            steps, values = scalars[found[tag]]
            ax.plot(steps, values, lw=1.2, color=color, label=tag, gid=tag)
        ax.set_ylabel(tag if found[tag] else f"{tag} (not logged)", color=color)
    if found["lr"] and (scalars[found["lr"]][1] > 0).all():
        ax_lr.set_yscale("log")
    ax_alpha.set_xlabel("step")
    fig.suptitle(str(log_dir), fontsize=8)
    return fig


# ---------------------------------------------------------------------- multiple shooting
def shooting_figure(y: torch.Tensor, node_predictions: torch.Tensor, n: int, title: str = "") -> Figure:
    """The multiple-shooting picture of one trajectory: measurements and every node's sub-trajectory.

    Args:
        y: ``[T]`` or ``[T, D]`` measurements (one panel per component).
        node_predictions: ``[m, n + 1]`` or ``[m, n + 1, D]``: ``g(f^k(s_i))``, ``k = 0..n`` (see
            ``ssm_ms.viz.shooting_predictions``). Sub-trajectory ``i`` is drawn at steps
            ``i*n .. (i+1)*n`` in its own colour (line ``gid`` ``"node{i}"``), its node as a dot at step ``i*n``
            (``gid`` ``"node{i}-start"``); where the last point of one misses the next node, the gap shows.
        n: steps per sub-trajectory, ``T = m * n``.
    """
    yy, pred = _numpy(y), _numpy(node_predictions)
    if yy.ndim == 1:
        yy = yy[:, None]
    if pred.ndim == 2:
        pred = pred[:, :, None]
    if yy.ndim != 2 or pred.ndim != 3:
        raise ValueError(
            f"shooting_figure draws vector data: y [T, D] and node_predictions [m, n+1, D], got "
            f"{tuple(y.shape)} and {tuple(node_predictions.shape)}"
        )
    m, _, d = pred.shape
    if pred.shape[1] != n + 1 or yy.shape[0] != m * n or yy.shape[1] != d:
        raise ValueError(
            f"with n={n} expected node_predictions [m, {n + 1}, D] and y [m*{n}, D], got "
            f"{tuple(node_predictions.shape)} and {tuple(y.shape)}"
        )
    fig = Figure(figsize=(8, 2.4 * d), constrained_layout=True)
    axes = fig.subplots(d, 1, sharex=True, squeeze=False)[:, 0]
    steps = np.arange(m * n)
    for j, ax in enumerate(axes):
        ax.plot(steps, yy[:, j], ".", ms=3, color="0.5", label="measurement", gid="measurement")
        for i in range(m):
            color = f"C{i % 10}"
            ax.plot(np.arange(i * n, (i + 1) * n + 1), pred[i, :, j], "-", lw=1.3, color=color, gid=f"node{i}")
            ax.plot([i * n], [pred[i, 0, j]], "o", ms=5, color=color, gid=f"node{i}-start")
        ax.set_ylabel(f"y[{j}]")
    axes[0].legend(loc="upper right", fontsize=7)
    axes[-1].set_xlabel("time step")
    fig.suptitle(title or f"{m} shooting nodes, {n} steps each")
    return fig
