"""State inference for unseen sequences: CNN-LSTM encoder stage, batched UKF, particle filter, and states fitted by
optimisation through the frozen SSM."""

from ssm_ms.inference.encoder_module import StateEncoderModule
from ssm_ms.inference.filter_module import FilterForecaster
from ssm_ms.inference.optimise import OptimisationForecaster, fit_nodes
from ssm_ms.inference.particle import ParticleFilter
from ssm_ms.inference.ssm_forecaster import SSMForecaster
from ssm_ms.inference.ukf import UnscentedKalmanFilter

__all__ = [
    "FilterForecaster",
    "OptimisationForecaster",
    "ParticleFilter",
    "SSMForecaster",
    "StateEncoderModule",
    "UnscentedKalmanFilter",
    "fit_nodes",
]
