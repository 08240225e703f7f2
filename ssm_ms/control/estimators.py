"""The state estimators of the closed loop: the latent state of a learned SSM from the measurements so far.

Both are recursive (one update per control period) and run on a batch of episodes:

- :class:`UKFEstimator`: the unscented Kalman filter over the SSM's own ``f(x, u)`` and ``g`` (no training beyond
  the SSM), started at the mean shooting node.
- :class:`ChartUKFEstimator`: the same filter over the code of a chart of the model's states
  (:class:`~ssm_ms.inference.chart.StateChart`), so that its estimate stays among the states training produced.
- :class:`EncoderEstimator`: the CNN-LSTM encoder trained on the SSM's latent trajectories (the forecasting stage,
  ``configs/<experiment>_encoder.yaml``), stepped one measurement at a time
  (:meth:`~ssm_ms.nets.encoder.StateEncoder.step`).

``start(y)`` takes the first measurements ``[B, ...]`` (as the environment gives them) and returns the state
``[B, d]``; ``next(u, y)`` takes the torques applied since (N m, ``[B, m]``) and the new measurements.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import torch

from ssm_ms.inference.ukf import UnscentedKalmanFilter

Transform = Callable[[torch.Tensor], torch.Tensor]


class UKFEstimator:
    """The UKF over ``f`` (taking torques in N m) and ``g``, from the ``prior`` state; measurements pass through
    ``to_frames`` (the SSM's normalisation) first."""

    def __init__(self, ukf: UnscentedKalmanFilter, prior: torch.Tensor, to_frames: Transform):
        self.ukf, self.prior, self.to_frames = ukf, prior, to_frames

    def start(self, y: torch.Tensor) -> torch.Tensor:
        b, d = len(y), self.prior.shape[-1]
        mean = self.prior.expand(b, -1).clone()
        cov = self.ukf.initial_covariance(b, d, mean.dtype, mean.device)
        self.mean, self.cov = self.ukf.update(mean, cov, self.to_frames(y))
        return self.mean

    def next(self, u: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        mean, cov = self.ukf.predict(self.mean, self.cov, u)
        self.mean, self.cov = self.ukf.update(mean, cov, self.to_frames(y))
        return self.mean


class ChartUKFEstimator(UKFEstimator):
    """The UKF over a :class:`~ssm_ms.inference.chart.StateChart`'s codes (``ukf`` built on ``E(f(D(z), u))`` and
    ``g(D(z))``), from code 0 (the mean code of the chart's states); returns the decoded states ``D(z)``."""

    def __init__(self, ukf: UnscentedKalmanFilter, chart, to_frames: Transform):
        super().__init__(ukf, torch.zeros(chart.dims), to_frames)
        self.chart = chart

    def start(self, y: torch.Tensor) -> torch.Tensor:
        return self.chart.decode(super().start(y))

    def next(self, u: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return self.chart.decode(super().next(u, y))


class EncoderEstimator:
    """A trained :class:`~ssm_ms.inference.StateEncoderModule`'s encoder, one measurement at a time: measurements
    through ``to_frames`` and torques through ``to_inputs`` (the normalisations it was trained with), its output
    mapped back to the SSM's latent units (the module's ``latent_mean`` and ``latent_std``)."""

    def __init__(self, module, to_frames: Transform, to_inputs: Transform):
        self.encoder = module.encoder
        self.mean, self.std = module.latent_mean, module.latent_std
        self.to_frames, self.to_inputs = to_frames, to_inputs

    def start(self, y: torch.Tensor) -> torch.Tensor:
        z, self.memory = self.encoder.step(self.to_frames(y))
        return z * self.std + self.mean

    def next(self, u: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        z, self.memory = self.encoder.step(self.to_frames(y), self.to_inputs(u), self.memory)
        return z * self.std + self.mean


def load_encoder(path: str, ssm_checkpoint: str, ssm: torch.nn.Module):
    """The :class:`~ssm_ms.inference.StateEncoderModule` of ``path`` (a file stripped without its SSM takes it from
    ``ssm_checkpoint``), refused unless it was trained on ``ssm`` (the same weights, within 1% of each tensor's
    largest value)."""
    from ssm_ms.inference import StateEncoderModule

    if not Path(path).is_file():
        raise ValueError(
            f"no encoder checkpoint at {path}: train one first (python cli.py fit --config "
            f"configs/<experiment>_encoder.yaml --model.init_args.ssm_checkpoint {ssm_checkpoint})"
        )
    another = (
        f"encoder_checkpoint {path} was trained on another SSM than ssm_checkpoint {ssm_checkpoint} (they differ in "
        "{}): give the encoder trained on this SSM (its hyperparameters name its ssm_checkpoint)"
    )
    try:
        module = StateEncoderModule.load_from_checkpoint(
            path, map_location="cpu", weights_only=False, ssm_checkpoint=str(ssm_checkpoint)
        )
    except RuntimeError as e:  # the file's SSM weights do not fit the given SSM's networks
        raise ValueError(another.format("their networks")) from e
    own, theirs = ssm.state_dict(), module.ssm.state_dict()
    differs = sorted(set(own) ^ set(theirs)) or [
        k
        for k, v in own.items()
        if v.shape != theirs[k].shape
        or (v.is_floating_point() and (v - theirs[k]).abs().max() > 1e-2 * v.abs().max().clamp_min(1e-12))
    ]
    if differs:
        raise ValueError(another.format(differs[0]))
    return module.eval()
