"""The paper's forecasting protocol: infer the state from the first ``k`` measurements of an unseen
sequence, iterate ``f`` from the last inferred state, decode with ``g``, and score the prediction.

Frame bookkeeping for a test sequence ``y[0..T-1]``:

* measurements ``y[0..k-1]`` are given to the inference method (CNN-LSTM encoder, UKF or particle
  filter), which returns inferred states ``x[0..k-1]``;
* the prediction of ``y[k + j]`` is ``g(f^{j+1}(x[k-1]))``, ``j = 0..p-1`` (``p = T - k`` unless
  set), scored against ``y[k..k+p-1]`` (the noisy frames, the paper's convention) and against the
  clean frames when the data set knows them.

Metrics (per test sequence, then mean and std over sequences):

* ``mse``: squared error averaged over the elements of a frame and the predicted frames;
* ``bce``: ``-[t log(p + 1e-12) + (1 - t) log(1 - p + 1e-12)]`` (the reference code's clamping, no
  other clipping), averaged over the pixels of a frame (``bce_reduction: mean``) or summed over them
  (``sum``, the paper's Moving MNIST Table 3 convention), then averaged over predicted frames.

Two references are computed by the same code so the numbers can be read: ``last`` repeats the last
inferred frame ``g(x[k-1])``; ``mean`` predicts the mean training frame.
"""

from __future__ import annotations

import contextvars
import os
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
import torch
from torchmetrics import CatMetric

from ssm_ms.machine import describe
from ssm_ms.module import MultipleShootingModule
from ssm_ms.shooting import decode, rollout

BCE_EPS = 1e-12
METRICS = ("mse", "bce")


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


def forecast(f: Callable[[torch.Tensor], torch.Tensor], x_last: torch.Tensor, steps: int) -> torch.Tensor:
    """States at the ``steps`` times after ``x_last [B, d]``: ``[B, steps, d]`` (the first is ``f(x_last)``)."""
    return rollout(f, f(x_last), steps)


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


def sequence_metrics(pred: torch.Tensor, target: torch.Tensor, metrics: Sequence[str], bce_reduction: str) -> dict[str, torch.Tensor]:
    out = {}
    for name in metrics:
        out[name] = mse_per_sequence(pred, target) if name == "mse" else bce_per_sequence(pred, target, bce_reduction)
    return out


# ---------------------------------------------------------------------------- checkpoints
def load_ssm(path: str | os.PathLike, map_location: str | torch.device = "cpu") -> tuple[MultipleShootingModule, dict]:
    """Load a trained ``MultipleShootingModule`` (and the raw checkpoint, for its data statistics)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(
            f"the SSM checkpoint {path} does not exist: train the model first (python cli.py fit --config "
            "configs/<experiment>.yaml) and set model.init_args.ssm_checkpoint to its checkpoints/last.ckpt"
        )
    checkpoint = torch.load(path, map_location=map_location, weights_only=False)
    if "state_dict" not in checkpoint or "nodes.weight" not in checkpoint["state_dict"]:
        raise ValueError(f"{path} is not a checkpoint of a MultipleShootingModule (no shooting nodes in it)")
    # LightningCLI hands a module it builds its hyperparameters through a context variable; the SSM loaded
    # here, during that construction, must not pick them up: load it in an empty context.
    model = contextvars.Context().run(
        MultipleShootingModule.load_from_checkpoint, path, map_location=map_location, weights_only=False
    )
    model.freeze()
    return model, checkpoint


def datamodule_state(checkpoint: Mapping[str, Any]) -> tuple[str, dict] | None:
    """``(key, state)`` of the DataModule saved in a checkpoint (normalisation and data identity)."""
    for key, value in checkpoint.items():
        if isinstance(value, dict) and "generator_params" in value and "name" in value:
            return key, value
    return None


def check_same_data(checkpoint: Mapping[str, Any], dm: Any, ssm: MultipleShootingModule) -> None:
    """Refuse to evaluate or train an encoder on another data set than the one the SSM learned."""
    saved = datamodule_state(checkpoint)
    if saved is None or dm is None:
        return
    _, state = saved
    current = dm.state_dict() if hasattr(dm, "state_dict") else {}
    problems = []
    if current.get("name") is not None and state["name"] != current.get("name"):
        problems.append(f"data set {state['name']!r} in the checkpoint, {current.get('name')!r} here")
    elif state.get("generator_params") and current.get("generator_params") and state["generator_params"] != current["generator_params"]:
        diff = {
            k: (state["generator_params"].get(k), current["generator_params"].get(k))
            for k in set(state["generator_params"]) | set(current["generator_params"])
            if state["generator_params"].get(k) != current["generator_params"].get(k)
        }
        problems.append(f"data parameters differ (checkpoint, here): {diff}")
    n = getattr(dm, "num_train_trajectories", None)
    if n is not None and n != ssm.nodes.num_embeddings:
        problems.append(f"the SSM has nodes for {ssm.nodes.num_embeddings} training trajectories, the data have {n}")
    if problems:
        raise ValueError(
            "the SSM checkpoint was trained on other data: " + "; ".join(problems)
            + ". Use the data section of the config the SSM was trained with."
        )


# ---------------------------------------------------------------------------- the protocol
class ForecastModule(pl.LightningModule):
    """Base of the evaluation stages: a frozen trained SSM plus an inference method; ``test`` runs the protocol.

    Subclasses implement :meth:`infer`. Results go to TensorBoard (``test/...``), to
    ``<results_dir>/<experiment>.json`` and to a markdown table ``<results_dir>/<experiment>.md``
    with the paper's values beside ours; figures to TensorBoard and, with ``figures_dir``, to PNG/GIF.

    Args:
        ssm_checkpoint: checkpoint of the trained ``MultipleShootingModule``.
        n_filter: measurements given to the inference method (pendulum 50, Moving MNIST 10, Lorenz 1990).
        n_predict: frames predicted after them (default: the rest of the sequence).
        metrics: among ``"mse"``, ``"bce"``.
        bce_reduction: ``"mean"`` over the pixels of a frame, or ``"sum"`` (Moving MNIST convention).
        original_units: undo the data normalisation before scoring (Lorenz: MSE in original units).
        experiment: name of the results files (default: the data set's name).
        results_dir: where the results files go.
        figures_dir: if set, PNG / GIF figures are written there too.
        method_name: how this inference method is labelled in the results (default: its kind).
    """

    method_kind = "model"

    def __init__(
        self,
        ssm_checkpoint: str,
        n_filter: int,
        n_predict: int | None = None,
        metrics: Sequence[str] = ("mse", "bce"),
        bce_reduction: str = "mean",
        original_units: bool = False,
        experiment: str | None = None,
        results_dir: str = "results",
        figures_dir: str | None = None,
        method_name: str | None = None,
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
        self.ssm, self._ssm_checkpoint = load_ssm(ssm_checkpoint)
        # plain attributes: under LightningCLI, hparams hold only what the config set
        self.ssm_checkpoint, self.n_filter, self.n_predict = str(ssm_checkpoint), int(n_filter), n_predict
        self.bce_reduction, self.original_units = bce_reduction, bool(original_units)
        self.experiment, self.results_dir, self.figures_dir = experiment, results_dir, figures_dir
        self.metric_names = list(metrics)
        self.method_name = method_name or self.method_kind
        self._metrics = torch.nn.ModuleDict()
        self._first_batch: dict[str, torch.Tensor] | None = None
        self._mean_frame: torch.Tensor | None = None

    # ------------------------------------------------------------------ to implement
    def infer(self, y_filter: torch.Tensor) -> torch.Tensor:
        """Inferred states ``[B, k, d]`` from measurements ``[B, k, *obs_shape]``."""
        raise NotImplementedError

    def inference_settings(self) -> str | None:
        """One line on how states are inferred, recorded with the results (``None``: nothing to add)."""
        return None

    # ------------------------------------------------------------------ set-up
    @property
    def datamodule(self):
        return getattr(self.trainer, "datamodule", None) if self._trainer is not None else None

    def setup(self, stage: str) -> None:
        dm = self.datamodule
        check_same_data(self._ssm_checkpoint, dm, self.ssm)
        saved = datamodule_state(self._ssm_checkpoint)
        if dm is not None and saved is not None and hasattr(dm, "load_state_dict"):
            dm.load_state_dict(saved[1])  # the SSM's normalisation statistics, not recomputed ones
        if dm is not None and hasattr(dm, "obs_shape"):
            if tuple(dm.obs_shape) != tuple(self.ssm.obs_shape()):
                raise ValueError(
                    f"g outputs measurements of shape {tuple(self.ssm.obs_shape())}, the data have {tuple(dm.obs_shape)}"
                )

    def normalizer(self):
        dm = self.datamodule
        return getattr(dm, "normalizer", None)

    def mean_frame(self, max_trajectories: int = 1000) -> torch.Tensor:
        """Mean training frame ``[*obs_shape]`` (normalised units) over up to ``max_trajectories``."""
        if self._mean_frame is None:
            total, count = None, 0
            for batch in self.datamodule.train_dataloader():
                y = batch["y"].double()
                s = y.sum(dim=(0, 1))
                total = s if total is None else total + s
                count += y.shape[0] * y.shape[1]
                if count >= max_trajectories * y.shape[1]:
                    break
            self._mean_frame = (total / count).float()
        return self._mean_frame

    # ------------------------------------------------------------------ test
    def _record(self, key: str, values: torch.Tensor) -> None:
        name = key.replace("/", "__")  # ModuleDict keys cannot hold "/"
        if name not in self._metrics:
            self._metrics[name] = CatMetric().to(values.device)
        self._metrics[name].update(values.detach())

    def on_test_epoch_start(self) -> None:
        self._start_time = time.time()
        self._metrics = torch.nn.ModuleDict()
        self._first_batch = None

    @torch.no_grad()
    def test_step(self, batch: Mapping[str, torch.Tensor], batch_idx: int) -> None:
        k = self.n_filter
        y_filter, y_future = split_sequence(batch["y"], k, self.n_predict)
        p = y_future.shape[1]
        states = self.infer(y_filter)  # [B, k, d]
        pred_states = forecast(self.ssm.f, states[:, -1], p)  # [B, p, d]
        belief = decode(self.ssm.g, states)  # the model's frames while filtering
        predicted = decode(self.ssm.g, pred_states)
        preds = {
            self.method_name: predicted,
            "last": belief[:, -1:].expand_as(y_future),
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
        if self._first_batch is None:  # kept for the figures
            self._first_batch = {key: batch[key][:, : k + p] for key in ("y", "y_clean", "state") if key in batch}
            self._first_batch["y_model"] = torch.cat([belief, predicted], 1)
            self._first_batch["states"] = torch.cat([states, pred_states], 1)

    def on_test_epoch_end(self) -> None:
        summary: dict[str, dict[str, float]] = {}
        for name, metric in self._metrics.items():
            key = name.replace("__", "/")
            values = metric.compute().flatten().double()
            summary[key] = {"mean": values.mean().item(), "std": values.std(unbiased=False).item(), "n": values.numel()}
            self.log(f"test/{key}", summary[key]["mean"])
        if self.trainer.is_global_zero:
            self.write_results(summary)
            self.log_figures()

    # ------------------------------------------------------------------ output
    def experiment_name(self) -> str:
        if self.experiment:
            return self.experiment
        dm = self.datamodule
        return getattr(dm, "name", "experiment")

    def write_results(self, summary: dict[str, dict[str, float]]) -> None:
        from ssm_ms.results import write_results  # the tables of the paper live there

        info = {
            "experiment": self.experiment_name(),
            "method": self.method_name,
            "ssm_checkpoint": str(self.ssm_checkpoint),
            "n_filter": self.n_filter,
            "n_predict": self.n_predict if self.n_predict is not None else "the rest of each sequence",
            "metrics": self.metric_names,
            "bce_reduction": self.bce_reduction,
            "bce_clamp": f"log(p + {BCE_EPS:g}), log(1 - p + {BCE_EPS:g})",
            "original_units": self.original_units,
            "inference": self.inference_settings(),
            "command": " ".join(sys.argv),
            "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "machine": describe(),
            "test_seconds": round(time.time() - getattr(self, "_start_time", time.time()), 1),
        }
        write_results(Path(self.results_dir), info, summary)

    def log_figures(self) -> None:
        if self._first_batch is not None:
            log_forecast_figures(self, self._first_batch)


def log_forecast_figures(module: ForecastModule, first: dict[str, torch.Tensor], n_sequences: int = 4) -> None:
    """Prediction mosaics / GIF (images) or the Lorenz prediction plot and attractor (vectors), and the
    SSM's training curves, to TensorBoard and, with ``figures_dir``, to files."""
    from ssm_ms import viz

    writer = viz.tensorboard_writer(module.trainer) if module._trainer is not None else None
    out_dir = Path(module.figures_dir) if module.figures_dir else None
    name = f"{module.experiment_name()}_{module.method_name}"
    k = module.n_filter
    y, y_model = first["y"], first["y_model"]
    figures: dict[str, Any] = {}
    if y.dim() == 5:  # images
        every = 1 if y.shape[1] <= 20 else 10
        mosaic = viz.prediction_mosaic(y[:n_sequences], y_model[:n_sequences], k, every=every)
        if writer is not None:
            writer.add_image(f"test/{module.method_name}/prediction_mosaic", mosaic, 0)
        if out_dir is not None:
            viz.save_png(mosaic, out_dir / f"{name}_mosaic.png", scale=max(1, 256 // y.shape[-1]))
            viz.save_gif(y[0], y_model[0], k, out_dir / f"{name}.gif")
    elif y.dim() == 3:  # vectors
        norm = module.normalizer()
        to_units = (lambda t: norm.denormalize(t)) if norm is not None else (lambda t: t)
        states = first["states"][0].clone()
        obs_index = 0
        mapping = module.ssm.hparams.get("node_init_map") or {}
        measured = {int(s): int(o) for s, o in mapping.items()}
        for s_i, o_i in measured.items():  # latent components that read a measurement: in its units
            if norm is not None:
                states[:, s_i] = states[:, s_i] * norm.std[o_i] + norm.mean[o_i]
            obs_index = s_i
        if states.shape[-1] == 3:
            figures["lorenz_prediction"] = viz.lorenz_prediction_figure(
                to_units(y[0]), to_units(first["y_clean"][0]) if "y_clean" in first else to_units(y[0]),
                states, k, true_state=first["state"][0] if "state" in first else None,
                measured_index=obs_index, window=min(y.shape[1], 400),
            )
        x0 = module.ssm.nodes.weight[:1].view(module.ssm.n_nodes, module.ssm.state_dim)[:1]
        attractor = rollout(module.ssm.f, x0, 10_000)[0]
        if attractor.shape[-1] >= 3:
            figures["attractor"] = viz.attractor_figure(attractor[:, :3], title="f iterated 10,000 times from a node")
    log_dir = Path(module.ssm_checkpoint).parent.parent
    try:
        figures["ssm_training"] = viz.loss_curves_figure(log_dir)
    except (FileNotFoundError, ValueError):
        pass  # the SSM's TensorBoard logs are not beside its checkpoint
    for key, fig in figures.items():
        if writer is not None:
            writer.add_figure(f"test/{module.method_name}/{key}", fig, 0, close=False)
        if out_dir is not None:  # figures of the SSM alone do not depend on the inference method
            stem = module.experiment_name() if key in ("attractor", "ssm_training") else name
            viz.save_figure(fig, out_dir / f"{stem}_{key}.png")
