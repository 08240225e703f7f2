"""The earlier name of :mod:`ssm_ms.forecasting.results` (results files beside the paper's tables), kept importable."""

from ssm_ms.forecasting.results import (
    PAPER,
    paper_key,
    paper_row,
    render_markdown,
    write_pipeline,
    write_results,
)

__all__ = ["PAPER", "paper_key", "paper_row", "render_markdown", "write_pipeline", "write_results"]
