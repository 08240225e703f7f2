"""State inference for unseen sequences: CNN-LSTM encoder stage, batched UKF, particle filter, and states fitted by
optimisation through the frozen SSM.

The names are imported on first use, so that a filter alone (``ssm_ms.inference.ukf``, the control loop's estimators,
``benchmarks/bench_ukf.py``) does not pay for Lightning, which the forecasters and the encoder stage need.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ssm_ms.inference.encoder_module import StateEncoderModule
    from ssm_ms.inference.filter_module import FilterForecaster
    from ssm_ms.inference.optimise import OptimisationForecaster, fit_nodes
    from ssm_ms.inference.particle import ParticleFilter
    from ssm_ms.inference.ssm_forecaster import SSMForecaster
    from ssm_ms.inference.ukf import UnscentedKalmanFilter

_HOMES = {
    "FilterForecaster": "filter_module",
    "OptimisationForecaster": "optimise",
    "ParticleFilter": "particle",
    "SSMForecaster": "ssm_forecaster",
    "StateEncoderModule": "encoder_module",
    "UnscentedKalmanFilter": "ukf",
    "fit_nodes": "optimise",
}
__all__ = [
    "FilterForecaster",
    "OptimisationForecaster",
    "ParticleFilter",
    "SSMForecaster",
    "StateEncoderModule",
    "UnscentedKalmanFilter",
    "fit_nodes",
]


def __getattr__(name: str) -> Any:
    if name in _HOMES:
        return getattr(importlib.import_module(f"ssm_ms.inference.{_HOMES[name]}"), name)
    raise AttributeError(f"module 'ssm_ms.inference' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
