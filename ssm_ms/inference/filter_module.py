"""Evaluation with a filter that uses the learned ``f`` and ``g`` directly: UKF or particle filter.

Nothing is trained: ``python cli.py test --config configs/lorenz_T1000_ukf.yaml`` runs the protocol.
The prior mean at time 0 is the mean of the SSM's shooting nodes, with the components the SSM's
``node_init_map`` reads from measurements set from the first measurement instead (Lorenz: the
measured coordinate starts at ``y[0]``).
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import nn

from ssm_ms.inference.particle import ParticleFilter
from ssm_ms.inference.ssm_forecaster import SSMForecaster
from ssm_ms.inference.ukf import UnscentedKalmanFilter
from ssm_ms.nets.sensors import SensorLayout


class FilterForecaster(SSMForecaster):
    """The forecasting protocol with states inferred by a UKF or a particle filter.

    Args:
        ssm_checkpoint: the trained ``MultipleShootingModule``: its checkpoint, or the model itself.
        n_filter: measurements filtered before predicting.
        method: ``"ukf"`` or ``"pf"``.
        process_var: process noise variance of the UKF (paper: 1e-6).
        process_std: process noise std of the particle filter: it keeps the cloud from collapsing
            after resampling, so it must be larger than the UKF's (1e-3 lost Lorenz's unobserved
            components in our tests, 1e-2 tracked them).
        measurement_var: measurement noise variance, in the units the SSM was trained in (normalised for Lorenz;
            paper: 0.5); a scalar or one per measured component. Unset: for data of several sensors (their
            ``sensor_layout``), each component's stream's ``noise_std ** 2``; else 0.5.
        init_var: prior variance at time 0 (paper: 0.1).
        init_mean: the prior mean at time 0 of the components no measurement sets (``node_init_map``):
            ``"nodes"`` (the default) the mean of the SSM's shooting nodes, ``"zero"`` zero, as the paper's filter
            (their measured effect on Lorenz: studies/ukf_settings/README.md).
        unscented: the UKF's sigma-point parameters, any of ``alpha``, ``beta``, ``kappa`` (default
            ``{alpha: 1, beta: 2, kappa: 0}``; ``{beta: 0}`` is the cubature rule, 2d points instead of 2d+1), and
            ``iterations``, its measurement updates per step (default 1; more: the iterated posterior linearisation,
            :class:`~ssm_ms.inference.UnscentedKalmanFilter`).
        n_particles, likelihood, resample_threshold, likelihood_scale, seed: particle filter settings
            (``likelihood="bernoulli"`` for images in [0, 1]).
        autocast: ``None`` (full precision) or ``"bfloat16"`` / ``"float16"``: run ``f`` and ``g`` under
            ``torch.autocast`` inside the filter (faster on CPUs with AVX512-BF16 and on GPUs; see
            benchmarks/results/ukf.md for speed and effect on the Lorenz results).
        metrics: scores of the test protocol.
        method_name: label of the results (default: ``method``).
        **kwargs: the protocol's other arguments (``n_predict``, ``bce_reduction``, ``original_units``,
            ``experiment``, ``results_dir``, ``figures_dir``, ``analysis``), see
            :class:`~ssm_ms.forecasting.protocol.ForecastModule`.
    """

    def __init__(
        self,
        ssm_checkpoint: str | nn.Module | None = None,
        *,
        n_filter: int,
        method: str = "ukf",
        process_var: float = 1e-6,
        process_std: float = 1e-2,
        measurement_var: float | list[float] | None = None,
        init_var: float = 0.1,
        init_mean: str = "nodes",
        unscented: dict[str, float] | None = None,
        n_particles: int = 1000,
        likelihood: str = "gaussian",
        resample_threshold: float = 0.5,
        likelihood_scale: float = 1.0,
        seed: int = 0,
        autocast: str | None = None,
        metrics: list[str] = ["mse"],  # noqa: B006 (read, never mutated; a list for the CLI)
        method_name: str | None = None,
        **kwargs: Any,
    ):
        if method not in ("ukf", "pf"):
            raise ValueError(f"method must be 'ukf' or 'pf', got {method!r}")
        if init_mean not in ("nodes", "zero"):
            raise ValueError(f"init_mean must be 'nodes' (the shooting nodes' mean) or 'zero', got {init_mean!r}")
        unscented = dict(unscented or {})
        unknown = set(unscented) - {"alpha", "beta", "kappa", "iterations"}
        if unknown:
            raise ValueError(f"unscented takes alpha, beta, kappa and iterations, got {sorted(unknown)}")
        if unscented and method != "ukf":
            raise ValueError("unscented sets the UKF's sigma points: it has no effect with method 'pf', remove it")
        super().__init__(
            ssm_checkpoint, n_filter=n_filter, metrics=metrics, method_name=method_name or method, **kwargs
        )
        self.method_kind = method
        self.init_mean = init_mean
        self.measurement_var_given = measurement_var is not None  # else the data's sensors' noise, at setup
        measurement_var = 0.5 if measurement_var is None else measurement_var
        f, g = self.ssm.f, self.ssm.g
        if method == "ukf":
            self.filter = UnscentedKalmanFilter(
                f,
                g,
                process_var=process_var,
                measurement_var=measurement_var,
                init_var=init_var,
                state_dim=self.ssm.state_dim,
                autocast=autocast,
                **unscented,
            )
        else:
            self.filter = ParticleFilter(
                f,
                g,
                n_particles=n_particles,
                process_std=process_std,
                measurement_std=torch.as_tensor(measurement_var, dtype=torch.float64).sqrt().tolist(),
                likelihood=likelihood,
                init_std=math.sqrt(init_var),
                resample_threshold=resample_threshold,
                likelihood_scale=likelihood_scale,
                seed=seed,
                state_dim=self.ssm.state_dim,
                autocast=autocast,
            )

    def setup(self, stage: str) -> None:
        super().setup(stage)
        layout = getattr(self.datamodule, "sensor_layout", None)
        if layout and not self.measurement_var_given:
            variances = SensorLayout.from_state_dict(layout).variances().tolist()
            if isinstance(self.filter, UnscentedKalmanFilter):
                self.filter.measurement_var = torch.tensor(variances, dtype=self.filter.measurement_var.dtype)
            else:
                self.filter.measurement_std = torch.tensor(variances, dtype=self.filter.measurement_std.dtype).sqrt()

    def inference_settings(self) -> str:
        flt = self.filter
        if isinstance(flt, UnscentedKalmanFilter):
            noise = (
                f"process_var={flt.process_var.tolist()}, measurement_var={flt.measurement_var.tolist()}, "
                f"init_var={flt.init_var.tolist()}, alpha={flt.alpha:g}, beta={flt.beta:g}, kappa={flt.kappa:g}"
            )
        else:
            noise = (
                f"n_particles={flt.n_particles}, process_std={flt.process_std.tolist()}, "
                f"measurement_std={flt.measurement_std.tolist()}, likelihood={flt.likelihood}"
            )
        precision = (
            "full precision"
            if flt.autocast is None
            else f"f and g under autocast({str(flt.autocast).removeprefix('torch.')})"
        )
        start = "" if self.init_mean == "nodes" else f"; init_mean={self.init_mean}"
        return f"{type(flt).__name__}: {noise}{start}; {precision}"

    def prior_mean(self, y_filter: torch.Tensor) -> torch.Tensor:
        """``[B, d]``: the mean shooting node (``init_mean: zero``: zero), with measured components taken from
        ``y[0]`` (:meth:`~ssm_ms.inference.SSMForecaster.start_states`)."""
        base = torch.zeros(self.ssm.state_dim) if self.init_mean == "zero" else None  # None: the mean node
        return self.start_states(y_filter[:, :1], base)[:, 0]

    def infer(self, y_filter: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        x0 = self.prior_mean(y_filter)
        given = None if u is None else u[:, : y_filter.shape[1] - 1]
        out = self.filter.filter(y_filter, x0, u=given)
        return out if isinstance(out, torch.Tensor) else out.means

    def infer_distribution(
        self, y_filter: torch.Tensor, n_predict: int, u: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Filtered means ``[B, k, d]`` (as :meth:`infer`) and covariances ``[B, k + p, d, d]``: the posterior ones
        over the ``k`` given steps, then the filter's own prediction without measurements for ``p`` steps (UKF:
        unscented time updates with the process noise; particle filter: the last posterior's weighted particles
        moved through ``f`` with the process noise). These describe the spread around the filter's predicted
        mean, which differs from the point forecast ``f^j(x[k-1])`` only by the nonlinearity of ``f``."""
        x0 = self.prior_mean(y_filter)
        k = y_filter.shape[1]
        given, future = (None, None) if u is None else (u[:, : k - 1], u[:, k - 1 : k - 1 + n_predict])
        if isinstance(self.filter, UnscentedKalmanFilter):
            result = self.filter.filter(y_filter, x0, u=given)
            mean, cov, ahead = result.means[:, -1], result.covs[:, -1], []
            for j in range(n_predict):
                mean, cov = self.filter.predict(mean, cov, None if future is None else future[:, j])
                ahead.append(cov)
            return result.means, torch.cat([result.covs, torch.stack(ahead, 1)], 1)
        result = self.filter.filter(y_filter, x0, return_particles=True, u=given)
        ahead = self.filter.propagate(result.particles, result.weights, n_predict, u=future)
        return result.means, torch.cat([result.covs, ahead], 1)
