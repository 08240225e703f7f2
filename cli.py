"""Command line of ssm-ms: ``python cli.py {fit,validate,test,predict} --config configs/<experiment>.yaml``.

LightningCLI in subclass mode with the omegaconf parser: a config names the model and the data by
``class_path`` and may interpolate (``${model.init_args.state_dim}``). ``python cli.py fit --help``
lists every option; ``--print_config`` shows the resolved configuration (interpolations resolved after
the command line). A user's mistake prints one ``error: ...`` line and exits non-zero without a
traceback; ``SSM_MS_TRACEBACK=1`` shows the full traceback. Ctrl-C prints the command that resumes the
run from its last completed epoch. See ``ssm_ms/cli.py``.

A ``--config`` file that does not exist is refused here, before Lightning is imported (~10 s on a slow CPU).
"""

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


if __name__ == "__main__":
    missing = missing_config(sys.argv[1:])
    if missing is not None:
        print(f"error: --config {missing}: no such file (the shipped configs are under configs/)", file=sys.stderr)
        raise SystemExit(2)
    from ssm_ms.cli import main

    main()
