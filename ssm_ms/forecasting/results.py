"""The results file of a test run: ``<results_dir>/<experiment>.json``, the one source of every score.

Every forecaster of one experiment (SSM + encoder, SSM + UKF, the LSTM and RKN baselines) and the closed-loop control
land in the same file: each test run replaces its own method's entry (``runs``), written whole or not at all (the
identification benchmarks' files go through the same writer: :mod:`ssm_ms.forecasting.benchmark_results`). The
library writes JSON only; what reads it (a markdown report, tables beside a paper's) is the application's
(``experiments/``: ``python cli.py test`` renders ``<experiment>.md`` beside each file a run wrote).
"""

from __future__ import annotations

import json
import os
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

# the results files this process wrote, in order (an application renders them after the run: experiments/cli.py)
WRITTEN: list[Path] = []


def results_folder(results_dir: str | Path | None, trainer: Any) -> Path:
    """Where a test run's results file goes: ``results_dir`` where given, else the run's own folder (the trainer's
    ``log_dir``: the logger's version folder, or ``default_root_dir`` without a logger)."""
    if results_dir is not None:
        return Path(results_dir)
    return Path(trainer.log_dir or trainer.default_root_dir)


def load(json_path: Path) -> dict[str, Any]:
    """The results file's content; ``{}`` where there is none yet. A file that is not a results file (not a JSON
    object: written by hand, or cut short by an older version's interrupted write) is moved aside to
    ``<name>.unreadable``, with a warning, rather than overwritten: the runs it held stay to be restored."""
    if not json_path.exists():
        return {}
    try:
        data = json.loads(json_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError):
        data = None
    if isinstance(data, dict):
        return data
    aside = json_path.with_name(json_path.name + ".unreadable")
    n = 1
    while aside.exists():  # an earlier file set aside stays too
        n += 1
        aside = json_path.with_name(f"{json_path.name}.unreadable-{n}")
    os.replace(json_path, aside)
    warnings.warn(
        f"{json_path} is not a results file (not a JSON object): moved to {aside} and a new one started; "
        "restore the runs it held from that file (or from git)",
        stacklevel=2,
    )
    return {}


def replace_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` whole or not at all: an interrupted write (Ctrl-C, SIGTERM, a full disk) leaves
    the file as it was."""
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def update_results(
    results_dir: Path,
    experiment: str,
    change: Callable[[dict[str, Any]], None],
    *,
    sort_keys: bool = True,
    end: str = "",
) -> Path:
    """Apply ``change`` to the content of ``<results_dir>/<experiment>.json`` (``{}`` where there is none yet) and
    write it back whole (``sort_keys``: keys sorted, or in the order ``change`` leaves them; ``end``: the text after
    the JSON); return its path (also recorded in :data:`WRITTEN`)."""
    results_dir = Path(results_dir)
    results_dir.mkdir(parents=True, exist_ok=True)
    path = results_dir / f"{experiment}.json"
    data = load(path)
    change(data)
    data["experiment"] = experiment
    replace_text(path, json.dumps(data, indent=2, sort_keys=sort_keys) + end)
    WRITTEN.append(path)
    return path


def write_results(
    results_dir: Path,
    info: dict[str, Any],
    summary: dict[str, dict[str, float]],
    analysis: dict[str, Any] | None = None,
    heading: dict[str, str] | None = None,
) -> Path:
    """Merge one test run (``info``: what ran, its ``experiment`` and ``method``; ``summary``: its scores) into
    ``<results_dir>/<experiment>.json``; return that file's path. ``heading`` (``{"title", "intro"}``) is kept in
    the file for a report of a results file that is not the forecasting protocol's, e.g. closed-loop control."""

    def merge(data: dict[str, Any]) -> None:
        if heading is not None:
            data["heading"] = heading
        run: dict[str, Any] = {"info": info, "summary": summary}
        if analysis:
            run["analysis"] = analysis
        data.setdefault("runs", {})[info["method"]] = run

    return update_results(results_dir, info["experiment"], merge)
