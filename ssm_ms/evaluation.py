"""The earlier name of :mod:`ssm_ms.forecasting.protocol` (the paper's forecasting protocol), kept importable."""

from ssm_ms.forecasting.protocol import (
    BCE_EPS,
    METRICS,
    Forecast,
    ForecastModule,
    ValidTimeAccumulator,
    bce_per_sequence,
    check_analysis,
    mse_per_sequence,
    sequence_metrics,
    split_sequence,
)

__all__ = ["BCE_EPS", "METRICS", "Forecast", "ForecastModule", "ValidTimeAccumulator", "bce_per_sequence",
           "check_analysis", "mse_per_sequence", "sequence_metrics", "split_sequence"]
