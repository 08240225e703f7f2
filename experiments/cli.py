"""The repository's command line, ``python cli.py {fit,validate,test,predict} --config configs/<experiment>.yaml``:
the library's (:func:`ssm_ms.__main__.main`), then the markdown report of each results file the run wrote
(``<results_dir>/<experiment>.md`` beside its ``.json``: :func:`render_report`), whether the run ended well or not."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


def render_report(json_path: Path) -> Path:
    """Render the ``.md`` beside a results file by what it holds: an identification benchmark's runs (scored per test
    recording: :func:`experiments.benchmark_results.render_file`), else the forecasting protocol's (and the
    closed-loop control's: :func:`experiments.results.render_file`); return the ``.md``'s path."""
    from experiments import benchmark_results, results
    from ssm_ms.forecasting.results import load

    if benchmark_results.is_benchmark_results(load(Path(json_path))):
        return benchmark_results.render_file(json_path)
    return results.render_file(json_path)


@contextmanager
def reports() -> Iterator[None]:
    """Render the report of every results file written in this block (:data:`ssm_ms.forecasting.results.WRITTEN`),
    also where it ends in an error or an interrupt."""
    from ssm_ms.forecasting.results import WRITTEN

    first = len(WRITTEN)
    try:
        yield
    finally:
        written = [path for path in dict.fromkeys(WRITTEN[first:]) if path.is_file()]
        for path in written:
            render_report(path)


def main(argv: list[str] | None = None) -> None:
    from ssm_ms.__main__ import main as run

    with reports():
        run(argv)


if __name__ == "__main__":
    main()
