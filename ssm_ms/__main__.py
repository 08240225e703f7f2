"""The library's command line: ``python -m ssm_ms {fit,validate,test,predict} --config configs/<experiment>.yaml``,
the LightningCLI of :mod:`ssm_ms.cli`. The repository's ``python cli.py ...`` (and the console script ``ssm-ms``) is
this program followed by the application's reports (``experiments/cli.py``: the ``.md`` beside each results file).

A ``--config`` file that does not exist is refused here, before Lightning is imported (~10 s on a slow CPU).
"""

from __future__ import annotations

import sys
from pathlib import Path


def missing_config(argv: list[str]) -> str | None:
    """The first ``--config`` file of the command line that is not a file, or None."""
    for i, arg in enumerate(argv):
        if arg == "--config" and i + 1 < len(argv):
            path = argv[i + 1]
        elif arg.startswith("--config="):
            path = arg.split("=", 1)[1]
        else:
            continue
        if not Path(path).is_file():
            return path
    return None


def main(argv: list[str] | None = None) -> None:
    """Check the ``--config`` files, then run the LightningCLI on ``argv`` (default: ``sys.argv[1:]``)."""
    missing = missing_config(sys.argv[1:] if argv is None else list(argv))
    if missing is not None:
        print(f"error: --config {missing}: no such file (the shipped configs are under configs/)", file=sys.stderr)
        raise SystemExit(2)
    from ssm_ms.cli import main as cli_main

    cli_main(argv)


if __name__ == "__main__":
    main()
