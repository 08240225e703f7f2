"""Second stage: a CNN-LSTM trained to map measurements to the latent states the SSM recovered.

Targets come from the trained SSM: for training trajectory ``j``, its latent trajectory is the
concatenation of ``f^k(s[j, i])``, ``k = 0..n-1``, over its shooting nodes ``i``. They are
normalised per component (statistics over all training trajectories, kept in the checkpoint) and
the encoder is trained by regression on the whole sequence. At test time it reads the first
``n_filter`` measurements and its last output starts the forecast.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from ssm_ms.inference.ssm_forecaster import SSMForecaster
from ssm_ms.nets.encoder import StateEncoder
from ssm_ms.runtime.memory import check_lstm_memory
from ssm_ms.training.shooting import rollout


class StateEncoderModule(SSMForecaster):
    """Trains a :class:`~ssm_ms.nets.encoder.StateEncoder` on the SSM's latent trajectories.

    Args:
        ssm_checkpoint: the trained ``MultipleShootingModule``: its checkpoint, or the model itself (frozen here).
        n_filter: measurements the encoder reads at test time.
        encoder: keyword arguments of ``StateEncoder`` (``preset``, ``hidden``, ...), without
            ``state_dim`` / ``obs_shape`` / ``input_dim`` / ``streams`` (taken from the SSM: an SSM whose ``g`` has one
            head per sensor gets an encoder that reads each sensor by itself, the CNN settings for its images).
        lr: Adam learning rate.
        validate_held_out: train on the training trajectories less the validation subset (the data's
            ``val_trajectories``), so that ``encoder/val_mse`` measures sequences the encoder has not seen (their
            targets are still the SSM's rollouts: the SSM trained on all of them). Without it (the default, as the
            paper's stages) the encoder trains on every trajectory and its validation cannot show it overfitting.
            A config that keeps its best epoch adds a ``ModelCheckpoint`` on ``encoder/val_mse`` (``best.ckpt``:
            docs/cli.md, "The best epoch").
        metrics: scores of the test protocol.
        **kwargs: the protocol's other arguments (``n_predict``, ``bce_reduction``, ``original_units``,
            ``experiment``, ``results_dir``, ``figures_dir``, ``method_name``, ``analysis``), see
            :class:`~ssm_ms.forecasting.protocol.ForecastModule`.
    """

    method_kind = "encoder"
    validates_on_training_trajectories = True  # its targets are the SSM's rollouts from training nodes

    def __init__(
        self,
        ssm_checkpoint: str | nn.Module | None = None,
        *,
        n_filter: int,
        encoder: dict[str, Any] | None = None,
        lr: float = 1e-3,
        validate_held_out: bool = False,
        metrics: list[str] = ["mse", "bce"],  # noqa: B006 (read, never mutated; a list for the CLI)
        **kwargs: Any,
    ):
        if not lr > 0:
            raise ValueError(f"the learning rate must be > 0, got {lr}: set model.init_args.lr (e.g. 1e-3)")
        super().__init__(ssm_checkpoint, n_filter=n_filter, metrics=metrics, **kwargs)
        self.validate_held_out = validate_held_out  # read by the DataModule's training loader
        streams = getattr(self.ssm.g, "shapes", None)  # several sensors: g's heads name them (SensorHeads)
        one_vector = len(self.ssm.obs_shape()) == 1 and not streams
        kwargs = dict(encoder or {"preset": "vector" if one_vector else None})
        for reserved in ("state_dim", "obs_shape", "input_dim", "streams"):
            if reserved in kwargs:
                raise ValueError(f"encoder.{reserved} comes from the SSM checkpoint; remove it from the config")
        self.encoder = StateEncoder(
            self.ssm.state_dim, self.ssm.obs_shape(), input_dim=self.ssm.input_dim, streams=streams, **kwargs
        )
        d = self.ssm.state_dim
        self.register_buffer("latent_mean", torch.zeros(d))
        self.register_buffer("latent_std", torch.ones(d))
        self.register_buffer("latent_stats_ready", torch.tensor(False))

    # ------------------------------------------------------------------ targets
    @torch.no_grad()
    def latent_targets(self, index: torch.Tensor, seq_len: int, u: torch.Tensor | None = None) -> torch.Tensor:
        """The SSM's latent trajectories ``[B, T, d]`` of training trajectories ``index`` (under their inputs
        ``u [B, T, m]``, each piece its own slice, for a driven SSM)."""
        nodes = self.ssm.node_states(index)  # [B, m, d]
        b, m, d = nodes.shape
        n = seq_len // m
        pieces = None if u is None else u[:, : m * n].reshape(b * m, n, -1).to(nodes)
        return rollout(self.ssm.f, nodes.reshape(b * m, d), n, pieces).view(b, m * n, d)

    def training_inputs(self, index: torch.Tensor) -> torch.Tensor | None:
        """The inputs ``[B, T, m]`` (as served: normalised) of training trajectories ``index`` (``None``: the SSM is
        not driven)."""
        if not self.input_dim:
            return None
        train = self.datamodule.train_split()
        return train.__getitems__(index.cpu().tolist())["u"].to(self.device)

    @torch.no_grad()
    def compute_latent_statistics(self, seq_len: int, chunk: int = 1024) -> None:
        """Per-component mean and std of the latent trajectories of all training trajectories."""
        n_traj = self.ssm.nodes.num_embeddings
        total = torch.zeros(self.ssm.state_dim, dtype=torch.float64, device=self.device)
        total_sq = torch.zeros_like(total)
        count = 0
        for start in range(0, n_traj, chunk):
            index = torch.arange(start, min(start + chunk, n_traj), device=self.device)
            z = self.latent_targets(index, seq_len, self.training_inputs(index)).double().flatten(0, 1)
            total += z.sum(0)
            total_sq += z.pow(2).sum(0)
            count += len(z)
        mean = total / count
        std = (total_sq / count - mean.pow(2)).clamp_min(0).sqrt()
        self.latent_mean.copy_(mean.float())
        self.latent_std.copy_(std.float().clamp_min(1e-6))
        self.latent_stats_ready.fill_(True)

    def setup(self, stage: str) -> None:
        super().setup(stage)
        dm = self.datamodule
        if stage == "fit" and not bool(self.latent_stats_ready):
            self.compute_latent_statistics(dm.seq_len)

    def on_fit_start(self) -> None:
        self.ssm.eval()  # frozen: the trainer puts the whole module in train mode
        dm = self.datamodule
        if dm is not None:  # the encoder trains on whole training sequences
            check_lstm_memory(
                self.encoder, dm.batch_size, dm.seq_len, self.device, "the encoder", self.trainer.num_devices
            )

    # ------------------------------------------------------------------ training
    def _regression(self, batch: Mapping[str, torch.Tensor]) -> torch.Tensor:
        y, u = batch["y"], batch.get("u")
        target = (self.latent_targets(batch["index"], y.shape[1], u) - self.latent_mean) / self.latent_std
        return F.mse_loss(self.encoder(y, u), target)

    def training_step(self, batch: Mapping[str, torch.Tensor], batch_idx: int) -> torch.Tensor:
        loss = self._regression(batch)
        self.log("encoder/train_mse", loss, batch_size=len(batch["y"]), prog_bar=True)
        return loss

    def validation_step(self, batch: Mapping[str, torch.Tensor], batch_idx: int) -> None:
        self.log("encoder/val_mse", self._regression(batch), batch_size=len(batch["y"]), prog_bar=True)

    def configure_optimizers(self) -> torch.optim.Optimizer:
        return torch.optim.Adam(self.encoder.parameters(), lr=self.hparams.lr)

    # ------------------------------------------------------------------ inference
    def infer(self, y_filter: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        if not bool(self.latent_stats_ready):
            raise RuntimeError(
                "this encoder has not been trained: fit it first (python cli.py fit --config <encoder config>) "
                "and test with --ckpt_path <its checkpoint>"
            )
        return self.encoder(y_filter, u) * self.latent_std + self.latent_mean
