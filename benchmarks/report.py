"""What every benchmark results file states first, and how it is written: the date, the machine and the command."""

from __future__ import annotations

import datetime
import shlex
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ssm_ms.runtime.machine import describe  # noqa: E402


def provenance(script: str, argv: list[str] | None, machine: str = "") -> list[str]:
    """The ``- Date``, ``- Machine`` and ``- Command`` lines of a run of ``script`` (``benchmarks/<name>.py``) with
    the arguments ``argv`` (``None``: the command line's); ``machine``, if given, is appended to the machine line
    (threads, software versions, other processes' CPU use)."""
    args = sys.argv[1:] if argv is None else argv
    return [
        f"- Date: {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC",
        f"- Machine: {describe()}" + (f"; {machine}" if machine else ""),
        f"- Command: `{shlex.join(['python', script, *args])}`",
    ]


def write(out: str | Path, lines: list[str]) -> None:
    """Write the results file ``out`` (its folder made) and print it."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
