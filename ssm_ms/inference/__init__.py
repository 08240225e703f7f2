"""State inference for unseen sequences: CNN-LSTM encoder stage, batched UKF, particle filter."""

from ssm_ms.inference.encoder_module import StateEncoderModule
from ssm_ms.inference.filter_module import FilterForecaster
from ssm_ms.inference.particle import ParticleFilter
from ssm_ms.inference.ssm_forecaster import SSMForecaster
from ssm_ms.inference.ukf import UnscentedKalmanFilter

__all__ = ["FilterForecaster", "ParticleFilter", "SSMForecaster", "StateEncoderModule", "UnscentedKalmanFilter"]
