"""Forecasting, for every forecaster (an SSM with an inference method, a baseline): the paper's test protocol
(:mod:`~ssm_ms.forecasting.protocol`: :class:`ForecastModule`; its metrics :mod:`~ssm_ms.forecasting.metrics`, its
analysis options :mod:`~ssm_ms.forecasting.analysis_settings`, the valid time :mod:`~ssm_ms.forecasting.valid_time`), the results
files beside the paper's tables (:mod:`~ssm_ms.forecasting.results`) and over seeds
(:mod:`~ssm_ms.forecasting.seeds`), the ``predict`` writer
(:mod:`~ssm_ms.forecasting.writer`) and the forecast figures (:mod:`~ssm_ms.forecasting.figures`)."""

from ssm_ms.forecasting.protocol import Forecast, ForecastModule
from ssm_ms.forecasting.writer import ForecastWriter

__all__ = ["Forecast", "ForecastModule", "ForecastWriter"]
