"""The paper's forecasting protocol, for any forecaster: given the first ``k`` measurements of an unseen
sequence, predict the next ``p``, and score the prediction.

A forecaster is a :class:`ForecastModule` that implements :meth:`ForecastModule.forecast`: the SSM with
an inference method (:class:`ssm_ms.inference.SSMForecaster`: CNN-LSTM encoder, UKF, particle filter, a fit;
the prediction of ``y[k + j]`` is ``g(f^{j+1}(x[k-1]))``) or a baseline without an SSM
(:mod:`ssm_ms.baselines`: sequence-to-sequence CNN-LSTM, Recurrent Kalman Network). Everything else --
the split, the metrics, the references, the results files and the figures -- is this one code path.

Each test batch (:meth:`ForecastModule.test_step`) is split (the first ``k`` measurements given, the next
``p`` to predict: :func:`~ssm_ms.forecasting.metrics.split_sequence`), forecast, and each prediction is
scored against each target by :func:`~ssm_ms.forecasting.metrics.sequence_metrics` (the metrics:
:mod:`ssm_ms.forecasting.metrics`). The predictions: the forecaster's, and two references computed by the
same code so the numbers can be read: ``last`` repeats the forecaster's estimate of the last given frame
(``g(x[k-1])`` for an SSM); ``mean`` predicts the mean training frame. The targets: the noisy frames (the
paper's convention), and the clean frames when the data set knows them.

Beyond the score (the ``analysis`` argument, read as an
:class:`~ssm_ms.forecasting.analysis_settings.AnalysisSettings`): the *valid prediction time* of every
forecaster (:mod:`ssm_ms.forecasting.valid_time`: how many steps its forecast stays within a normalised error
of 0.5 of the noiseless truth, in steps, seconds and Lyapunov times of the true system), and for an SSM what
``f`` is on its own (:meth:`ssm_ms.inference.SSMForecaster.analyze`: Lyapunov exponents, long free runs
against the data; :mod:`ssm_ms.analysis`).
"""

from __future__ import annotations

import sys
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from datetime import datetime, timezone
from typing import Any, NamedTuple

import lightning.pytorch as pl
import torch
from torchmetrics import CatMetric

from ssm_ms.checkpointing import restore_float_weights
from ssm_ms.forecasting.analysis_settings import AnalysisOptions, AnalysisSettings
from ssm_ms.forecasting.metrics import (
    BCE_EPS,
    METRICS,
    flat_scalars,
    sequence_metrics,
    sequence_summary,
    split_sequence,
    ssim_per_sequence,
)
from ssm_ms.forecasting.valid_time import (
    ValidTimeAccumulator,
    reference_exponents,
    valid_time_split,
)
from ssm_ms.nets.sensors import SensorLayout
from ssm_ms.runtime.machine import describe


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
    states: torch.Tensor | None = None
    state_covs: torch.Tensor | None = None


class ForecastModule(pl.LightningModule):
    """Base of every forecaster: ``test`` runs the protocol on the DataModule's test split; ``predict``
    forecasts a user's own sequences (the DataModule's ``predict_path``) with the same :meth:`forecast`,
    in original units, written by :class:`ssm_ms.forecasting.writer.ForecastWriter` (see :meth:`predict_step`).

    Subclasses implement :meth:`forecast` (and :meth:`describe` to say what they are). Results go to
    TensorBoard (``test/...``) and to ``<results_dir>/<experiment>.json`` (:mod:`ssm_ms.forecasting.results`; the
    repository's ``python cli.py`` renders its markdown report beside it); figures to TensorBoard and, with
    ``figures_dir``, to PNG/GIF.

    Args:
        n_filter: measurements given to the forecaster (pendulum 50, Moving MNIST 10, Lorenz 1990).
        n_predict: frames predicted after them (default: the rest of the sequence).
        metrics: among ``"mse"``, ``"bce"``, ``"mse_sum"``, ``"ssim"`` (see :mod:`ssm_ms.forecasting.metrics`).
        bce_reduction: ``"mean"`` over the pixels of a frame, or ``"sum"`` (Moving MNIST convention).
        original_units: undo the data normalisation before scoring (Lorenz: MSE in original units).
        experiment: name of the results files (default: the data set's name).
        results_dir: where the results file goes (default: the run's own folder, the trainer's ``log_dir``; the
            shipped configs name ``results``).
        figures_dir: if set, PNG / GIF figures are written there too.
        method_name: the key of this forecaster in the results files (default: :attr:`method_kind`).
        analysis: what to compute beyond the score (default: nothing): a mapping of ``valid_time`` (any
            forecaster), ``dynamics`` (SSMs), ``true_system``, ``dt`` (seconds per step, default the data set's
            ``sample_period``), e.g. ``{valid_time: {n_filter: 1000, horizon: 1000}, dynamics: {}}``, checked
            against :class:`~ssm_ms.forecasting.analysis_settings.AnalysisSettings` (its module doc: what a
            section left out or given as ``{}`` means); from Python, an ``AnalysisSettings`` is taken too.
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
        results_dir: str | None = None,
        figures_dir: str | None = None,
        method_name: str | None = None,
        analysis: AnalysisOptions | None = None,
    ):
        super().__init__()
        with warnings.catch_warnings():  # Lightning's advice to ignore a module given as ssm_checkpoint: done below
            warnings.filterwarnings("ignore", message=".*is an instance of `nn.Module`")
            self.save_hyperparameters()  # with the subclass's arguments too
        for hparams in (self._hparams, self._hparams_initial):  # a model object given from Python is no setting
            for key, value in list(hparams.items()):
                if isinstance(value, torch.nn.Module) or isinstance(getattr(value, "module", None), torch.nn.Module):
                    hparams[key] = None
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
        self.sensor_layout: SensorLayout | None = None  # several sensors: the data's, at setup (scored per stream)
        self.method_name = method_name or self.method_kind
        self.analysis_settings: AnalysisSettings | None = AnalysisSettings.of(analysis)  # None: no analysis
        if isinstance(analysis, AnalysisSettings):  # checkpoints hold plain values (read with weights_only)
            self.hparams["analysis"] = analysis.as_dict()
        self._metrics = torch.nn.ModuleDict()
        self._first_batch: dict[str, torch.Tensor] | None = None
        self._mean_frame: torch.Tensor | None = None
        self._valid_time: ValidTimeAccumulator | None = None

    # inputs per step the forecaster's model is driven by (0: an autonomous system); the data must have as many
    input_dim = 0

    # ------------------------------------------------------------------ to implement
    def forecast(self, y_filter: torch.Tensor, n_predict: int, u: torch.Tensor | None = None) -> Forecast:
        """Estimate of ``y_filter [B, k, *obs_shape]`` and prediction of the ``n_predict`` frames after it; for a
        driven model, under the inputs ``u [B, k + n_predict - 1, m]``: ``u[:, t]`` moves the system from ``t`` to
        ``t + 1``, the given ones first, then those of the forecast."""
        raise NotImplementedError

    def forecast_distribution(self, y_filter: torch.Tensor, n_predict: int, u: torch.Tensor | None = None) -> Forecast:
        """:meth:`forecast` with the states' covariances where the forecaster has them (``predict`` calls
        this one; the test protocol, which needs no covariances, calls :meth:`forecast`)."""
        return self.forecast(y_filter, n_predict, u)

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
        data_inputs = int(getattr(self.datamodule, "input_dim", 0) or 0)
        if self.datamodule is not None and data_inputs != self.input_dim:
            raise ValueError(
                f"{type(self).__name__} forecasts a system driven by {self.input_dim} inputs per step but the data have "
                f"{data_inputs}: "
                + (
                    "this forecaster takes no inputs; test a model with input_dim > 0 on these data"
                    if self.input_dim == 0
                    else "give the data their inputs (FileDataModule: input_key)"
                )
            )
        layout = getattr(self.datamodule, "sensor_layout", None)
        self.sensor_layout = SensorLayout.from_state_dict(layout) if layout else None
        if "ssim" in self.metric_names and stage in ("fit", "test") and self.datamodule is not None:
            shapes = [tuple(self.datamodule.obs_shape)]
            if self.sensor_layout is not None:  # several sensors: the image streams are scored by ssim
                shapes = [s.shape for s in self.sensor_layout.streams if "ssim" in self.stream_metrics(s.shape)]
            for shape in shapes:
                ssim_per_sequence(torch.zeros(1, 1, *shape), torch.zeros(1, 1, *shape))
        test = getattr(self.datamodule, "datasets", {}).get("test") if stage == "test" else None
        seq_len = getattr(test, "seq_len", None)
        if seq_len is not None:
            split_sequence(torch.zeros(1, seq_len, 1), self.n_filter, self.n_predict)
            if self.analysis_section("valid_time") is not None:
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
    def on_test_epoch_start(self) -> None:
        self._start_time = time.time()
        self._metrics = torch.nn.ModuleDict()
        self._first_batch = None
        self._valid_time = (
            ValidTimeAccumulator(self.sensor_layout) if self.analysis_section("valid_time") is not None else None
        )

    @torch.no_grad()
    def test_step(self, batch: Mapping[str, torch.Tensor], batch_idx: int) -> None:
        """Split, forecast, score each prediction against each target, add to the valid time, and keep the first
        batch for the figures."""
        y_filter, y_future = split_sequence(batch["y"], self.n_filter, self.n_predict)
        out = self.checked_forecast(y_filter, y_future.shape[1], u=batch.get("u"))
        self.score(self.predictions(out, y_future), self.targets(batch, y_future))
        if self._valid_time is not None:
            self.add_to_valid_time(batch, out)
        if self._first_batch is None:
            self._first_batch = self.figure_batch(batch, out)

    def checked_forecast(
        self, y_filter: torch.Tensor, n_predict: int, distribution: bool = False, u: torch.Tensor | None = None
    ) -> Forecast:
        """:meth:`forecast` (or :meth:`forecast_distribution`), refused unless its frames have the shapes of the
        ``y_filter [B, k, *obs]`` given and of the ``[B, n_predict, *obs]`` to predict. A driven forecaster gets
        the first ``k + n_predict - 1`` inputs of ``u``, refused when there are fewer: a forecast needs the inputs
        of its whole horizon."""
        if self.input_dim:
            k, needed = y_filter.shape[1], y_filter.shape[1] + n_predict - 1
            if u is None or u.shape[1] < needed:
                have = "none" if u is None else f"{u.shape[1]}"
                raise ValueError(
                    f"forecasting {n_predict} steps after {k} given samples of a driven system needs the inputs of "
                    f"those {needed} transitions (u[0 .. {needed - 1}]), got {have}: give the future inputs too"
                )
            u = u[:, :needed]
        else:
            u = None
        out = (self.forecast_distribution if distribution else self.forecast)(y_filter, n_predict, u)
        expected = (tuple(y_filter.shape), (len(y_filter), n_predict, *y_filter.shape[2:]))
        if (tuple(out.filtered.shape), tuple(out.predicted.shape)) != expected:
            raise RuntimeError(
                f"{type(self).__name__}.forecast returned frames of shapes {list(out.filtered.shape)} and "
                f"{list(out.predicted.shape)} for {list(expected[0])} given and {list(expected[1])} to predict"
            )
        return out

    def predictions(self, out: Forecast, y_future: torch.Tensor) -> dict[str, torch.Tensor]:
        """``{name: [B, p, *obs]}``: the forecaster's prediction (under its :attr:`method_name`) and the references,
        ``last`` (its estimate of the last given frame, held) and ``mean`` (the mean training frame)."""
        return {
            self.method_name: out.predicted,
            "last": out.filtered[:, -1:].expand_as(y_future),
            "mean": self.mean_frame().to(y_future).expand_as(y_future),
        }

    def targets(self, batch: Mapping[str, torch.Tensor], y_future: torch.Tensor) -> dict[str, torch.Tensor]:
        """``{"noisy": y_future}`` the frames to predict ``[B, p, *obs]``, and ``"clean"``, the same frames without
        the noise, where the data set knows them."""
        k, p = self.n_filter, y_future.shape[1]
        targets = {"noisy": y_future}
        if "y_clean" in batch:
            targets["clean"] = batch["y_clean"][:, k : k + p]
        return targets

    def to_units(self) -> Callable[[torch.Tensor], torch.Tensor] | None:
        """What takes frames to the units they are scored in: the data normalisation undone with ``original_units``
        (``None``: scored as they are)."""
        norm = self.normalizer()
        return norm.denormalize if self.original_units and norm is not None else None

    def score(self, predictions: Mapping[str, torch.Tensor], targets: Mapping[str, torch.Tensor]) -> None:
        """Every metric of each prediction against each target, per sequence, recorded as
        ``<prediction>/<target>/<metric>`` (summarised over the test set at the end: :meth:`on_test_epoch_end`);
        several sensors stream by stream, ``<prediction>/<target>/<stream>/<metric>`` (:meth:`stream_metrics`)."""
        to_units = self.to_units()
        if to_units is not None:
            predictions = {name: to_units(v) for name, v in predictions.items()}
            targets = {name: to_units(v) for name, v in targets.items()}
        layout = self.sensor_layout
        for method, pred in predictions.items():
            for target_name, target in targets.items():
                if layout is None:
                    scores = sequence_metrics(pred, target, self.metric_names, self.bce_reduction)
                    for metric, values in scores.items():
                        self._record(f"{method}/{target_name}/{metric}", values)
                    continue
                # several sensors: each stream in its own shape, its unsampled frames left out
                streams = zip(layout.streams, layout.split(pred).values(), layout.split(target).values())
                for stream, p, t in streams:
                    names = self.stream_metrics(stream.shape)
                    for metric, values in sequence_metrics(p, t, names, self.bce_reduction, missing=True).items():
                        self._record(f"{method}/{target_name}/{stream.name}/{metric}", values)

    def stream_metrics(self, shape: Sequence[int]) -> list[str]:
        """The metrics of one sensor's stream of samples of ``shape``: an image stream ``[C, H, W]`` all of
        :attr:`metric_names`; a vector stream those of them that score any values (``mse``, ``mse_sum``; ``mse``
        where neither is asked), as ``bce`` and ``ssim`` need images in [0, 1]."""
        if len(shape) == 3:
            return list(self.metric_names)
        return [m for m in self.metric_names if m in ("mse", "mse_sum")] or ["mse"]

    def _record(self, key: str, values: torch.Tensor) -> None:
        name = key.replace("/", "__")  # ModuleDict keys cannot hold "/"
        if name not in self._metrics:
            self._metrics[name] = CatMetric(nan_strategy="disable").to(values.device)  # NaN: a diverged forecast
        self._metrics[name].update(values.detach())

    def add_to_valid_time(self, batch: Mapping[str, torch.Tensor], out: Forecast) -> None:
        """The batch's forecasts against the noiseless truth (the noisy frames where the data set has none), over
        the valid time's split: ``out`` where that is the protocol's, else a forecast of its own."""
        y = batch["y"]
        k, h = self._valid_time_split(y.shape[1])
        if (k, h) != (out.filtered.shape[1], out.predicted.shape[1]):
            out = self.checked_forecast(y[:, :k], h, u=batch.get("u"))
        truth = batch["y_clean" if "y_clean" in batch else "y"]
        self._valid_time.add_forecast(
            out.filtered, out.predicted, truth, clean="y_clean" in batch, to_units=self.to_units()
        )

    def figure_batch(self, batch: Mapping[str, torch.Tensor], out: Forecast) -> dict[str, torch.Tensor]:
        """What the figures draw from the first test batch: its sequences up to the forecast's end, the forecaster's
        frames ``y_model`` (estimate, then prediction) and its states where it has them."""
        end = self.n_filter + out.predicted.shape[1]
        first = {key: batch[key][:, :end] for key in ("y", "y_clean", "state") if key in batch}
        first["y_model"] = torch.cat([out.filtered, out.predicted], 1)
        if out.states is not None:
            first["states"] = out.states
        return first

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
        out = self.checked_forecast(y[:, :k], p, distribution=True, u=batch.get("u"))
        norm = self.normalizer()
        to_units = norm.denormalize if norm is not None else (lambda t: t)
        result = {
            "index": batch["index"],
            "measured": to_units(y),
            "filtered": to_units(out.filtered),
            "predicted": to_units(out.predicted),
        }
        if out.states is not None:
            result["states"], result["predicted_states"] = out.states[:, :k], out.states[:, k:]
        if out.state_covs is not None:
            result["state_cov"], result["predicted_state_cov"] = out.state_covs[:, :k], out.state_covs[:, k:]
        return result

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """A pretrained file's int8 weights become float32 before Lightning loads them (``--weights int8``)."""
        restore_float_weights(checkpoint)

    def configure_callbacks(self):
        """``predict`` without a :class:`~ssm_ms.forecasting.writer.ForecastWriter` among the trainer's callbacks gets
        one writing ``predictions/<experiment>_<method>.npz``."""
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
        analysis = self.analyze() if self.trainer.is_global_zero and self.analysis_settings is not None else {}
        for name, value in flat_scalars(analysis).items():
            self.log(f"analysis/{name}", value, rank_zero_only=True)
        if self.trainer.is_global_zero:
            self.write_results(summary, analysis)
            self.log_figures()

    # ------------------------------------------------------------------ analysis
    def analysis_section(self, name: str) -> Any:
        """The ``analysis`` settings' ``name`` (``"valid_time"``, ``"dynamics"``, ``"true_system"``, ``"dt"``);
        ``None`` where it is not set or there is no analysis."""
        return None if self.analysis_settings is None else getattr(self.analysis_settings, name)

    def _valid_time_split(self, seq_len: int) -> tuple[int, int]:
        return valid_time_split(self.analysis_section("valid_time"), self.n_filter, self.n_predict, seq_len)

    def sample_period(self) -> float | None:
        """Seconds per step: ``analysis.dt``, else the data set's ``sample_period`` (``None``: unknown)."""
        dt = self.analysis_section("dt") or getattr(self.datamodule, "sample_period", None)
        return None if dt is None else float(dt)

    def analyze(self) -> dict[str, Any]:
        """What the ``analysis`` setting asks for, as a JSON-ready dict (written beside the scores): the true system's
        exponents where the data set can give them, and the valid time."""
        out: dict[str, Any] = {}
        true_system = self.analysis_section("true_system")
        reference = reference_exponents(self.datamodule, true_system) if true_system is not None else None
        if reference is not None:
            out["true_system"] = reference
        if self._valid_time is not None and self._valid_time.count:
            settings = self.analysis_section("valid_time")
            out["valid_time"] = self._valid_time.report(
                settings.threshold,
                settings.n_filter or self.n_filter,
                self.sample_period(),
                reference["largest"] if reference else None,
            )
        return out

    # ------------------------------------------------------------------ output
    def experiment_name(self) -> str:
        if self.experiment:
            return self.experiment
        dm = self.datamodule
        return getattr(dm, "name", "experiment")

    def write_results(self, summary: dict[str, dict[str, float]], analysis: dict[str, Any] | None = None) -> None:
        from ssm_ms.forecasting.results import results_folder, write_results

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
        write_results(results_folder(self.results_dir, self.trainer), info, summary, analysis or None)

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
