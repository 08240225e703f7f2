"""The paper's forecasting protocol, for any forecaster: given the first ``k`` measurements of an unseen
sequence, predict the next ``p``, and score the prediction.

A forecaster is a :class:`ForecastModule` that implements :meth:`ForecastModule.forecast`: the SSM with
an inference method (:class:`ssm_ms.inference.SSMForecaster`: CNN-LSTM encoder, UKF, particle filter;
the prediction of ``y[k + j]`` is ``g(f^{j+1}(x[k-1]))``) or a baseline without an SSM
(:mod:`ssm_ms.baselines`: sequence-to-sequence CNN-LSTM, Recurrent Kalman Network). Everything else --
the split, the metrics, the references, the results files and the figures -- is this one code path.

Frame bookkeeping for a test sequence ``y[0..T-1]``:

* measurements ``y[0..k-1]`` are given to the forecaster, which returns its estimate of them (the
  frames it believes while filtering) and its prediction of ``y[k..k+p-1]`` (``p = T - k`` unless set);
* the prediction is scored against ``y[k..k+p-1]`` (the noisy frames, the paper's convention) and
  against the clean frames when the data set knows them.

Metrics (per test sequence, then mean and std over sequences):

* ``mse``: squared error averaged over the elements of a frame and the predicted frames;
* ``bce``: ``-[t log(p + 1e-12) + (1 - t) log(1 - p + 1e-12)]`` (the reference code's clamping, no
  other clipping), averaged over the pixels of a frame (``bce_reduction: mean``) or summed over them
  (``sum``, the paper's Moving MNIST Table 3 convention), then averaged over predicted frames;
* ``mse_sum``: squared error summed over the elements of a frame, averaged over the predicted frames (the
  per-frame MSE of video-prediction papers and OpenSTL);
* ``ssim`` (images in [0, 1]): the structural similarity of each predicted frame (Wang et al. 2004: an 11 x 11
  Gaussian window of std 1.5, ``C1 = 0.01^2``, ``C2 = 0.03^2``, averaged over the window positions inside
  the frame and over channels, as OpenSTL computes it), averaged over the predicted frames; higher is better.

Two references are computed by the same code so the numbers can be read: ``last`` repeats the
forecaster's estimate of the last given frame (``g(x[k-1])`` for an SSM); ``mean`` predicts the mean
training frame.

Beyond the score (``analysis`` argument, :mod:`ssm_ms.analysis`): the *valid prediction time* of every
forecaster (how many steps its forecast stays within a normalised error of 0.5 of the noiseless truth,
in steps, seconds and Lyapunov times of the true system; for images, the error above the forecaster's own
reconstruction error on its last given frames: see :class:`ValidTimeAccumulator`), and for an SSM what ``f`` is on its own
(:meth:`ssm_ms.inference.SSMForecaster.analyze`: Lyapunov exponents, long free runs against the data).
"""

from __future__ import annotations

import json
import math
import sys
import time
from collections.abc import Mapping, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, NamedTuple, Optional

import lightning.pytorch as pl
import numpy as np
import torch
from torchmetrics import CatMetric

from ssm_ms.checkpointing import restore_float_weights
from ssm_ms.runtime.machine import describe

BCE_EPS = 1e-12
METRICS = ("mse", "bce", "mse_sum", "ssim")
SSIM_WINDOW, SSIM_SIGMA, SSIM_K1, SSIM_K2 = 11, 1.5, 0.01, 0.03
FLOOR_FRAMES = 10  # images: the valid time counts errors above the reconstruction error on the last 10 given frames
# analysis: {section: {key: default}}; a section absent from the config is not computed
ANALYSIS_DEFAULTS: dict[str, dict[str, Any]] = {
    # forecast `horizon` steps after `n_filter` given ones (None: the protocol's split), valid while the
    # normalised error <= threshold (the reservoir-computing convention, Vlachas et al. 2020)
    "valid_time": {"n_filter": None, "horizon": None, "threshold": 0.5},
    # SSMs only: f from `runs` shooting nodes: Lyapunov spectrum, and long free runs from `free_runs` nodes
    # (None: the same `runs`; more runs steady the attractor statistics) (ssm_ms.analysis.dynamics_report)
    "dynamics": {"runs": 16, "free_runs": None, "lyapunov_steps": 4000, "transient": 2000, "align": 600,
                 "free_steps": 20_000, "seed": 0},
    # the true system's exponents, where the data set has its equations (true_transition): from the first
    # states of `runs` test sequences; computed once per data set and settings, cached beside the data
    "true_system": {"runs": 16, "lyapunov_steps": 4000, "transient": 2000, "align": 600},
}


def check_analysis(analysis: Mapping[str, Any] | None) -> dict[str, Any]:
    """The ``analysis`` setting with defaults filled in; unknown sections or keys are refused."""
    if not analysis:
        return {}
    out: dict[str, Any] = {}
    for section, values in analysis.items():
        if section == "dt":
            if values is not None and not float(values) > 0:
                raise ValueError(f"analysis.dt must be > 0 (seconds per step), got {values!r}")
            out["dt"] = None if values is None else float(values)
            continue
        if section not in ANALYSIS_DEFAULTS:
            raise ValueError(f"unknown analysis section {section!r}: choose among {sorted(ANALYSIS_DEFAULTS) + ['dt']}")
        values = dict(values or {})
        unknown = set(values) - set(ANALYSIS_DEFAULTS[section])
        if unknown:
            raise ValueError(f"analysis.{section} takes {sorted(ANALYSIS_DEFAULTS[section])}, got {sorted(unknown)}")
        merged = {**ANALYSIS_DEFAULTS[section], **values}
        for key, value in merged.items():
            least = 0 if key in ("transient", "align", "seed") else 1
            whole = isinstance(value, (int, float)) and not isinstance(value, bool) and int(value) == value
            if value is not None and key != "threshold" and not (whole and value >= least):
                raise ValueError(f"analysis.{section}.{key} must be a whole number >= {least}, got {value!r}")
        if section == "valid_time" and not merged["threshold"] > 0:
            raise ValueError(f"analysis.valid_time.threshold must be > 0, got {merged['threshold']!r}")
        out[section] = merged
    return out


# ---------------------------------------------------------------------------- pure functions
def split_sequence(y: torch.Tensor, n_filter: int, n_predict: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """``y [B, T, ...]`` -> (measurements given to inference ``[B, k, ...]``, frames to predict ``[B, p, ...]``)."""
    t = y.shape[1]
    p = t - n_filter if n_predict is None else n_predict
    if n_filter < 1 or p < 1 or n_filter + p > t:
        raise ValueError(
            f"cannot filter {n_filter} and predict {p} frames of sequences of length {t}: "
            f"choose n_filter + n_predict <= {t} with both >= 1"
        )
    return y[:, :n_filter], y[:, n_filter : n_filter + p]


def mse_per_sequence(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """``[B, p, ...]`` -> ``[B]``: squared error averaged over frame elements and frames."""
    return (pred - target).pow(2).flatten(1).mean(1)


def bce_per_sequence(pred: torch.Tensor, target: torch.Tensor, reduction: str = "mean") -> torch.Tensor:
    """``[B, p, ...]`` -> ``[B]``: binary cross-entropy per frame (mean or sum over its elements), averaged over frames."""
    if reduction not in ("mean", "sum"):
        raise ValueError(f"bce_reduction must be 'mean' or 'sum', got {reduction!r}")
    e = -(target * torch.log(pred + BCE_EPS) + (1 - target) * torch.log(1 - pred + BCE_EPS))
    per_frame = e.flatten(2)
    per_frame = per_frame.mean(2) if reduction == "mean" else per_frame.sum(2)
    return per_frame.mean(1)


def mse_sum_per_sequence(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """``[B, p, ...]`` -> ``[B]``: squared error summed over a frame's elements, averaged over frames."""
    return (pred - target).pow(2).flatten(2).sum(2).mean(1)


def ssim_per_sequence(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """``[B, p, C, H, W]`` images in [0, 1] -> ``[B]``: each frame's SSIM (see the module doc: the window positions
    that lie inside the frame, no padding), averaged over frames. Computed in float64."""
    if pred.dim() != 5 or min(pred.shape[-2:]) < SSIM_WINDOW:
        raise ValueError(f"metric 'ssim' needs image frames [B, T, C, H, W] of at least {SSIM_WINDOW} x {SSIM_WINDOW} "
                         f"pixels, got {list(pred.shape)}: leave 'ssim' out of metrics for this data")
    b, p, c, h, w = pred.shape
    x = pred.detach().reshape(b * p * c, 1, h, w).double()
    y = target.detach().reshape(b * p * c, 1, h, w).double()
    r = torch.arange(SSIM_WINDOW, dtype=torch.float64, device=x.device) - SSIM_WINDOW // 2
    g = torch.exp(-(r**2) / (2 * SSIM_SIGMA**2))
    g = g / g.sum()
    window = (g[:, None] * g[None, :])[None, None]
    mu_x, mu_y, xx, yy, xy = torch.nn.functional.conv2d(torch.cat([x, y, x * x, y * y, x * y]), window).split(len(x))
    var_x, var_y, cov = xx - mu_x**2, yy - mu_y**2, xy - mu_x * mu_y
    c1, c2 = SSIM_K1**2, SSIM_K2**2
    ssim = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2))
    return ssim.reshape(b, p, -1).mean(2).mean(1).to(pred.dtype)


def sequence_metrics(pred: torch.Tensor, target: torch.Tensor, metrics: Sequence[str], bce_reduction: str) -> dict[str, torch.Tensor]:
    """``{metric: [B]}`` for the names in ``metrics`` (see :data:`METRICS` and the module doc)."""
    per_sequence = {
        "mse": mse_per_sequence,
        "bce": lambda p, t: bce_per_sequence(p, t, bce_reduction),
        "mse_sum": mse_sum_per_sequence,
        "ssim": ssim_per_sequence,
    }
    return {name: per_sequence[name](pred, target) for name in metrics}


# ---------------------------------------------------------------------------- the protocol
class Forecast(NamedTuple):
    """What a forecaster returns for measurements ``y[0..k-1]`` and ``p`` steps to predict.

    ``filtered [B, k, *obs_shape]``: its estimate of the given measurements (what it believes while
    filtering; the ``last`` reference repeats ``filtered[:, -1]``); ``predicted [B, p, *obs_shape]``: its
    prediction of ``y[k..k+p-1]``; ``states [B, k + p, d]``: latent states behind them, where the
    forecaster has states it can show (the SSM's inferred then predicted states), else ``None``;
    ``state_covs [B, k + p, d, d]``: their covariances, where the forecaster has them (the filters, from
    :meth:`ForecastModule.forecast_distribution` only), else ``None``.
    """

    filtered: torch.Tensor
    predicted: torch.Tensor
    states: Optional[torch.Tensor] = None
    state_covs: Optional[torch.Tensor] = None


class ForecastModule(pl.LightningModule):
    """Base of every forecaster: ``test`` runs the protocol on the DataModule's test split; ``predict``
    forecasts a user's own sequences (the DataModule's ``predict_path``) with the same :meth:`forecast`,
    in original units, written by :class:`ssm_ms.forecasting.writer.ForecastWriter` (see :meth:`predict_step`).

    Subclasses implement :meth:`forecast` (and :meth:`describe` to say what they are). Results go to
    TensorBoard (``test/...``), to ``<results_dir>/<experiment>.json`` and to a markdown table
    ``<results_dir>/<experiment>.md`` with the paper's values beside ours; figures to TensorBoard and,
    with ``figures_dir``, to PNG/GIF.

    Args:
        n_filter: measurements given to the forecaster (pendulum 50, Moving MNIST 10, Lorenz 1990).
        n_predict: frames predicted after them (default: the rest of the sequence).
        metrics: among ``"mse"``, ``"bce"``, ``"mse_sum"``, ``"ssim"`` (see the module doc).
        bce_reduction: ``"mean"`` over the pixels of a frame, or ``"sum"`` (Moving MNIST convention).
        original_units: undo the data normalisation before scoring (Lorenz: MSE in original units).
        experiment: name of the results files (default: the data set's name).
        results_dir: where the results files go.
        figures_dir: if set, PNG / GIF figures are written there too.
        method_name: the key of this forecaster in the results files (default: :attr:`method_kind`).
        analysis: what to compute beyond the score (default: nothing): ``valid_time`` (any forecaster),
            ``dynamics`` (SSMs), ``dt`` (seconds per step, default the data set's ``sample_period``); see
            :data:`ANALYSIS_DEFAULTS`, e.g. ``{valid_time: {n_filter: 1000, horizon: 1000}, dynamics: {}}``.
    """

    method_kind = "model"

    def __init__(
        self,
        n_filter: int,
        n_predict: int | None = None,
        metrics: Sequence[str] = ("mse", "bce"),
        bce_reduction: str = "mean",
        original_units: bool = False,
        experiment: str | None = None,
        results_dir: str = "results",
        figures_dir: str | None = None,
        method_name: str | None = None,
        analysis: dict[str, Any] | None = None,
    ):
        super().__init__()
        self.save_hyperparameters()  # with the subclass's arguments too
        bad = [m for m in metrics if m not in METRICS]
        if bad:
            raise ValueError(f"unknown metrics {bad}: choose among {list(METRICS)}")
        if bce_reduction not in ("mean", "sum"):
            raise ValueError(f"bce_reduction must be 'mean' or 'sum', got {bce_reduction!r}")
        if n_filter < 1:
            raise ValueError(f"n_filter must be >= 1, got {n_filter}")
        if n_predict is not None and n_predict < 1:
            raise ValueError(f"n_predict must be >= 1 (or unset: the rest of each sequence), got {n_predict}")
        # plain attributes: under LightningCLI, hparams hold only what the config set
        self.n_filter, self.n_predict = int(n_filter), n_predict
        self.bce_reduction, self.original_units = bce_reduction, bool(original_units)
        self.experiment, self.results_dir, self.figures_dir = experiment, results_dir, figures_dir
        self.metric_names = list(metrics)
        self.method_name = method_name or self.method_kind
        self.analysis_settings = check_analysis(analysis)
        self._metrics = torch.nn.ModuleDict()
        self._first_batch: dict[str, torch.Tensor] | None = None
        self._mean_frame: torch.Tensor | None = None

    # ------------------------------------------------------------------ to implement
    def forecast(self, y_filter: torch.Tensor, n_predict: int) -> Forecast:
        """Estimate of ``y_filter [B, k, *obs_shape]`` and prediction of the ``n_predict`` frames after it."""
        raise NotImplementedError

    def forecast_distribution(self, y_filter: torch.Tensor, n_predict: int) -> Forecast:
        """:meth:`forecast` with the states' covariances where the forecaster has them (``predict`` calls
        this one; the test protocol, which needs no covariances, calls :meth:`forecast`)."""
        return self.forecast(y_filter, n_predict)

    def describe(self) -> dict[str, Any]:
        """What this forecaster is, for the results: ``model`` (e.g. ``"SSM-LL"``, ``"LSTM"``), ``inference``
        (e.g. ``"encoder"``, ``"ukf"``, or ``None``), ``label`` (its row in the table) and any checkpoint it reads."""
        return {"model": type(self).__name__, "inference": None, "label": self.method_name}

    def inference_settings(self) -> str | None:
        """One line on how states are inferred, recorded with the results (``None``: nothing to add)."""
        return None

    def forecast_figures(self, first: dict[str, torch.Tensor]) -> dict[str, Any]:
        """Figures of this kind of forecaster (``{name: Figure}``) from the first test batch, beside the protocol's."""
        return {}

    # ------------------------------------------------------------------ set-up
    @property
    def datamodule(self):
        return getattr(self.trainer, "datamodule", None) if self._trainer is not None else None

    def setup(self, stage: str) -> None:
        """Refuse, before any work, a split that does not fit the test sequences, and ``ssim`` on data that are not
        images it can score."""
        if stage == "predict":
            self.prediction_split()
        obs_shape = getattr(self.datamodule, "obs_shape", None) if "ssim" in self.metric_names and stage in ("fit", "test") else None
        if obs_shape is not None:
            ssim_per_sequence(torch.zeros(1, 1, *obs_shape), torch.zeros(1, 1, *obs_shape))
        test = getattr(self.datamodule, "datasets", {}).get("test") if stage == "test" else None
        seq_len = getattr(test, "seq_len", None)
        if seq_len is not None:
            split_sequence(torch.zeros(1, seq_len, 1), self.n_filter, self.n_predict)
            if "valid_time" in self.analysis_settings:
                split_sequence(torch.zeros(1, seq_len, 1), *self._valid_time_split(seq_len))

    def normalizer(self):
        dm = self.datamodule
        return getattr(dm, "normalizer", None)

    def mean_frame(self) -> torch.Tensor:
        """Mean training measurement ``[*obs_shape]`` in normalised units (the data set's, saved in checkpoints)."""
        if self._mean_frame is None:
            dm, norm = self.datamodule, self.normalizer()
            mean = dm.mean_measurement()
            self._mean_frame = mean if norm is None else norm.normalize(mean)
        return self._mean_frame

    # ------------------------------------------------------------------ test
    def _record(self, key: str, values: torch.Tensor) -> None:
        name = key.replace("/", "__")  # ModuleDict keys cannot hold "/"
        if name not in self._metrics:
            self._metrics[name] = CatMetric(nan_strategy="disable").to(values.device)  # NaN: a diverged forecast
        self._metrics[name].update(values.detach())

    def on_test_epoch_start(self) -> None:
        self._start_time = time.time()
        self._metrics = torch.nn.ModuleDict()
        self._first_batch = None
        self._valid_time = ValidTimeAccumulator() if "valid_time" in self.analysis_settings else None

    @torch.no_grad()
    def test_step(self, batch: Mapping[str, torch.Tensor], batch_idx: int) -> None:
        k = self.n_filter
        y_filter, y_future = split_sequence(batch["y"], k, self.n_predict)
        p = y_future.shape[1]
        out = self.forecast(y_filter, p)
        if tuple(out.predicted.shape) != tuple(y_future.shape) or tuple(out.filtered.shape) != tuple(y_filter.shape):
            raise RuntimeError(
                f"{type(self).__name__}.forecast returned frames of shapes {list(out.filtered.shape)} and "
                f"{list(out.predicted.shape)} for {list(y_filter.shape)} given and {list(y_future.shape)} to predict"
            )
        preds = {
            self.method_name: out.predicted,
            "last": out.filtered[:, -1:].expand_as(y_future),
            "mean": self.mean_frame().to(y_future).expand_as(y_future),
        }
        targets = {"noisy": y_future}
        if "y_clean" in batch:
            targets["clean"] = batch["y_clean"][:, k : k + p]
        norm = self.normalizer()
        if self.original_units and norm is not None:
            preds = {name: norm.denormalize(v) for name, v in preds.items()}
            targets = {name: norm.denormalize(v) for name, v in targets.items()}
        for method, pred in preds.items():
            for target_name, target in targets.items():
                scores = sequence_metrics(pred, target, self.metric_names, self.bce_reduction)
                for metric, values in scores.items():
                    self._record(f"{method}/{target_name}/{metric}", values)
        if self._valid_time is not None:
            k_v, h = self._valid_time_split(batch["y"].shape[1])
            out_v = out if (k_v, h) == (k, p) else self.forecast(batch["y"][:, :k_v], h)
            truth = batch["y_clean" if "y_clean" in batch else "y"]
            m = min(FLOOR_FRAMES, k_v)
            pred, given, truth, truth_given = out_v.predicted, out_v.filtered[:, -m:], truth[:, k_v : k_v + h], truth[:, k_v - m : k_v]
            if self.original_units and norm is not None:
                pred, truth = norm.denormalize(pred), norm.denormalize(truth)
                given, truth_given = norm.denormalize(given), norm.denormalize(truth_given)
            self._valid_time.update(pred, truth, clean="y_clean" in batch, given=(given, truth_given))
        if self._first_batch is None:  # kept for the figures
            self._first_batch = {key: batch[key][:, : k + p] for key in ("y", "y_clean", "state") if key in batch}
            self._first_batch["y_model"] = torch.cat([out.filtered, out.predicted], 1)
            if out.states is not None:
                self._first_batch["states"] = out.states

    # ------------------------------------------------------------------ predict
    def prediction_split(self, seq_len: int | None = None) -> tuple[int | None, int]:
        """``(k, p)`` of ``predict``: the DataModule's ``predict_given`` (``None``: all ``seq_len`` samples)
        and ``predict_steps``, else this forecaster's ``n_predict``."""
        dm = self.datamodule
        k = getattr(dm, "predict_given", None)
        p = getattr(dm, "predict_steps", None) or self.n_predict
        if p is None:
            raise ValueError(
                "how many steps to forecast? set --data.init_args.predict_steps P (this forecaster has no n_predict)"
            )
        return (k or seq_len), int(p)

    @torch.no_grad()
    def predict_step(self, batch: Mapping[str, torch.Tensor], batch_idx: int) -> dict[str, torch.Tensor]:
        """Forecast a batch of a user's sequences: the first ``k`` samples are given, ``p`` steps are predicted
        (:meth:`prediction_split`), by the same :meth:`forecast` as the test protocol. Measurements come back
        in original units (the data normalisation undone); states and their covariances in the model's.

        Returns ``{"index" [B], "measured" [B, T, *obs] (the sequence as given, original units), "filtered"
        [B, k, *obs], "predicted" [B, p, *obs]}``, plus ``"states" [B, k, d]``, ``"predicted_states" [B, p,
        d]`` where the forecaster has states and ``"state_cov" [B, k, d, d]``, ``"predicted_state_cov" [B, p,
        d, d]`` where it has covariances.
        """
        y = batch["y"]
        k, p = self.prediction_split(y.shape[1])
        out = self.forecast_distribution(y[:, :k], p)
        expected = (tuple(y[:, :k].shape), (len(y), p, *y.shape[2:]))
        if (tuple(out.filtered.shape), tuple(out.predicted.shape)) != expected:
            raise RuntimeError(
                f"{type(self).__name__}.forecast returned frames of shapes {list(out.filtered.shape)} and "
                f"{list(out.predicted.shape)} for {list(expected[0])} given and {list(expected[1])} to predict"
            )
        norm = self.normalizer()
        to_units = norm.denormalize if norm is not None else (lambda t: t)
        result = {"index": batch["index"], "measured": to_units(y), "filtered": to_units(out.filtered),
                  "predicted": to_units(out.predicted)}
        if out.states is not None:
            result["states"], result["predicted_states"] = out.states[:, :k], out.states[:, k:]
        if out.state_covs is not None:
            result["state_cov"], result["predicted_state_cov"] = out.state_covs[:, :k], out.state_covs[:, k:]
        return result

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """A pretrained file's int8 weights become float32 before Lightning loads them (``--weights int8``)."""
        restore_float_weights(checkpoint)

    def configure_callbacks(self):
        """``predict`` without a :class:`~ssm_ms.forecasting.writer.ForecastWriter` among the trainer's callbacks gets one
        writing ``predictions/<experiment>_<method>.npz``."""
        from ssm_ms.forecasting.writer import ForecastWriter

        if self.trainer.state.fn != "predict" or any(isinstance(c, ForecastWriter) for c in self.trainer.callbacks):
            return []
        return [ForecastWriter(f"predictions/{self.experiment_name()}_{self.method_name}.npz")]

    def on_test_epoch_end(self) -> None:
        summary: dict[str, dict[str, float]] = {}
        for name, metric in self._metrics.items():
            key = name.replace("__", "/")
            summary[key] = sequence_summary(metric.compute())
            self.log(f"test/{key}", summary[key]["mean"])
        analysis = self.analyze() if self.trainer.is_global_zero and self.analysis_settings else {}
        for name, value in flat_scalars(analysis).items():
            self.log(f"analysis/{name}", value, rank_zero_only=True)
        if self.trainer.is_global_zero:
            self.write_results(summary, analysis)
            self.log_figures()

    # ------------------------------------------------------------------ analysis
    def _valid_time_split(self, seq_len: int) -> tuple[int, int]:
        vt = self.analysis_settings["valid_time"]
        k = vt["n_filter"] or self.n_filter
        return k, vt["horizon"] or self.n_predict or seq_len - k

    def sample_period(self) -> float | None:
        """Seconds per step: ``analysis.dt``, else the data set's ``sample_period`` (``None``: unknown)."""
        dt = self.analysis_settings.get("dt") or getattr(self.datamodule, "sample_period", None)
        return None if dt is None else float(dt)

    def analyze(self) -> dict[str, Any]:
        """What the ``analysis`` setting asks for, as a JSON-ready dict (written beside the scores)."""
        from ssm_ms.analysis import summarize_valid_time

        out: dict[str, Any] = {}
        reference = reference_exponents(
            self.datamodule, self.analysis_settings.get("true_system", ANALYSIS_DEFAULTS["true_system"])
        )
        if reference is not None:
            out["true_system"] = reference
        if self._valid_time is not None and self._valid_time.count:
            settings = self.analysis_settings["valid_time"]
            steps, horizon = self._valid_time.steps(settings["threshold"])
            dt = self.sample_period()
            largest = reference["largest"] if reference else None
            vt = summarize_valid_time(steps, horizon, dt or 1.0, largest)
            if dt is None:
                vt = {k: v for k, v in vt.items() if "seconds" not in k and "lyapunov" not in k}
            vt.update(threshold=settings["threshold"], n_filter=settings["n_filter"] or self.n_filter,
                      truth="noiseless" if self._valid_time.clean else "noisy", dt=dt,
                      error_at_step=self._valid_time.growth(), given_error=self._valid_time.floor())
            out["valid_time"] = vt
        return out

    # ------------------------------------------------------------------ output
    def experiment_name(self) -> str:
        if self.experiment:
            return self.experiment
        dm = self.datamodule
        return getattr(dm, "name", "experiment")

    def write_results(self, summary: dict[str, dict[str, float]], analysis: dict[str, Any] | None = None) -> None:
        from ssm_ms.forecasting.results import (
            write_results,  # the tables of the paper live there
        )

        info = {
            "experiment": self.experiment_name(),
            "method": self.method_name,
            **self.describe(),
            "n_filter": self.n_filter,
            "n_predict": self.n_predict if self.n_predict is not None else "the rest of each sequence",
            "metrics": self.metric_names,
            "bce_reduction": self.bce_reduction,
            "bce_clamp": f"log(p + {BCE_EPS:g}), log(1 - p + {BCE_EPS:g})",
            "original_units": self.original_units,
            "test_sequences": self._test_sequences(summary),
            "data": getattr(self, "data_note", None),
            "inference_settings": self.inference_settings(),
            "command": " ".join(sys.argv),
            "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "machine": describe(),
            "test_seconds": round(time.time() - getattr(self, "_start_time", time.time()), 1),
        }
        write_results(Path(self.results_dir), info, summary, analysis or None)

    @staticmethod
    def _test_sequences(summary: dict[str, dict[str, float]]) -> int | None:
        """How many test sequences were scored (the metrics' count)."""
        counts = [entry["n"] for entry in summary.values() if isinstance(entry, dict) and "n" in entry]
        return int(max(counts)) if counts else None

    def log_figures(self) -> None:
        from ssm_ms.forecasting.figures import (
            log_forecast_figures,  # matplotlib: loaded when figures are drawn
        )

        if self._first_batch is not None:
            log_forecast_figures(self, self._first_batch)


class ValidTimeAccumulator:
    """Squared forecast errors per sequence and step, and the truth's statistics, over the test batches.

    The valid time needs the scale of the truth over the whole test set, known only at the end: errors are
    kept per step and thresholded in :meth:`steps`. Vectors: per component ``[B, h, D]``, each scaled by its
    std. Images: pooled, the mean squared error over the pixels ``[B, h, 1]`` scaled by the mean per-pixel
    variance, so that, as for vectors, a normalised error of 1 is as bad as predicting the mean frame (and
    background pixels that never change divide nothing).

    Images, in excess of the method's own floor: a decoder's reconstruction of frames it was given is already
    blurred (the full-size pendulum SSM: normalised error ~0.5 on the given frames), which would make every
    image forecast "invalid" from its first frame. So for images the error of a step is the part above the
    sequence's reconstruction error on its last :data:`FLOOR_FRAMES` given frames (the ``given`` pairs of
    :meth:`update`): ``sqrt(max(mse_t - mse_given, 0) / mean pixel variance)``. Valid while the forecast
    has lost no more than that to its reconstruction; a forecast that drifts off the object's phase soon
    exceeds it. Vectors keep the convention's plain error (no floor).
    """

    def __init__(self) -> None:
        self.errors: list[torch.Tensor] = []
        self.floors: list[torch.Tensor] = []
        self.total = self.total_sq = None
        self.count = 0
        self.clean = True
        self.pooled = False

    def update(
        self,
        pred: torch.Tensor,
        truth: torch.Tensor,
        clean: bool = True,
        given: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> None:
        """Add a batch: predictions and truth ``[B, h, *obs_shape]``; ``clean``: the truth is noiseless;
        ``given``: the method's estimate of its last given measurements and their truth ``[B, m, *obs_shape]``
        (images: the floor; without it, none)."""
        self.clean = self.clean and clean
        pred, truth = pred.double(), truth.double()
        self.pooled = truth.dim() > 3
        sq = (pred - truth).pow(2)
        if self.pooled:  # images
            sq = sq.flatten(2).mean(2, keepdim=True)
            floor = torch.zeros(len(sq), dtype=torch.float64)
            if given is not None:
                floor = (given[0].double() - given[1].double()).pow(2).flatten(1).mean(1).cpu()
            self.floors.append(floor)
        self.errors.append(sq.cpu())
        values = truth.flatten(2).reshape(-1, truth[0, 0].numel())
        total, total_sq = values.sum(0).cpu(), values.pow(2).sum(0).cpu()
        self.total = total if self.total is None else self.total + total
        self.total_sq = total_sq if self.total_sq is None else self.total_sq + total_sq
        self.count += len(values)

    def _variance(self) -> torch.Tensor:
        mean = self.total / self.count
        var = (self.total_sq / self.count - mean.pow(2)).clamp_min(0)
        return (var.mean(0, keepdim=True) if self.pooled else var).clamp_min(1e-30)

    def normalised_errors(self) -> torch.Tensor:
        """``[N, h]``: each test sequence's normalised error at each forecast step (images: above its floor)."""
        errors = torch.cat(self.errors)  # [N, h, D or 1]
        if self.pooled:
            errors = (errors - torch.cat(self.floors)[:, None, None]).clamp_min(0)
        return (errors / self._variance()).mean(-1).sqrt()

    def floor(self) -> float | None:
        """Images: the mean normalised reconstruction error on the given frames, ``sqrt(mse_given / var)``."""
        if not self.pooled:
            return None
        return float((torch.cat(self.floors) / self._variance()).sqrt().mean())

    def steps(self, threshold: float) -> tuple[torch.Tensor, int]:
        """Valid steps per test sequence ``[N]`` (``inf``: valid over the whole horizon) and the horizon."""
        from ssm_ms.analysis import valid_steps

        errors = self.normalised_errors()
        return valid_steps(errors, threshold), errors.shape[1]

    def growth(self) -> dict[str, float]:
        """The mean normalised error at the first, a quarter, half and last forecast step: how errors grow.

        Over the sequences whose forecast stayed finite at every step: a diverged one is left out, as the scores
        leave it out (NaN where none stayed finite)."""
        errors = self.normalised_errors()
        curve = errors[torch.isfinite(errors).all(1)].mean(0)
        h = len(curve)
        return {str(step): float(curve[step - 1]) for step in sorted({1, max(1, h // 4), max(1, h // 2), h})}


def sequence_summary(values: torch.Tensor) -> dict[str, float]:
    """``{"mean", "std", "n", "non_finite"}`` of per-sequence scores: ``n`` sequences, of which ``non_finite`` scored
    NaN or inf (a forecast that diverged); mean and std are over the finite ones (NaN when none is)."""
    values = torch.as_tensor(values).flatten().double()
    finite = values[torch.isfinite(values)]
    mean, std = (finite.mean().item(), finite.std(unbiased=False).item()) if finite.numel() else (math.nan, math.nan)
    return {"mean": mean, "std": std, "n": values.numel(), "non_finite": values.numel() - finite.numel()}


def reference_exponents(dm: Any, settings: Mapping[str, int] | None = None) -> dict[str, Any] | None:
    """The true system's Lyapunov exponents per time unit, where the data set can give them: computed from
    its own equations (``true_transition``, from the first states of the test sequences; ``settings`` as
    ``ANALYSIS_DEFAULTS["true_system"]``) and cached in the data set's cache folder, or stated
    (``known_largest_exponent``, e.g. 0 for the undamped simple pendulum)."""
    if dm is None:
        return None
    if callable(getattr(dm, "true_transition", None)) and getattr(dm, "sample_period", None):
        from ssm_ms.analysis import lyapunov_spectrum

        settings = dict(settings or ANALYSIS_DEFAULTS["true_system"])
        name = "true_exponents_" + "_".join(f"{k}{v}" for k, v in sorted(settings.items())) + ".json"
        cache = Path(dm.cache_dir) / name if hasattr(dm, "cache_dir") else None
        if cache is not None and cache.is_file():
            try:
                return json.loads(cache.read_text())
            except ValueError:  # cut short (a run stopped while it wrote it): computed again below
                pass
        test = dm.datasets.get("test") if hasattr(dm, "datasets") else None
        states = getattr(test, "arrays", {}).get("state") if test is not None else None
        if states is None:
            return None
        x0 = torch.from_numpy(np.array(states[: settings["runs"], 0], dtype=np.float64))
        res = lyapunov_spectrum(dm.true_transition(), x0, steps=settings["lyapunov_steps"], dt=float(dm.sample_period),
                                transient=settings["transient"], align=settings["align"])
        result = {"exponents": res.exponents.tolist(), "largest": float(res.exponents[0]),
                  "source": f"the data set's equations, Benettin QR over {len(x0)} runs of {settings['lyapunov_steps']} steps"}
        if cache is not None:
            cache.write_text(json.dumps(result))
        return result
    if getattr(dm, "known_largest_exponent", None) is not None:
        return {"largest": float(dm.known_largest_exponent), "source": "known for this system"}
    return None


def flat_scalars(tree: Mapping[str, Any], prefix: str = "") -> dict[str, float]:
    """Numeric leaves of a nested dict as ``{"a/b": value}`` (lists give ``a/b/0``, ...), for TensorBoard."""
    out: dict[str, float] = {}
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(flat_scalars(value, name + "/"))
        elif isinstance(value, (list, tuple)):
            out.update({f"{name}/{i}": float(v) for i, v in enumerate(value) if isinstance(v, (int, float))})
        elif isinstance(value, (int, float)) and not isinstance(value, bool) and np.isfinite(value):
            out[name] = float(value)
    return out
