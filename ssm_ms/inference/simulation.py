"""Free-run simulation of a learned SSM from its inputs alone, its initial state estimated from the first samples: the
protocol of the system-identification benchmarks, as validation during training and as a test stage.

- :func:`estimate_states`: the latent states of measurements ``y [B, k, *obs]`` (inputs ``u``): the UKF on ``f`` and
  ``g``, states fitted through them by the shooting objective, or a trained encoder.
- :func:`free_run`: ``g`` of the states ``f`` reaches from ``x`` under the inputs, rolled out in chunks (memory
  bounded over 10^5 steps), with the first step at which the run left the finite range or a bound.
- :class:`SimulationValidation`: a callback scoring the held-out end of the training recording that way every few
  epochs (``val/sim_rmse`` in the data's unit, which a ``ModelCheckpoint`` can monitor to keep the best epoch).
- :class:`SimulationTest`: ``cli.py test`` of the protocol on every test recording, scored by the benchmark loader's
  own error metrics (RMSE, NRMSE, fit index) in the benchmark's unit.

Everything here is in the model's normalised units but the scores, which are in the data's units times the data
module's ``unit_scale`` (Silverbox: mV from the files' V).
"""

from __future__ import annotations

import logging
import math
import sys
import time
from collections.abc import Mapping
from datetime import datetime, timezone
from typing import Any

import lightning.pytorch as pl
import numpy as np
import torch
from torch import nn

from ssm_ms.checkpointing import kept_score
from ssm_ms.forecasting.metrics import DIVERGENCE_BOUND, first_divergence
from ssm_ms.inference.optimise import OptimisationForecaster
from ssm_ms.inference.ssm_forecaster import INFERENCE_LABELS, MODEL_NAMES
from ssm_ms.inference.ukf import UnscentedKalmanFilter
from ssm_ms.loading import load_ssm
from ssm_ms.module import MultipleShootingModule
from ssm_ms.runtime.machine import describe
from ssm_ms.training.shooting import decode, rollout

_log = logging.getLogger("ssm_ms")
METHODS = ("ukf", "fit", "encoder")


def estimate_states(
    ssm: MultipleShootingModule,
    y: torch.Tensor,
    u: torch.Tensor | None = None,
    method: str = "ukf",
    options: Mapping[str, Any] | None = None,
    encoder: Any = None,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """States ``[B, k, d]`` of normalised measurements ``y [B, k, *obs]`` under the inputs ``u [B, >= k - 1, m]``, and
    the UKF's covariances ``[B, k, d, d]`` (``None`` for the other methods).

    ``method``: ``"ukf"`` (:class:`~ssm_ms.inference.UnscentedKalmanFilter`'s settings in ``options``; its measurement
    variance defaults to the model's fit residual at the end of training, ``fit_mse``, else the paper's 0.5),
    ``"fit"`` (:class:`~ssm_ms.inference.OptimisationForecaster`'s, one node by default) or ``"encoder"`` (a trained
    :class:`~ssm_ms.inference.StateEncoderModule` given as ``encoder``; an SSM's own node encoder gives the state
    after the samples, not along them: :func:`initial_state`)."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {list(METHODS)}, got {method!r}")
    options = dict(options or {})
    k = y.shape[1]
    given = None if u is None else u[:, : k - 1]
    if method == "encoder":
        if encoder is None:
            raise ValueError("method 'encoder' needs a trained encoder (python cli.py fit --config <its config>)")
        if options:
            raise ValueError(f"the encoder takes no options, got {sorted(options)}")
        return encoder.infer(y, u), None
    if method == "fit":
        return OptimisationForecaster(ssm, n_filter=k, **{"n_nodes": 1, **options}).infer(y, u), None
    if "measurement_var" not in options:
        options["measurement_var"] = ssm.fit_mse if ssm.fit_mse is not None else 0.5
    try:
        ukf = UnscentedKalmanFilter(ssm.f, ssm.g, state_dim=ssm.state_dim, **options)
    except TypeError as err:
        raise ValueError(f"the UKF's options are UnscentedKalmanFilter's (process_var, init_var, ...): {err}") from None
    # the prior mean as FilterForecaster's: the mean shooting node, the components node_init_map reads from y[0]
    prior = ssm.states_at_measurements(y[:, :1], ssm.training_states().mean(0))[:, 0]
    result = ukf.filter(y, prior, u=given)
    return result.means, result.covs


def default_method(ssm: MultipleShootingModule) -> str:
    """The state estimate a recording gets where none is named: the SSM's node encoder where it has one (it was
    trained for it), else the UKF on its ``f`` and ``g``."""
    return "encoder" if ssm.node_encoder is not None else "ukf"


def initial_state(
    ssm: MultipleShootingModule,
    y: torch.Tensor,
    u: torch.Tensor | None = None,
    method: str | None = None,
    options: Mapping[str, Any] | None = None,
    encoder: Any = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The state at sample ``k`` of normalised measurements ``y [B, k, *obs]`` (inputs ``u [B, >= k, m]``), the
    recording's first ``k`` samples: ``(x [B, d], estimates [B, k, *obs])``, ``estimates`` being ``g`` of the
    states along the ``k`` samples (NaN where the method gives none).

    ``method`` (``None``: :func:`default_method`): ``"encoder"`` with no ``encoder`` given and an SSM with amortised
    nodes reads the last ``history`` of the ``k`` samples with its node encoder, as in training; every other
    estimate is :func:`estimate_states` along the ``k`` samples, stepped once through ``f``."""
    method = default_method(ssm) if method is None else method
    k = y.shape[1]
    if method == "encoder" and encoder is None and ssm.node_encoder is not None:
        if options:
            raise ValueError(f"the node encoder takes no options, got {sorted(options)}")
        h = ssm.history
        if k < h:
            raise ValueError(
                f"the node encoder reads the {h} samples before a state, but only {k} are given to estimate it from: "
                f"give at least {h} (n_init), or train a node encoder of a shorter history"
            )
        uh = None if u is None or not ssm.input_dim else u[:, k - h : k]
        x = ssm.node_encoder(y[:, k - h : k], uh)
        return x, torch.full_like(y, float("nan"))
    states, _ = estimate_states(ssm, y, u, method, options, encoder)
    x = next_state(ssm.f, states[:, -1], None if u is None else u[:, k - 1])
    return x, decode(ssm.g, states, ssm.hparams.decode_chunk)


def next_state(f: nn.Module, x: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
    """``f(x)``, or ``f(x, u)`` for a driven ``f``."""
    return f(x) if u is None else f(x, u)


def free_run(
    f: nn.Module,
    g: nn.Module,
    x: torch.Tensor,
    steps: int,
    u: torch.Tensor | None = None,
    chunk: int = 10_000,
    decode_chunk: int | None = None,
    bound: float | None = None,
    progress: str | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``g`` of ``x [B, d]`` and of its ``steps - 1`` successors under ``u [B, >= steps - 1, m]``: ``[B, steps, *obs]``,
    rolled out ``chunk`` steps at a time; and per sequence the first step at which a measurement left the finite
    range or, with ``bound``, exceeded it in magnitude (``-1``: never). The values are what ``f`` and ``g`` compute;
    the caller reports a divergence (a score is not taken from a diverged run). ``progress``: a bar of that title
    over the chunks, on a terminal (stderr)."""
    if chunk < 1 or steps < 1:
        raise ValueError(f"steps and chunk must be >= 1, got {steps} and {chunk}")
    out, diverged = [], torch.full((x.shape[0],), -1, dtype=torch.long, device=x.device)
    starts = range(0, steps, chunk)
    if progress is not None and len(starts) > 1:
        from tqdm import tqdm

        starts = tqdm(starts, desc=progress, unit="chunk", leave=False, disable=None)
    for start in starts:
        n = min(chunk, steps - start)
        states = rollout(f, x, n, None if u is None else u[:, start : start + n - 1])
        y = decode(g, states, decode_chunk)
        first = first_divergence(y, bound)
        first = torch.where(first >= 0, first + start, first)
        diverged = torch.where(diverged < 0, first, diverged)
        out.append(y)
        if start + n < steps:
            x = next_state(f, states[:, -1], None if u is None else u[:, start + n - 1])
    return torch.cat(out, 1), diverged


def simulate_recording(
    ssm: MultipleShootingModule,
    y: torch.Tensor,
    u: torch.Tensor,
    n_init: int,
    method: str | None = None,
    options: Mapping[str, Any] | None = None,
    encoder: Any = None,
    chunk: int = 10_000,
    bound: float | None = None,
    progress: str | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The benchmark protocol on normalised recordings ``y [B, T, *obs]``, ``u [B, T, m]``: the state from the first
    ``n_init`` samples (:func:`initial_state`), then the free run of the other ``T - n_init`` from the inputs alone.
    Returns the model's measurements ``[B, T, *obs]`` (the first ``n_init`` its estimates of them, NaN where the
    method gives none) and where the run diverged (``-1``: never; else the sample, counted from the recording's
    start)."""
    t = y.shape[1]
    if not 0 < n_init < t:
        raise ValueError(f"n_init={n_init} must be between 1 and the recording's {t - 1} samples")
    x, estimates = initial_state(ssm, y[:, :n_init], u, method, options, encoder)
    y_run, diverged = free_run(
        ssm.f,
        ssm.g,
        x,
        t - n_init,
        None if u is None else u[:, n_init:],
        chunk,
        ssm.hparams.decode_chunk,
        bound,
        progress,
    )
    return torch.cat([estimates, y_run], 1), torch.where(diverged >= 0, diverged + n_init, diverged)


def divergence_bound(ssm: MultipleShootingModule) -> float | None:
    """The magnitude (model units) past which a simulation counts as diverged: :data:`DIVERGENCE_BOUND` training
    stds (the data are normalised, so their range is a few units); ``None`` for data that were not normalised."""
    return DIVERGENCE_BOUND if not ssm.units.is_identity else None


def scores(y_true: np.ndarray, y_model: np.ndarray, n_init: int) -> dict[str, float]:
    """RMSE, NRMSE and fit index of ``y_model`` against ``y_true`` (``[T, p]``, the reported unit) after the first
    ``n_init`` samples: the benchmark loader's own ``error_metrics`` where it is installed, else the same formulas."""
    try:
        from nonlinear_benchmarks import error_metrics as em
    except ImportError:  # the formulas of nonlinear_benchmarks.error_metrics
        e, y = y_model[n_init:] - y_true[n_init:], y_true[n_init:]
        rmse = np.sqrt(np.mean(e**2, axis=0))
        std = np.std(y, axis=0)
        return {
            "rmse": float(rmse.mean()),
            "nrmse": float((rmse / std).mean()),
            "fit_index": float((100 * (1 - rmse / std)).mean()),
        }
    return {
        "rmse": float(np.mean(em.RMSE(y_true, y_model, n_init=n_init))),
        "nrmse": float(np.mean(em.NRMSE(y_true, y_model, n_init=n_init))),
        "fit_index": float(np.mean(em.fit_index(y_true, y_model, n_init=n_init))),
    }


def _to_unit(dm: Any, ssm: MultipleShootingModule, y: torch.Tensor) -> np.ndarray:
    """Normalised measurements ``[T, p]`` -> the data's reported unit (``dm.unit_scale`` times the files')."""
    return (ssm.units.y_to_user(y.double()) * float(getattr(dm, "unit_scale", 1.0))).cpu().numpy()


# ---------------------------------------------------------------------------- validation during training
def held_out_score(
    ssm: MultipleShootingModule, dm: Any, method: str | None = None, options: dict[str, Any] | None = None
) -> tuple[float, list[int]]:
    """The protocol on the data's held-out recordings (``dm.split_dataloader("val")``): the mean RMSE (the data's
    reported unit) over them, scored from ``dm.val_scored_from`` (default ``dm.n_init``), and for each recording the
    sample where its simulation diverged (-1: it did not); the RMSE is infinite where one diverged."""
    scored_from = int(getattr(dm, "val_scored_from", dm.n_init))
    total, where = 0.0, []
    with torch.no_grad():
        for batch in dm.split_dataloader("val"):
            y, u = batch["y"].to(ssm.device), batch.get("u")
            u = None if u is None else u.to(ssm.device)
            y_model, diverged = simulate_recording(
                ssm, y, u, dm.n_init, own_method(ssm, method), dict(options or {}), bound=divergence_bound(ssm)
            )
            for b in range(len(y)):
                where.append(int(diverged[b]))
                if where[-1] < 0:
                    truth, model = _to_unit(dm, ssm, y[b]), _to_unit(dm, ssm, y_model[b])
                    total += scores(truth.reshape(len(truth), -1), model.reshape(len(model), -1), scored_from)["rmse"]
    return (math.inf if max(where, default=-1) >= 0 else total / max(len(where), 1)), where


class SimulationValidation(pl.Callback):
    """Score the data module's held-out recordings (``split_dataloader("val")``, e.g. the end of a benchmark's
    training recording) by the protocol at every validation (``trainer.check_val_every_n_epoch``):
    ``val/sim_rmse`` (:func:`held_out_score`) and ``val/sim_diverged`` (1 where a run diverged: its RMSE is then
    infinite, and the log says at which sample), for the checkpoint that keeps the best epoch
    (``ModelCheckpoint(monitor="val/sim_rmse")``). The sanity check before training is not scored.

    Args:
        method, options: the state estimate from the first ``n_init`` samples (:func:`initial_state`; ``None``: the
            SSM's node encoder where it has amortised nodes, else the UKF).
    """

    def __init__(self, method: str | None = None, options: dict[str, Any] | None = None):
        self.method, self.options = check_method(method), dict(options or {})

    def on_validation_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if trainer.sanity_checking:
            return
        dm = trainer.datamodule
        if not hasattr(dm, "n_init") or not callable(getattr(dm, "split_dataloader", None)):
            raise ValueError(
                "SimulationValidation scores held-out recordings: the data need a 'val' split of whole recordings and "
                "n_init (datamodules.benchmarks.BenchmarkDataModule)"
            )
        rmse, where = held_out_score(pl_module, dm, self.method, self.options)
        for k, sample in enumerate(where):
            if sample >= 0:
                _log.warning(
                    "validation: the simulation of held-out recording %d diverged at sample %d (epoch %d)",
                    k,
                    sample,
                    trainer.current_epoch,
                )
        pl_module.log("val/sim_rmse", rmse, prog_bar=True)
        pl_module.log("val/sim_diverged", float(max(where, default=-1) >= 0))


# ---------------------------------------------------------------------------- the test stage
class SimulationTest(pl.LightningModule):
    """``cli.py test``: the benchmark protocol on every test recording of the data (one test data loader each): the
    state from its first ``n_init`` samples (the data's), the free run of the rest, scored in the benchmark's unit;
    results in ``<results_dir>/<experiment>.json`` and ``.md``, a figure per recording in ``figures_dir``.

    Args:
        ssm_checkpoint: the trained SSM (its ``best.ckpt``: the epoch the validation chose), or the model itself.
        method, options: the state estimate (:func:`initial_state`; ``None``: the SSM's node encoder where it has
            amortised nodes, else the UKF).
        chunk: steps rolled out per call.
        experiment: the results files' name (default: the data's name); ``method_name``: this row's key, ``{d}`` in
            it the SSM's latent dimension (one name for every order ``make reproduce ... --orders`` fits).
        results_dir, figures_dir: where they go (``results_dir`` ``None``: the run's own folder, the trainer's
            ``log_dir``; ``figures_dir`` ``None``: no figures).
        selection: how the model was chosen, recorded with the results (``make reproduce ... --orders``: each
            latent dimension's validation score and the one chosen).
    """

    def __init__(
        self,
        ssm_checkpoint: str | nn.Module | None = None,
        method: str | None = None,
        options: dict[str, Any] | None = None,
        chunk: int = 10_000,
        experiment: str | None = None,
        method_name: str | None = None,
        results_dir: str | None = None,
        figures_dir: str | None = None,
        selection: dict[str, Any] | None = None,
    ):
        super().__init__()
        if ssm_checkpoint is None:
            raise ValueError("model.init_args.ssm_checkpoint is not set: give the SSM run's checkpoints/best.ckpt")
        check_method(method)
        given = getattr(ssm_checkpoint, "module", ssm_checkpoint)
        saved: dict[str, Any] = {}
        if isinstance(given, MultipleShootingModule):
            self.ssm = given.eval()
        else:
            self.ssm, saved = load_ssm(given)
        # what the fit's validation kept this epoch by, and the epoch (the results file says both)
        callbacks = saved.get("callbacks") or {}
        timer = callbacks.get("Timer", {}).get("time_elapsed", {})
        self.kept = {
            "val_sim_rmse": kept_score(saved, None if isinstance(given, nn.Module) else given),
            "epoch": saved.get("epoch"),
            # the fit's time until then (training and validation; a time-budgeted fit's Timer)
            "seconds": round(timer.get("train", 0.0) + timer.get("validate", 0.0), 1) if timer else None,
            # other processes' CPU use during the fit until then (a time-budgeted fit's ShootingSchedule)
            "cpu_others": callbacks.get("ShootingSchedule", {}).get("cpu_others"),
        }
        method = own_method(self.ssm, method)
        self.ssm_checkpoint = None if isinstance(given, nn.Module) else str(given)
        self.save_hyperparameters(ignore=["ssm_checkpoint"])
        self.method, self.options, self.chunk = method, dict(options or {}), int(chunk)
        if method_name is not None:
            try:
                method_name = method_name.format(d=self.ssm.state_dim)
            except (KeyError, IndexError, ValueError):
                raise ValueError(
                    f"model.init_args.method_name {method_name!r}: braces may hold only {{d}}, the latent dimension"
                ) from None
        self.experiment, self.method_name = experiment, method_name
        self.results_dir, self.figures_dir, self.selection = results_dir, figures_dir, selection
        self.rows: dict[str, dict[str, Any]] = {}
        self.figures: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def setup(self, stage: str) -> None:
        dm = self.trainer.datamodule
        if not hasattr(dm, "n_init") or not hasattr(dm, "test_names"):
            raise ValueError(
                "SimulationTest runs a benchmark's protocol: give its data (datamodules.benchmarks.BenchmarkDataModule)"
            )
        if self.ssm.data_state is not None:
            dm.load_state_dict(self.ssm.data_state)  # the SSM's normalisation, not recomputed
        self._start = time.time()

    def test_step(self, batch: Mapping[str, torch.Tensor], batch_idx: int, dataloader_idx: int = 0) -> None:
        dm = self.trainer.datamodule
        name = dm.test_names[dataloader_idx]
        y, u = batch["y"], batch.get("u")
        started = time.time()
        _log.info("test %s: %d samples, the state from the first %d", name, y.shape[1], dm.n_init)
        y_model, where = simulate_recording(
            self.ssm,
            y,
            u,
            dm.n_init,
            self.method,
            self.options,
            chunk=self.chunk,
            bound=divergence_bound(self.ssm),
            progress=f"simulating {name}",
        )
        truth, model = _to_unit(dm, self.ssm, y[0]), _to_unit(dm, self.ssm, y_model[0])
        truth, model = truth.reshape(len(truth), -1), model.reshape(len(model), -1)
        diverged = int(where[0])
        row = {"samples": int(y.shape[1]), "n_init": int(dm.n_init), "seconds": round(time.time() - started, 2)}
        if diverged >= 0:
            row.update(rmse=None, nrmse=None, fit_index=None, diverged_at=diverged)
            _log.warning("test %s: the simulation diverged at sample %d (no score)", name, diverged)
        else:
            row.update(scores(truth, model, dm.n_init), diverged_at=None)
        self.rows[name] = row
        self.figures[name] = (truth, model)
        if row["rmse"] is not None:
            self.log(f"test/{name}/rmse", row["rmse"], add_dataloader_idx=False)

    def on_test_epoch_end(self) -> None:
        if not self.trainer.is_global_zero:
            return
        from ssm_ms.forecasting.benchmark_results import write_benchmark_results
        from ssm_ms.forecasting.results import results_folder

        dm = self.trainer.datamodule
        info = {
            "experiment": self.experiment or dm.name,
            "method": self.method_name or f"{model_name(self.ssm)} + {method_label(self.ssm, self.method)}",
            "model": model_name(self.ssm),
            "state_dim": self.ssm.state_dim,
            "seed": self.ssm.seed,
            "validation": {"unit": getattr(dm, "unit", ""), **self.kept},
            "ssm_checkpoint": self.ssm_checkpoint,
            "inference": {"method": self.method, **self.options},
            "benchmark": getattr(dm, "benchmark", dm.name),
            "unit": getattr(dm, "unit", ""),
            "command": " ".join(sys.argv),
            "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "machine": describe(),
            "test_seconds": round(time.time() - self._start, 1),
            "stability": local_stability(self.ssm),
            "selection": self.selection,
        }
        write_benchmark_results(
            results_folder(self.results_dir, self.trainer), info, self.rows, self.figures, self.figures_dir, dm.n_init
        )


def check_method(method: str | None) -> str | None:
    """A simulation's state estimate, checked (``"encoder"``: the SSM's node encoder, checked with the SSM)."""
    if method not in (None, "ukf", "fit", "encoder"):
        raise ValueError(f"method must be 'ukf', 'fit' or 'encoder' (or unset: the SSM's default), got {method!r}")
    return method


def own_method(ssm: MultipleShootingModule, method: str | None) -> str:
    """``method`` for this SSM (``None``: :func:`default_method`); ``"encoder"`` needs its node encoder."""
    if method == "encoder" and ssm.node_encoder is None:
        raise ValueError(
            "method 'encoder' reads the state with the SSM's node encoder, and this SSM has free nodes: use 'ukf' or "
            "'fit' (or train it with amortised nodes, model.init_args.node_encoder)"
        )
    return default_method(ssm) if method is None else method


def method_label(ssm: MultipleShootingModule, method: str) -> str:
    """The state estimate's name in a results row."""
    return (
        "node encoder" if method == "encoder" and ssm.node_encoder is not None else INFERENCE_LABELS.get(method, method)
    )


def model_name(ssm: MultipleShootingModule) -> str:
    """``SSM-LL (d = 4)``: the transition's paper name and the latent dimension."""
    name = type(ssm.f).__name__
    label = MODEL_NAMES.get(name, f"SSM ({name})")
    if getattr(ssm.f, "linear", None) is not None:  # FullyConnectedTransition(linear=True): not the paper's SSM-FC
        label += " with a linear part" if getattr(ssm.f, "residual", True) else " with a linear part, no identity"
    return f"{label} (d = {ssm.state_dim})"


def local_stability(ssm: MultipleShootingModule, n: int = 256) -> dict[str, float]:
    """The spectral radius of ``f``'s Jacobian in ``x`` at ``n`` of its shooting nodes (training states; the inputs at
    their training mean, 0 in normalised units): its median, 90th percentile, maximum, and the share of those states
    where it exceeds 1 (``f`` locally expanding)."""
    from ssm_ms.analysis import linearize

    nodes = ssm.training_states()
    x = nodes[torch.randperm(len(nodes), generator=torch.Generator().manual_seed(0))[:n]]
    u = torch.zeros(len(x), ssm.input_dim, dtype=x.dtype) if ssm.input_dim else None
    a = linearize(ssm.f, ssm.g, x, u).A
    radius = torch.linalg.eigvals(a.double()).abs().amax(-1)
    return {
        "median": float(radius.median()),
        "p90": float(radius.quantile(0.9)),
        "max": float(radius.max()),
        "share_above_1": float((radius > 1).double().mean()),
        "states": len(x),
    }
