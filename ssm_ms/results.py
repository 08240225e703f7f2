"""Results files of the forecasting protocol: ``results/<experiment>.json`` and a markdown table.

Several inference methods of one experiment (e.g. Lorenz with the encoder and with the UKF) land in
the same files: each test run replaces its own method's entry and the table is rebuilt from all.

``PAPER`` holds the paper's tables as rows of ``{column: value}``; a value of ``None`` is printed as
"not transcribed": those cells must be filled from the paper (Jordana et al. 2021, Tables 1-4).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

# Paper tables. Columns are "<target>/<metric>" as produced by the protocol. None: not transcribed yet.
PAPER: dict[str, dict[str, Any]] = {
    "pendulum": {
        "table": "Table 1 (simple pendulum, 50 frames filtered, 50 predicted, per-pixel scores vs noisy frames)",
        "rows": {m: {"noisy/mse": None, "noisy/bce": None} for m in ("SSM-LL", "SSM-FC", "RKN", "LSTM")},
    },
    "quad": {
        "table": "Table 2 (quadruple pendulum, 50 frames filtered, 50 predicted, per-pixel scores vs noisy frames)",
        "rows": {m: {"noisy/mse": None, "noisy/bce": None} for m in ("SSM-LL", "SSM-FC", "RKN", "LSTM")},
    },
    "mnist": {
        "table": "Table 3 (Moving MNIST, 10 frames filtered, 10 predicted, BCE summed over the pixels of a frame)",
        "rows": {m: {"noisy/bce": None} for m in ("SSM-LL", "RKN", "LSTM")},
    },
    "lorenz": {
        "table": "Table 4 (Lorenz, 1990 steps filtered, 10 predicted, MSE vs noiseless x in original units)",
        "rows": {f"T={t}": {"clean/mse": None} for t in (10, 100, 1000, 10000)},
    },
}


def paper_key(experiment: str) -> str | None:
    """Which paper table an experiment belongs to (``pendulum_fc`` -> ``pendulum``, ``lorenz_T1000`` -> ``lorenz``)."""
    for key in sorted(PAPER, key=len, reverse=True):
        if experiment == key or experiment.startswith(key + "_"):
            return key
    return None


def _cell(entry: dict[str, float] | None) -> str:
    if entry is None:
        return "—"
    return f"{entry['mean']:.4g} ± {entry['std']:.2g}"


def render_markdown(experiment: str, runs: dict[str, dict[str, Any]], pipeline: dict[str, Any] | None = None) -> str:
    """The markdown report of an experiment from its runs ``{method: {"info": ..., "summary": ...}}``."""
    lines = [f"# Forecasting results: {experiment}", ""]
    columns: list[str] = []
    rows: list[tuple[str, dict[str, dict[str, float]]]] = []
    for method, run in sorted(runs.items()):
        per_row: dict[str, dict[str, dict[str, float]]] = {}
        for key, value in run["summary"].items():
            row, col = key.split("/", 1)
            per_row.setdefault(row, {})[col] = value
            if col not in columns:
                columns.append(col)
        # the method first, then the references it computed
        for row in sorted(per_row, key=lambda r: (r in ("last", "mean"), r)):
            label = row if row == method else f"{row} (reference, with {method})"
            rows.append((label, per_row[row]))
    columns.sort()
    lines.append("Mean ± std over test sequences. `last`: repeat the last inferred frame; `mean`: the mean training frame.")
    lines.append("")
    lines.append("| method | " + " | ".join(columns) + " |")
    lines.append("|---" * (len(columns) + 1) + "|")
    for label, values in rows:
        lines.append(f"| {label} | " + " | ".join(_cell(values.get(c)) for c in columns) + " |")
    lines.append("")
    key = paper_key(experiment)
    if key is not None:
        paper = PAPER[key]
        pcols = sorted({c for r in paper["rows"].values() for c in r})
        lines += [f"## The paper: {paper['table']}", ""]
        lines.append("| method | " + " | ".join(pcols) + " |")
        lines.append("|---" * (len(pcols) + 1) + "|")
        for name, values in paper["rows"].items():
            cells = ["not transcribed" if values.get(c) is None else f"{values[c]:.4g}" for c in pcols]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
        lines.append("")
    lines.append("## Runs")
    lines.append("")
    for method, run in sorted(runs.items()):
        info = run["info"]
        lines.append(f"- **{method}**: `{info.get('command', '')}`")
        for field in ("date", "machine", "ssm_checkpoint", "n_filter", "n_predict", "bce_reduction", "bce_clamp",
                      "original_units", "inference", "test_seconds"):
            if info.get(field) is not None:
                lines.append(f"  - {field}: {info[field]}")
    lines.append("")
    if pipeline:
        lines += ["## How this was produced", "", f"`{pipeline.get('command', '')}` on {pipeline.get('machine', '?')}, "
                  f"{pipeline.get('date', '?')}: {pipeline.get('total_seconds', '?')} s in all.", ""]
        lines += ["| stage | seconds |", "|---|---|"]
        lines += [f"| `{st['command']}` | {st['seconds']} |" for st in pipeline.get("stages", [])]
        lines.append("")
    return "\n".join(lines)


def _load(json_path: Path) -> dict[str, Any]:
    if json_path.exists():
        try:
            data = json.loads(json_path.read_text())
            if isinstance(data, dict):
                return data
        except json.JSONDecodeError:
            pass
    return {}


def _save(results_dir: Path, experiment: str, data: dict[str, Any]) -> Path:
    data["experiment"] = experiment
    (results_dir / f"{experiment}.json").write_text(json.dumps(data, indent=2, sort_keys=True))
    md_path = results_dir / f"{experiment}.md"
    md_path.write_text(render_markdown(experiment, data.get("runs", {}), data.get("pipeline")))
    return md_path


def write_results(results_dir: Path, info: dict[str, Any], summary: dict[str, dict[str, float]]) -> Path:
    """Merge one test run into ``<results_dir>/<experiment>.json`` and rewrite ``<experiment>.md``."""
    results_dir.mkdir(parents=True, exist_ok=True)
    experiment = info["experiment"]
    data = _load(results_dir / f"{experiment}.json")
    data.setdefault("runs", {})[info["method"]] = {"info": info, "summary": summary}
    return _save(results_dir, experiment, data)


def write_pipeline(results_dir: Path, experiment: str, pipeline: dict[str, Any]) -> Path:
    """Record how the whole experiment was produced (commands, durations, machine) and rewrite the table."""
    results_dir.mkdir(parents=True, exist_ok=True)
    data = _load(results_dir / f"{experiment}.json")
    data["pipeline"] = pipeline
    return _save(results_dir, experiment, data)
