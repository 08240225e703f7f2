"""Forecasting with a trained SSM: infer the state from the first ``k`` measurements, iterate ``f`` from
the last inferred state, decode with ``g``.

:class:`SSMForecaster` is the :class:`~ssm_ms.forecasting.protocol.ForecastModule` of every inference method
over a frozen ``MultipleShootingModule`` checkpoint; subclasses implement :meth:`SSMForecaster.infer`
(:class:`~ssm_ms.inference.StateEncoderModule`: a trained CNN-LSTM; :class:`~ssm_ms.inference.FilterForecaster`:
UKF or particle filter; :class:`~ssm_ms.inference.OptimisationForecaster`: states fitted through ``f`` and ``g``). It
also checks that the test data are the data the SSM learned, and uses the
SSM's normalisation statistics.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from ssm_ms.checkpointing import SSM_DIGEST_KEY, state_digest
from ssm_ms.forecasting.analysis_settings import DynamicsSettings, ValidTimeSettings
from ssm_ms.forecasting.protocol import Forecast, ForecastModule
from ssm_ms.loading import load_ssm
from ssm_ms.module import MultipleShootingModule
from ssm_ms.training.shooting import decode, rollout

_log = logging.getLogger("ssm_ms")

# Paper names of the transition models.
MODEL_NAMES = {"LocallyLinearTransition": "SSM-LL", "FullyConnectedTransition": "SSM-FC"}
# An observation model g the results tables name beside f's name (the paper's own g's are not named).
G_NAMES = {"SpriteDecoder": "sprite decoder"}
# How the results tables name the inference methods (a custom method_name is shown as it is).
INFERENCE_LABELS = {
    "encoder": "CNN-LSTM encoder",
    "ukf": "UKF",
    "pf": "particle filter",
    "optimise": "states fitted by optimisation",
}


# ---------------------------------------------------------------------------- checkpoints
def data_differences(state: Mapping[str, Any] | None, dm: Any, split: str = "train") -> list[str]:
    """How the ``split`` of ``dm`` differs from the one of the data an SSM learned (``state``: its
    :attr:`~ssm_ms.module.MultipleShootingModule.data_state`; empty: the same). Only what determines that split is
    compared (:meth:`~datamodules.base.TrajectoryDataModule.params_of`): a test split of another size is the same
    training data."""
    if state is None or dm is None:
        return []
    current = dm.state_dict() if hasattr(dm, "state_dict") else {}
    if current.get("name") is not None and state["name"] != current.get("name"):
        return [f"data set {state['name']!r} in the checkpoint, {current.get('name')!r} here"]
    theirs, ours = state.get("generator_params"), current.get("generator_params")
    if not theirs or not ours:
        return []
    if hasattr(dm, "params_of"):
        theirs, ours = dm.params_of(split, theirs), dm.params_of(split, ours)
    diff = {k: (theirs.get(k), ours.get(k)) for k in sorted(set(theirs) | set(ours)) if theirs.get(k) != ours.get(k)}
    return [f"data parameters differ (checkpoint, here): {diff}"] if diff else []


def check_same_data(dm: Any, ssm: MultipleShootingModule) -> None:
    """Refuse to train an encoder on other training data than the SSM learned: its targets are the SSM's
    shooting nodes, one per training trajectory."""
    problems = data_differences(ssm.data_state, dm)
    n = getattr(dm, "num_train_trajectories", None)
    if n is not None and n != ssm.nodes.num_embeddings:
        problems.append(f"the SSM has nodes for {ssm.nodes.num_embeddings} training trajectories, the data have {n}")
    if problems:
        raise ValueError(
            "the SSM checkpoint was trained on other data: "
            + "; ".join(problems)
            + ". Use the data section of the config the SSM was trained with."
        )


# ---------------------------------------------------------------------------- the protocol


def training_measurements(dm: Any, max_values: int = 2_000_000) -> torch.Tensor | None:
    """Noiseless training measurements ``[M, D]`` in original units (the cache's arrays; noisy ones if the data
    set has no noiseless copy), evenly subsampled to at most ``max_values`` numbers."""
    train = dm.train_split() if hasattr(dm, "train_split") else None
    arrays = getattr(train, "arrays", None)
    if arrays is None:
        return None
    y = arrays.get("y_clean", arrays["y"])
    every = max(1, -(-y.size // max_values))
    flat = np.asarray(y).reshape(-1, int(np.prod(y.shape[2:])))
    return torch.from_numpy(np.array(flat[::every], dtype=np.float64))


def ssm_log_dir(checkpoint: str | Path) -> Path | None:
    """The run folder of an SSM checkpoint saved by training (``<run>/checkpoints/<file>.ckpt``, its TensorBoard
    events in ``<run>``); ``None`` for a file elsewhere (a stripped ``pretrained/`` file: the folder above holds
    other runs' events, not its own)."""
    path = Path(checkpoint)
    return path.parent.parent if path.parent.name == "checkpoints" else None


def predict_states(f, x_last: torch.Tensor, steps: int, u: torch.Tensor | None = None) -> torch.Tensor:
    """States at the ``steps`` times after ``x_last [B, d]``: ``[B, steps, d]`` (the first is ``f(x_last)``; for a
    driven ``f``, ``f(x_last, u[:, 0])``, then under ``u[:, 1:]``)."""
    if u is None:
        return rollout(f, f(x_last), steps)
    return rollout(f, f(x_last, u[:, 0]), steps, u[:, 1:])


# ---------------------------------------------------------------------------- the forecaster
class SSMForecaster(ForecastModule):
    """A frozen trained SSM plus an inference method; ``test`` runs the protocol.

    Subclasses implement :meth:`infer`. The prediction of ``y[k + j]`` is ``g(f^{j+1}(x[k-1]))``.

    Args:
        ssm_checkpoint: checkpoint of the trained ``MultipleShootingModule``, or the model itself (from Python: a
            ``MultipleShootingModule`` or an ``ssm_ms.SSM``, its data state read from it). Optional on the
            command line with ``--ckpt_path``: that checkpoint's recorded one is used (and wins over a given one, as
            every setting).
        n_filter: measurements given to the inference method.
        **kwargs: the protocol's other arguments (``n_predict``, ``metrics``, ``bce_reduction``,
            ``original_units``, ``experiment``, ``results_dir``, ``figures_dir``, ``method_name``, ``analysis``),
            see :class:`~ssm_ms.forecasting.protocol.ForecastModule`.
    """

    # figures of the SSM alone, shared by the inference methods tested on it: named after the experiment, or, for a
    # method with a name of its own (another SSM of the experiment, e.g. `encoder_ssm1000`), after that method
    shared_figures = ("attractor", "ssm_training")

    def __init__(self, ssm_checkpoint: str | nn.Module | None = None, *, n_filter: int, **kwargs: Any):
        if ssm_checkpoint is None:
            raise ValueError(
                "model.init_args.ssm_checkpoint is not set: give the last.ckpt of the SSM run (python cli.py fit "
                "--config configs/<experiment>.yaml); a checkpoint of this stage given with --ckpt_path supplies "
                "the one it was trained with"
            )
        given = getattr(ssm_checkpoint, "module", ssm_checkpoint)  # an ssm_ms.SSM holds its MultipleShootingModule
        if isinstance(given, nn.Module) and not isinstance(given, MultipleShootingModule):
            raise ValueError(
                f"ssm_checkpoint takes an SSM checkpoint path or a MultipleShootingModule, got a {type(given).__name__}"
            )
        super().__init__(n_filter, **kwargs)
        if isinstance(given, MultipleShootingModule):  # used, not frozen: the caller may train it further
            self.ssm = given.eval()
            self.ssm_checkpoint = None
        else:
            self.ssm, _ = load_ssm(given)
            self.ssm_checkpoint = str(given)
        self.input_dim = self.ssm.input_dim

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """A file stripped without its SSM (``python -m ssm_ms.pretrained --ssm-checkpoint``) takes the SSM's weights
        from ``ssm_checkpoint``, loaded above, once they are checked to be the ones it was stripped with."""
        super().on_load_checkpoint(checkpoint)
        digest = checkpoint.get(SSM_DIGEST_KEY)
        if digest is None:
            return
        own = self.ssm.state_dict()
        if state_digest(own) != digest:
            raise ValueError(
                f"this {self.method_name} checkpoint was stored without its SSM, to be loaded with the SSM it was "
                f"stripped with; ssm_checkpoint {self.ssm_checkpoint} holds another one: give "
                f"model.init_args.ssm_checkpoint the file named in the checkpoint's hyperparameters"
            )
        checkpoint["state_dict"] = {**checkpoint["state_dict"], **{f"ssm.{k}": v for k, v in own.items()}}

    def start_states(self, y_at: torch.Tensor, base: torch.Tensor | None = None) -> torch.Tensor:
        """``[B, m, d]``: a start for the states at the times of the measurements ``y_at [B, m, *obs]``: ``base [d]``
        (default: the mean shooting node) with the components the SSM's ``node_init_map`` reads from measurements
        taken from ``y_at`` (Lorenz: the measured coordinate), as the SSM's own nodes start
        (:meth:`~ssm_ms.module.MultipleShootingModule.states_at_measurements`)."""
        if base is None:
            base = self.ssm.training_states().mean(0)
        return self.ssm.states_at_measurements(y_at, base)

    # ------------------------------------------------------------------ to implement
    def infer(self, y_filter: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        """Inferred states ``[B, k, d]`` from measurements ``[B, k, *obs_shape]`` (and, for a driven SSM, the inputs
        ``u [B, >= k - 1, m]`` between them)."""
        raise NotImplementedError

    def infer_distribution(
        self, y_filter: torch.Tensor, n_predict: int, u: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Inferred states ``[B, k, d]`` and the covariances ``[B, k + p, d, d]`` of the inferred and the
        ``p = n_predict`` predicted states, where the method has them (default: :meth:`infer`, ``None``); ``u``
        the inputs of all ``k + p - 1`` transitions for a driven SSM."""
        return self.infer(y_filter, u), None

    # ------------------------------------------------------------------ the protocol's hooks
    def forecast(self, y_filter: torch.Tensor, n_predict: int, u: torch.Tensor | None = None) -> Forecast:
        return self._forecast_from(self.infer(y_filter, u), n_predict, u)

    def forecast_distribution(self, y_filter: torch.Tensor, n_predict: int, u: torch.Tensor | None = None) -> Forecast:
        states, covs = self.infer_distribution(y_filter, n_predict, u)
        return self._forecast_from(states, n_predict, u)._replace(state_covs=covs)

    def _forecast_from(self, states: torch.Tensor, n_predict: int, u: torch.Tensor | None = None) -> Forecast:
        """The prediction of ``y[k + j]`` is ``g(f^{j+1}(x[k-1]))`` from the inferred ``states [B, k, d]`` (under the
        inputs ``u[:, k - 1 : k - 1 + p]`` for a driven SSM)."""
        k = states.shape[1]
        future = None if u is None else u[:, k - 1 : k - 1 + n_predict]
        pred_states = predict_states(self.ssm.f, states[:, -1], n_predict, future)  # [B, p, d]
        return Forecast(
            filtered=decode(self.ssm.g, states),
            predicted=decode(self.ssm.g, pred_states),
            states=torch.cat([states, pred_states], 1),
        )

    def describe(self) -> dict[str, Any]:
        name = type(self.ssm.f).__name__
        model = MODEL_NAMES.get(name, f"SSM ({name})")
        if (g_name := G_NAMES.get(type(self.ssm.g).__name__)) is not None:
            model = f"{model} with a {g_name}"
        how = INFERENCE_LABELS.get(self.method_kind, self.method_kind)
        if self.method_name != self.method_kind:  # a row of its own beside the default one (another SSM)
            how = f"{how} ({self.method_name})"
        return {
            "model": model,
            "inference": self.method_kind,
            "label": f"{model} + {how}",
            "ssm_checkpoint": self.ssm_checkpoint,
        }

    def setup(self, stage: str) -> None:
        super().setup(stage)
        if self.input_dim and self.analysis_section("dynamics") is not None:
            raise ValueError(
                "analysis.dynamics studies f on its own (free runs, Lyapunov exponents), but this SSM's f is driven "
                "by inputs: remove analysis.dynamics (valid_time still applies)"
            )
        dm = self.datamodule
        if stage == "fit":
            check_same_data(dm, self.ssm)
        else:  # a test on other data (another noise level, rendering, ...) is an experiment: said, not refused
            self.data_note = "; ".join(data_differences(self.ssm.data_state, dm, "test")) or None
            if self.data_note:
                _log.warning("the test data differ from the SSM's data set: %s", self.data_note)
        if dm is not None and self.ssm.data_state is not None and hasattr(dm, "load_state_dict"):
            dm.load_state_dict(self.ssm.data_state)  # the SSM's normalisation statistics, not recomputed ones
        if dm is not None and hasattr(dm, "obs_shape"):
            if tuple(dm.obs_shape) != tuple(self.ssm.obs_shape()):
                raise ValueError(
                    f"g outputs measurements of shape {tuple(self.ssm.obs_shape())}, the data have {tuple(dm.obs_shape)}"
                )

    def analyze(self) -> dict[str, Any]:
        """The protocol's analysis, plus (``analysis.dynamics``) what ``f`` does on its own from shooting nodes:
        :func:`ssm_ms.analysis.dynamics_report` (Lyapunov spectrum; free runs decoded in original units against
        the training split's noiseless measurements, for vector data; the Lorenz wing share where the data set
        defines wings), and, where the data set can simulate its truth from a trajectory's initial state
        (``true_measurements``), the period, amplitude and valid time of free runs from first nodes."""
        from ssm_ms.analysis import dynamics_report

        out = super().analyze()
        settings = self.analysis_section("dynamics")
        if settings is None:
            return out
        dm, norm = self.datamodule, self.normalizer()
        to_units = norm.denormalize if norm is not None else None
        nodes = self.ssm.training_states()
        generator = torch.Generator().manual_seed(settings.seed)
        free_runs = settings.free_runs or settings.runs
        if max(settings.runs, free_runs) > len(nodes):
            raise ValueError(
                f"analysis.dynamics asks for {max(settings.runs, free_runs)} runs from shooting nodes but "
                f"the model has {len(nodes)}: lower analysis.dynamics.runs / free_runs"
            )
        drawn = nodes[torch.randperm(len(nodes), generator=generator)[: max(settings.runs, free_runs)]]
        vector = len(self.ssm.obs_shape()) == 1
        report = dynamics_report(
            self.ssm.f,
            self.ssm.g,
            drawn[: settings.runs],
            self.sample_period() or 1.0,
            to_units=to_units,
            free_starts=drawn[:free_runs],
            reference=training_measurements(dm) if vector else None,
            lyapunov_steps=settings.lyapunov_steps,
            transient=settings.transient,
            align=settings.align,
            free_steps=settings.free_steps,
            wing_level=dm.wing_level() if hasattr(dm, "wing_level") else None,
        )
        if callable(getattr(dm, "true_measurements", None)):
            report["oscillation"] = self.oscillation(settings, generator)
        out["dynamics"] = report
        return out

    @torch.no_grad()
    def oscillation(self, settings: DynamicsSettings, generator: torch.Generator) -> dict[str, Any]:
        """Free runs of ``f`` from the first node of training trajectories against the data generator's own
        continuation from their initial states, over ``free_steps`` steps: period, amplitude, valid time."""
        from ssm_ms.analysis import amplitude_ratio, dominant_period, valid_steps

        dm = self.datamodule
        n_traj = self.ssm.nodes.num_embeddings
        index = torch.randperm(n_traj, generator=generator)[: settings.runs].sort().values
        horizon = settings.free_steps
        states = rollout(self.ssm.f, self.ssm.node_states(index.to(self.device))[:, 0], horizon)
        model = decode(self.ssm.g, states).cpu().double()
        truth = dm.true_measurements("train", index.tolist(), horizon).double()
        dt = self.sample_period() or 1.0
        flat_m, flat_t = model.flatten(2), truth.flatten(2)
        period_m, period_t = dominant_period(flat_m, dt), dominant_period(flat_t, dt)
        error = (period_m - period_t).abs() / period_t
        window = max(2, horizon // 10)
        amp_m, amp_t = amplitude_ratio(flat_m, window), amplitude_ratio(flat_t, window)
        pixel_var = (
            flat_t.flatten(0, 1).var(0, unbiased=False).mean()
        )  # as the protocol's valid time: 1 = the mean frame
        nrmse = ((flat_m - flat_t).pow(2).mean(-1) / pixel_var).sqrt()
        valid = valid_steps(nrmse, (self.analysis_section("valid_time") or ValidTimeSettings()).threshold)
        valid = torch.where(torch.isinf(valid), torch.full_like(valid, float(horizon)), valid)
        finite = torch.isfinite(error)
        return {
            "runs": len(index),
            "horizon": horizon,
            "dt": dt,
            "period_model": period_m.tolist(),
            "period_truth": period_t.tolist(),
            "median_period_error": float(error[finite].median()) if finite.any() else None,
            "share_within_5_percent": float((error[finite] < 0.05).double().mean()) if finite.any() else None,
            "median_amplitude_ratio_model": float(amp_m.median()),
            "median_amplitude_ratio_truth": float(amp_t.median()),
            "median_valid_steps": float(valid.median()),
        }

    def forecast_figures(self, first: dict[str, torch.Tensor]) -> dict[str, Any]:
        """The Lorenz-style plot of the inferred and predicted states, the attractor of ``f`` iterated
        10,000 times from a shooting node, and the SSM's training curves."""
        from ssm_ms import drawing

        figures: dict[str, Any] = {}
        y = first["y"]
        if y.dim() == 3:  # vectors
            norm = self.normalizer()
            to_units = (lambda t: norm.denormalize(t)) if norm is not None else (lambda t: t)
            states = first["states"][0].clone()
            obs_index = 0
            mapping = self.ssm.hparams.get("node_init_map") or {}
            measured = {int(s): int(o) for s, o in mapping.items()}
            for s_i, o_i in measured.items():  # latent components that read a measurement: in its units
                if norm is not None:
                    states[:, s_i] = states[:, s_i] * norm.std[o_i] + norm.mean[o_i]
                obs_index = s_i
            if states.shape[-1] == 3 and y.shape[-1] == 1:  # a three-state system seen through one component
                figures["lorenz_prediction"] = drawing.lorenz_prediction_figure(
                    to_units(y[0]),
                    to_units(first["y_clean"][0]) if "y_clean" in first else to_units(y[0]),
                    states,
                    self.n_filter,
                    true_state=first["state"][0] if "state" in first else None,
                    measured_index=obs_index,
                    window=min(y.shape[1], 400),
                )
            x0 = self.ssm.nodes.weight[:1].view(self.ssm.n_nodes, self.ssm.state_dim)[:1]
            attractor = rollout(self.ssm.f, x0, 10_000)[0] if not self.input_dim else x0  # a driven f: no free run
            if attractor.shape[0] > 1 and attractor.shape[-1] >= 3:
                true = first["state"][:4] if "state" in first and first["state"].shape[-1] == 3 else None
                figures["attractor"] = drawing.attractor_figure(
                    attractor[:, :3], title="f iterated 10,000 times from a node", true_states=true
                )
        if (log_dir := ssm_log_dir(self.ssm_checkpoint)) is not None:
            try:
                figures["ssm_training"] = drawing.loss_curves_figure(log_dir)
            except (FileNotFoundError, ValueError):
                pass  # the SSM's TensorBoard logs are not beside its checkpoint
        return figures
