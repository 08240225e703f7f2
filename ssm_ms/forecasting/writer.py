"""Forecasts of a user's own sequences, written by ``python cli.py predict``.

``predict`` runs the forecaster of a stage config (an SSM with its trained encoder, or a filter: UKF /
particle filter; a baseline works too) on the sequences of the DataModule's ``predict_path``: each
sequence's first ``k = predict_given`` samples are given (default: all of them), the next ``p =
predict_steps`` steps are forecast (default: the forecaster's ``n_predict``), by the same
:meth:`~ssm_ms.forecasting.protocol.ForecastModule.forecast` as the test protocol
(:meth:`~ssm_ms.forecasting.protocol.ForecastModule.predict_step`). :class:`ForecastWriter` collects the batches
and writes one ``.npz``:

========================  ======================  ==============================================
key                       shape                   what
========================  ======================  ==============================================
``index``                 ``[N]``                 the sequence's position in ``predict_path``
``filtered``              ``[N, k, *obs]``        the model's estimate of the given measurements
``predicted``             ``[N, p, *obs]``        the forecast of the ``p`` steps after them
``states``                ``[N, k, d]``           inferred latent states (SSMs)
``predicted_states``      ``[N, p, d]``           the latent states of the forecast (SSMs)
``state_cov``             ``[N, k, d, d]``        posterior covariances of the inferred states (filters)
``predicted_state_cov``   ``[N, p, d, d]``        the filter's covariances over the forecast (filters)
``k``, ``p``, ``method``  scalars                 the split and the forecaster (its results label)
========================  ======================  ==============================================

Several sensors (:mod:`ssm_ms.nets.sensors`): each stream's measurements under its own keys,
``filtered_<name>`` ``[N, k, *shape]`` and ``predicted_<name>`` ``[N, p, *shape]``, in place of the packed
``filtered`` and ``predicted``; the figures one PNG per sequence and stream (``sequence_00000_<name>.png``).

Measurements (``filtered``, ``predicted``) are in the units of the file (the data normalisation kept in
the checkpoint is undone); states and covariances in the model's latent units. With ``figures`` set, one
PNG per sequence goes to the folder ``<output without .npz>_figures/``: vectors as each component over
time (given samples, the model's estimate, the forecast and, where the file holds them, the samples that
followed), images as the given-then-following frames over the model's frames.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch
from lightning.pytorch.callbacks import BasePredictionWriter

from ssm_ms.forecasting.metrics import DIVERGENCE_BOUND, first_divergence
from ssm_ms.nets.sensors import SensorLayout

# predict_step outputs that are not written to the .npz (the figures use them)
NOT_SAVED = ("measured",)
MEASUREMENTS = ("measured", "filtered", "predicted")  # split per stream with several sensors


class ForecastWriter(BasePredictionWriter):
    """Writes the forecasts of ``python cli.py predict`` to one ``.npz`` (see the module docstring).

    Args:
        output: the ``.npz`` file to write (its folder is created). Written at the end of the run; an
            existing file is replaced.
        figures: ``False``/``0``: no figures; ``True``: one PNG per sequence; an integer ``n``: the first ``n``
            sequences.
    """

    def __init__(self, output: str = "predictions/forecast.npz", figures: bool | int = False):
        super().__init__(write_interval="batch")
        if not str(output).endswith(".npz"):
            raise ValueError(f"ForecastWriter output must be a .npz file name, got {output!r}")
        if isinstance(figures, bool):
            figures = -1 if figures else 0
        if figures < -1:
            raise ValueError(f"figures must be true, false or a number of sequences >= 0, got {figures}")
        self.output, self.figures = Path(output), int(figures)
        self._parts: list[dict[str, np.ndarray]] = []
        self._drawn = 0

    def on_predict_epoch_start(self, trainer, pl_module) -> None:
        self._parts, self._drawn = [], 0
        if self.figures:
            self.figures_dir.mkdir(parents=True, exist_ok=True)

    @property
    def figures_dir(self) -> Path:
        return self.output.with_name(self.output.stem + "_figures")

    def write_on_batch_end(
        self,
        trainer,
        pl_module,
        prediction: dict[str, torch.Tensor],
        batch_indices,
        batch,
        batch_idx: int,
        dataloader_idx: int = 0,
    ) -> None:
        part = {key: value.detach().cpu().numpy() for key, value in prediction.items()}
        self._split = (part["filtered"].shape[1], part["predicted"].shape[1])  # k, p
        layout = getattr(trainer.datamodule, "sensor_layout", None)
        if layout:  # several sensors: each stream's measurements in its own shape
            layout = SensorLayout.from_state_dict(layout)
            for key in MEASUREMENTS:
                packed = part.pop(key)
                for name, stream in layout.split(torch.from_numpy(packed)).items():
                    part[f"{key}_{name}"] = stream.numpy()
        if self.figures:
            self._draw(part, pl_module)
        self._parts.append({key: value for key, value in part.items() if key not in NOT_SAVED})

    def on_predict_epoch_end(self, trainer, pl_module) -> None:
        if not self._parts or not trainer.is_global_zero:
            return
        arrays = {key: np.concatenate([part[key] for part in self._parts]) for key in self._parts[0]}
        k, p = self._split
        self.output.parent.mkdir(parents=True, exist_ok=True)
        np.savez(self.output, **arrays, k=np.int64(k), p=np.int64(p), method=np.str_(pl_module.method_name))
        n = len(arrays["index"])
        covs = " and covariances" if "state_cov" in arrays else ""
        print(
            f"wrote {self.output}: forecasts of {p} steps after {k} given for {n} sequences (original units), "
            f"states{covs}" + (f"; figures in {self.figures_dir}" if self.figures else "")
        )
        diverged = self._diverged(arrays, pl_module)
        if diverged:
            shown = ", ".join(f"sequence {i} at step {s}" for i, s in diverged[:5])
            more = f" and {len(diverged) - 5} more" if len(diverged) > 5 else ""
            print(
                f"warning: {len(diverged)} of the {n} forecasts diverged (left the finite range, or "
                f"{DIVERGENCE_BOUND:g} training standard deviations): {shown}{more}; their values there are not a "
                "forecast",
                file=sys.stderr,
            )
        self._parts = []

    @staticmethod
    def _diverged(arrays: dict[str, np.ndarray], pl_module: Any) -> list[tuple[int, int]]:
        """``(sequence, step)`` of the forecasts that diverged: the first predicted step (counted from the forecast's
        start) outside the finite range or :data:`DIVERGENCE_BOUND` in the model's normalised units."""
        norm = pl_module.normalizer() if callable(getattr(pl_module, "normalizer", None)) else None
        keys = [k for k in arrays if k == "predicted" or k.startswith("predicted_") and k != "predicted_states"]
        keys = [k for k in keys if "cov" not in k]
        found: dict[int, int] = {}
        for key in keys:
            y = torch.from_numpy(np.asarray(arrays[key], dtype=np.float64))
            if key == "predicted" and norm is not None:
                y = norm.normalize(y)
            bound = DIVERGENCE_BOUND if key == "predicted" and norm is not None and not norm.is_identity else None
            for i, step in enumerate(first_divergence(y, bound).tolist()):
                if step >= 0:
                    found[i] = min(step, found.get(i, step))
        return sorted(found.items())

    # ------------------------------------------------------------------ figures
    def _draw(self, part: dict[str, np.ndarray], pl_module: Any) -> None:
        streams = [""] if "measured" in part else [k[len("measured_") :] for k in part if k.startswith("measured_")]
        for b, index in enumerate(part["index"]):
            if 0 <= self.figures <= self._drawn:
                return
            for stream in streams:
                suffix = f"_{stream}" if stream else ""
                measured, filtered, predicted = (part[key + suffix][b] for key in MEASUREMENTS)
                path = self.figures_dir / f"sequence_{int(index):05d}{suffix}.png"
                title = (
                    f"sequence {int(index)}{' ' + stream if stream else ''}: {pl_module.method_name}, "
                    f"{len(filtered)} given, {len(predicted)} forecast"
                )
                self._draw_one(measured, filtered, predicted, title, path)
            self._drawn += 1

    @staticmethod
    def _draw_one(measured: np.ndarray, filtered: np.ndarray, predicted: np.ndarray, title: str, path: Path) -> None:
        from ssm_ms import drawing
        from ssm_ms.forecasting import figures

        if measured.ndim == 2:  # vectors [T, D]
            drawing.save_figure(figures.forecast_figure(measured, filtered, predicted, title), path)
        else:  # images [T, C, H, W]: given then following frames over the model's frames
            model = np.concatenate([filtered, predicted])
            truth = np.ones_like(model)  # blank where the file holds nothing after the given frames
            shown = min(len(measured), len(model))
            truth[:shown] = measured[:shown]
            every = max(1, len(model) // 20)
            mosaic = drawing.prediction_mosaic(
                torch.from_numpy(truth), torch.from_numpy(model), len(filtered), every=every
            )
            drawing.save_png(mosaic, path, scale=max(1, 96 // truth.shape[-1]))
