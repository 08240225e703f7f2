"""The earlier name of :mod:`ssm_ms.forecasting.writer`: ``--trainer.callbacks+=ssm_ms.predict.ForecastWriter``
keeps working (``ssm_ms.forecasting.ForecastWriter`` is the name to use)."""

from ssm_ms.forecasting.writer import ForecastWriter

__all__ = ["ForecastWriter"]
