"""Forecasters without an SSM, for the paper's comparisons: the sequence-to-sequence CNN-LSTM and the
Recurrent Kalman Network (Becker et al. 2019), trained on the same DataModules and tested by the same
protocol (:mod:`ssm_ms.forecasting.protocol`)."""

from ssm_ms.baselines.lstm import Seq2SeqLSTM
from ssm_ms.baselines.module import BaselineForecaster, LSTMBaseline, RKNBaseline
from ssm_ms.baselines.rkn import RecurrentKalmanNetwork

__all__ = ["BaselineForecaster", "LSTMBaseline", "RKNBaseline", "RecurrentKalmanNetwork", "Seq2SeqLSTM"]
