"""Forecasting, for every forecaster (an SSM with an inference method, a baseline): the paper's test protocol
(:mod:`~ssm_ms.forecasting.protocol`: :class:`ForecastModule`; its metrics :mod:`~ssm_ms.forecasting.metrics`, its
analysis options :mod:`~ssm_ms.forecasting.analysis_settings`, the valid time
:mod:`~ssm_ms.forecasting.valid_time`), the results files (:mod:`~ssm_ms.forecasting.results`, JSON), the ``predict`` writer
(:mod:`~ssm_ms.forecasting.writer`) and the forecast figures (:mod:`~ssm_ms.forecasting.figures`)."""

import importlib

__all__ = ["Forecast", "ForecastModule", "ForecastWriter"]

# Imported when first asked for (``ssm_ms.forecasting.ForecastWriter`` in a config): the results files and
# the application (``experiments/``) use this package without Lightning (~10 s of imports on a slow 2-core CPU).
_HOMES = {"Forecast": "protocol", "ForecastModule": "protocol", "ForecastWriter": "writer"}


def __getattr__(name: str):
    if name in _HOMES:
        return getattr(importlib.import_module(f"{__name__}.{_HOMES[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
