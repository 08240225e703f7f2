"""Figures of forecasts: what the test protocol logs to TensorBoard and writes to ``figures_dir``
(:func:`log_forecast_figures`), and what ``predict`` draws per sequence (:func:`forecast_figure`). The drawing
primitives (mosaics, GIFs, plots) are :mod:`ssm_ms.drawing`'s."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from ssm_ms.nets.sensors import by_stream


def log_forecast_figures(module: Any, first: dict[str, torch.Tensor], n_sequences: int = 4) -> None:
    """``module``: a :class:`~ssm_ms.forecasting.protocol.ForecastModule` (not imported: the protocol calls this).
    Prediction mosaics / GIF (images) or the prediction plot over time (vectors), plus the forecaster's
    own figures (:meth:`ForecastModule.forecast_figures`), to TensorBoard and, with ``figures_dir``, to files.
    Several sensors: each stream's, its name appended to the figure's."""
    from ssm_ms import drawing
    from ssm_ms.viz import tensorboard_writer

    writer = tensorboard_writer(module.trainer) if module._trainer is not None else None
    out_dir = Path(module.figures_dir) if module.figures_dir else None
    name = f"{module.experiment_name()}_{module.method_name}"
    k = module.n_filter
    figures: dict[str, Any] = module.forecast_figures(first)
    norm = module.normalizer()
    to_units = (lambda t: norm.denormalize(t)) if norm is not None else (lambda t: t)
    drawn = first["y"], first["y_model"], first.get("y_clean")
    if module.sensor_layout is not None:  # several sensors: to units packed (the statistics are of the packed vector)
        drawn, to_units = tuple(None if t is None else to_units(t) for t in drawn), (lambda t: t)
    streams = by_stream(module.sensor_layout, *drawn)
    for stream, (y, y_model, y_clean) in streams.items():  # several sensors: each stream drawn in its own shape
        suffix = f"_{stream}" if stream else ""
        if y.dim() == 5:  # images
            every = 1 if y.shape[1] <= 20 else 10
            mosaic = drawing.prediction_mosaic(y[:n_sequences], y_model[:n_sequences], k, every=every)
            if writer is not None:
                writer.add_image(f"test/{module.method_name}/prediction_mosaic{suffix}", mosaic, 0)
            if out_dir is not None:
                drawing.save_png(mosaic, out_dir / f"{name}{suffix}_mosaic.png", scale=max(1, 256 // y.shape[-1]))
                drawing.save_gif(y[0], y_model[0], k, out_dir / f"{name}{suffix}.gif")
        elif y.dim() == 3 and "lorenz_prediction" not in figures:  # vectors: the measured components over time
            clean = to_units(y_clean) if y_clean is not None else None
            if y.shape[-1] == 1:
                figures[f"lorenz_prediction{suffix}"] = drawing.lorenz_prediction_figure(
                    to_units(y[0]),
                    None if clean is None else clean[0],
                    to_units(y_model[0]),
                    k,
                    window=min(y.shape[1], 400),
                )
            else:
                figures[f"prediction{suffix}"] = drawing.series_figure(
                    to_units(y), to_units(y_model), clean, title=f"filtering {k} steps, then prediction"
                )
    shared = getattr(module, "shared_figures", ())
    for key, fig in figures.items():
        if writer is not None:
            writer.add_figure(f"test/{module.method_name}/{key}", fig, 0, close=False)
        if out_dir is not None:  # figures of the SSM alone: one per SSM, not per inference method
            default = module.method_name == module.method_kind  # the experiment's own SSM; else a row of its own
            stem = module.experiment_name() if key in shared and default else name
            drawing.save_figure(fig, out_dir / f"{stem}_{key}.png")


def forecast_figure(measured: np.ndarray, filtered: np.ndarray, predicted: np.ndarray, title: str = ""):
    """One sequence of vector measurements: each component over time, the given samples (dots), what followed
    them in the file (crosses), the model's estimate of the given ones (line) and its forecast (dashed)."""
    from matplotlib.figure import Figure

    k, p, dims = len(filtered), len(predicted), measured.shape[-1]
    fig = Figure(figsize=(8, 1.8 * dims + 0.6), constrained_layout=True)
    axes = fig.subplots(dims, 1, squeeze=False, sharex=True)[:, 0]
    t_given, t_next = np.arange(k), np.arange(k, k + p)
    after = measured[k : k + p]
    for i, ax in enumerate(axes):
        ax.plot(t_given, measured[:k, i], ".", ms=3, color="0.4", label="given")
        if len(after):
            ax.plot(t_next[: len(after)], after[:, i], "x", ms=3, color="0.6", label="in the file after")
        ax.plot(t_given, filtered[:, i], "-", lw=1.2, color="C0", label="model (given part)")
        ax.plot(t_next, predicted[:, i], "--", lw=1.4, color="C1", label="forecast")
        ax.axvline(k - 0.5, color="k", lw=0.6, alpha=0.5)
        ax.set_ylabel(f"y[{i}]")
    axes[0].legend(loc="upper right", fontsize=7, ncol=4)
    axes[-1].set_xlabel("time step")
    if title:
        fig.suptitle(title, fontsize=9)
    return fig
