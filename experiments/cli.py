"""The repository's command line, ``python cli.py {fit,validate,test,predict} --config configs/<experiment>.yaml``:
the library's (:func:`ssm_ms.__main__.main`), then the markdown report of each results file the run wrote
(``<results_dir>/<experiment>.md`` beside its ``.json``: :func:`experiments.results.render_file`), whether the run
ended well or not."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager


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
        if written:
            from experiments.results import render_file

            for path in written:
                render_file(path)


def main(argv: list[str] | None = None) -> None:
    from ssm_ms.__main__ import main as run

    with reports():
        run(argv)


if __name__ == "__main__":
    main()
