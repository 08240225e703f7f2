"""The baselines as Lightning modules: trained on the experiment's DataModule, tested by the same protocol.

A :class:`BaselineForecaster` wraps a network that maps ``(y [B, T, *obs_shape], observed [B, T])`` to an
estimate of every measurement (:class:`~ssm_ms.baselines.common.SequenceOutput`). Training shows it the
first ``k`` measurements of each training sequence and asks for all of them (the given ones
reconstructed, the rest predicted), with the loss of the experiment's SSM (``mse`` or ``bce``) or, for a
network with a variance output, the Gaussian negative log-likelihood. Testing gives it the first
``n_filter`` measurements of each test sequence with the remaining steps unobserved, and the protocol
of :mod:`ssm_ms.forecasting.protocol` scores the prediction like any other forecaster's.

The network is built when the data are known (``setup``): its input and output shapes come from the
DataModule, so the same config works at any image size its presets support; the shape is recorded in
the hyperparameters and checkpoints reload on their own.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from ssm_ms.baselines.common import SequenceOutput
from ssm_ms.baselines.lstm import Seq2SeqLSTM
from ssm_ms.baselines.rkn import RecurrentKalmanNetwork
from ssm_ms.checkpointing import SSM_DIGEST_KEY, holds_ssm
from ssm_ms.forecasting.protocol import Forecast, ForecastModule
from ssm_ms.runtime.memory import check_lstm_memory

LOSSES = ("mse", "bce", "gaussian_nll")


class BaselineForecaster(ForecastModule):
    """A forecaster without an SSM: one network trained end to end on the measurement sequences.

    Args:
        n_filter: measurements given at test time (pendulum 50, Lorenz 1990).
        network: keyword arguments of the network (see :class:`~ssm_ms.baselines.lstm.Seq2SeqLSTM`,
            :class:`~ssm_ms.baselines.rkn.RecurrentKalmanNetwork`), without ``obs_shape``.
        loss: ``"mse"``, ``"bce"`` (images in [0, 1]) or ``"gaussian_nll"`` (networks with a variance).
        lr: Adam learning rate.
        train_n_filter: measurements given per training sequence, the rest being predicted. ``None``:
            ``n_filter`` when it leaves something to predict in a training sequence, else the training
            length minus ``n_predict`` (Lorenz T=1000 with 1990 filtered / 10 predicted at test: 990 given, 10
            predicted per training piece).
        train_window: train on a random window of this many consecutive steps of each training sequence
            (validation: its last window) instead of the whole sequence: cheaper steps for long sequences
            (a CPU-sized Lorenz twin: 200 of 1000); ``None`` (default, the paper's setting): whole sequences.
        obs_shape: shape of one measurement; ``None``: taken from the DataModule (recorded in the checkpoint).
        validate_held_out: train on the training trajectories less the validation subset (the data's
            ``val_trajectories``), so that ``val/loss`` measures sequences the network has not seen and a
            ``ModelCheckpoint`` on it can keep the best epoch. Without it (the default, as the paper's runs) the
            network trains on every trajectory and validates on some of them.
        metrics, n_predict, **kwargs: the protocol's arguments (``analysis``: ``valid_time``, not ``dynamics``), see
            :class:`~ssm_ms.forecasting.protocol.ForecastModule`.
    """

    model_name = "baseline"

    def __init__(
        self,
        n_filter: int,
        network: dict[str, Any] | None = None,
        loss: str = "mse",
        lr: float = 1e-3,
        train_n_filter: int | None = None,
        train_window: int | None = None,
        obs_shape: list[int] | None = None,
        validate_held_out: bool = False,
        n_predict: int | None = None,
        metrics: list[str] = ["mse", "bce"],  # noqa: B006 (read, never mutated; a list for the CLI)
        **kwargs: Any,
    ):
        super().__init__(n_filter, n_predict=n_predict, metrics=metrics, **kwargs)
        if loss not in LOSSES:
            raise ValueError(f"unknown loss {loss!r}: choose one of {list(LOSSES)}")
        if not lr > 0:
            raise ValueError(f"lr must be > 0, got {lr}")
        if train_n_filter is not None and train_n_filter < 1:
            raise ValueError(f"train_n_filter must be >= 1, got {train_n_filter}")
        if train_window is not None and train_window < 2:
            raise ValueError(f"train_window must be >= 2 steps (or unset: whole sequences), got {train_window}")
        self.train_window = train_window
        self.validate_held_out = validate_held_out  # read by the DataModule's training loader
        if "obs_shape" in (network or {}):
            raise ValueError("network.obs_shape comes from the data: remove it from the config")
        if self.analysis_section("dynamics") is not None:
            raise ValueError(
                "analysis.dynamics studies an SSM's f; a baseline has none: keep valid_time, drop dynamics"
            )
        self.network_kwargs = dict(network or {})
        self.loss_name, self.lr, self.train_n_filter = loss, float(lr), train_n_filter
        self.net: nn.Module | None = None
        if obs_shape is not None:
            self.build(tuple(obs_shape))

    # ------------------------------------------------------------------ to implement
    def build_network(self, obs_shape: tuple[int, ...]) -> nn.Module:
        raise NotImplementedError

    # ------------------------------------------------------------------ construction
    def build(self, obs_shape: tuple[int, ...]) -> None:
        self.net = self.build_network(obs_shape)
        self.hparams["obs_shape"] = list(obs_shape)
        has_var = getattr(self.net, "decoder_var", None) is not None
        if self.loss_name == "gaussian_nll" and not has_var:
            raise ValueError(
                f"loss gaussian_nll needs a network with a variance output; this {self.model_name} has none: "
                "use loss mse (or, for the RKN on vectors, network.output: gaussian)"
            )

    def setup(self, stage: str) -> None:
        super().setup(stage)
        dm = self.datamodule
        if dm is None or not hasattr(dm, "obs_shape"):
            if self.net is None:
                raise ValueError(f"the {self.model_name} needs the data's measurement shape: give obs_shape")
            return
        shape = tuple(dm.obs_shape)
        if self.net is None:
            self.build(shape)
        elif tuple(self.hparams["obs_shape"]) != shape:
            raise ValueError(
                f"this {self.model_name} was built for measurements of shape {list(self.hparams['obs_shape'])}, "
                f"the data have {list(shape)}: use the data section it was trained with"
            )
        if stage == "fit":
            if self.train_window is not None and self.train_window > dm.seq_len:
                raise ValueError(
                    f"train_window={self.train_window} is longer than the training sequences ({dm.seq_len} steps): "
                    f"choose at most {dm.seq_len}, or unset it"
                )
            self.training_split(min(dm.seq_len, self.train_window or dm.seq_len))  # fail now if nothing to predict
        if self.loss_name == "bce" and len(shape) == 1:
            raise ValueError(
                "loss bce is for images in [0, 1]; these measurements are vectors: use mse or gaussian_nll"
            )

    def on_fit_start(self) -> None:
        dm = self.datamodule
        if dm is not None:
            steps = min(dm.seq_len, self.train_window or dm.seq_len)
            what = f"the {self.model_name}"
            check_lstm_memory(self.net, dm.batch_size, steps, self.device, what, self.trainer.num_devices)

    def training_split(self, seq_len: int) -> int:
        """How many leading measurements of a training sequence of ``seq_len`` steps are given."""
        k = self.train_n_filter
        if k is None:
            k = self.n_filter if self.n_filter < seq_len else seq_len - (self.n_predict or 0)
        if not 1 <= k < seq_len:
            raise ValueError(
                f"training sequences have {seq_len} steps: giving {k} of them leaves "
                f"{'nothing' if k >= seq_len else 'too little'} to learn from; set model.init_args.train_n_filter "
                f"between 1 and {seq_len - 1}"
            )
        return k

    # ------------------------------------------------------------------ the network on a split sequence
    def run(self, y: torch.Tensor, n_given: int) -> SequenceOutput:
        """The network on ``y [B, T, ...]`` with the first ``n_given`` steps observed and the rest predicted."""
        observed = torch.zeros(y.shape[:2], dtype=torch.bool, device=y.device)
        observed[:, :n_given] = True
        return self.net(y, observed)

    def loss(self, out: SequenceOutput, y: torch.Tensor) -> torch.Tensor:
        if self.loss_name == "mse":
            return F.mse_loss(out.mean, y)
        if self.loss_name == "bce":
            return F.binary_cross_entropy(out.mean, y)
        return F.gaussian_nll_loss(out.mean, y, out.var)

    def window(self, y: torch.Tensor, random: bool) -> torch.Tensor:
        """``train_window`` consecutive steps of each sequence ``y [B, T, ...]``: at random starts, or the last ones."""
        w = self.train_window
        if w is None or w >= y.shape[1]:
            return y
        if not random:
            return y[:, -w:]
        start = torch.randint(0, y.shape[1] - w + 1, (len(y), 1), device=y.device)
        return y[torch.arange(len(y), device=y.device)[:, None], start + torch.arange(w, device=y.device)]

    def _step(self, batch: Mapping[str, torch.Tensor], stage: str) -> torch.Tensor:
        y = self.window(batch["y"], random=stage == "train")
        k = self.training_split(y.shape[1])
        out = self.run(y, k)
        loss = self.loss(out, y)
        bs = len(y)
        self.log(f"{stage}/loss", loss, batch_size=bs, prog_bar=True)
        self.log(f"{stage}/predict_mse", F.mse_loss(out.mean[:, k:], y[:, k:]), batch_size=bs)
        return loss

    def training_step(self, batch: Mapping[str, torch.Tensor], batch_idx: int) -> torch.Tensor:
        loss = self._step(batch, "train")
        if not torch.isfinite(loss):
            raise FloatingPointError(
                f"the {self.model_name}'s training loss is not finite at epoch {self.current_epoch}, step "
                f"{self.global_step}: lower the learning rate or clip gradients (trainer.gradient_clip_val)"
            )
        return loss

    def validation_step(self, batch: Mapping[str, torch.Tensor], batch_idx: int) -> None:
        self._step(batch, "val")

    def configure_optimizers(self) -> torch.optim.Optimizer:
        return torch.optim.Adam(self.parameters(), lr=self.lr)

    # ------------------------------------------------------------------ the protocol's hooks
    def forecast(self, y_filter: torch.Tensor, n_predict: int, u: torch.Tensor | None = None) -> Forecast:
        k = y_filter.shape[1]
        future = y_filter.new_zeros(y_filter.shape[0], n_predict, *y_filter.shape[2:])
        out = self.run(torch.cat([y_filter, future], 1), k)
        return Forecast(filtered=out.mean[:, :k], predicted=out.mean[:, k:])

    def describe(self) -> dict[str, Any]:
        return {"model": self.model_name, "inference": None, "label": self.model_name}

    # ------------------------------------------------------------------ checkpoints
    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        checkpoint["forecaster"] = type(self).__name__

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Refuse, with a message that says what the file is, a checkpoint of anything but this baseline."""
        super().on_load_checkpoint(checkpoint)
        kind = checkpoint.get("forecaster")
        state = checkpoint.get("state_dict", {})
        if kind != type(self).__name__:
            if holds_ssm(checkpoint) or SSM_DIGEST_KEY in checkpoint or any(k.startswith("ssm.") for k in state):
                what = "an SSM (or one of its encoder stages)"
            else:
                what = f"a {kind}" if kind else "not a checkpoint of this project's baselines"
            raise ValueError(
                f"the checkpoint is {what}, not a {type(self).__name__}: give --ckpt_path the last.ckpt of "
                f"`python cli.py fit` with this baseline's config"
            )
        if self.net is None and "obs_shape" in checkpoint.get("hyper_parameters", {}):
            self.build(tuple(checkpoint["hyper_parameters"]["obs_shape"]))


class LSTMBaseline(BaselineForecaster):
    """The paper's sequence-to-sequence CNN-LSTM (:class:`~ssm_ms.baselines.lstm.Seq2SeqLSTM`).

    ``network``: ``hidden`` (paper: 1024), ``encoder_preset``, ``decoder_preset`` (preset names, or the layers as
    mappings: see :class:`~ssm_ms.baselines.lstm.Seq2SeqLSTM`), ``output``.
    """

    model_name = "LSTM"
    method_kind = "lstm"

    def build_network(self, obs_shape: tuple[int, ...]) -> nn.Module:
        return Seq2SeqLSTM(obs_shape, **self.network_kwargs)


class RKNBaseline(BaselineForecaster):
    """The Recurrent Kalman Network (:class:`~ssm_ms.baselines.rkn.RecurrentKalmanNetwork`).

    ``network``: ``latent_state_dim`` (even; 30), ``n_basis`` (15), ``bandwidth`` (3), ``coeff_hidden``,
    ``encoder_preset``, ``encoder_hidden``, ``decoder_preset``, ``decoder_hidden``, ``initial_cov`` (10),
    ``normalize_latent_obs``, ``output``, ``initial_transition_var`` (0.1): the RKN code's defaults where
    it has them. Train it with gradient clipping (``trainer.gradient_clip_val``, the configs use 5).
    """

    model_name = "RKN"
    method_kind = "rkn"

    def build_network(self, obs_shape: tuple[int, ...]) -> nn.Module:
        return RecurrentKalmanNetwork(obs_shape, **self.network_kwargs)
