"""The markdown report of an identification benchmark's results file: ``results/benchmarks/<experiment>.md``,
rendered from ``<experiment>.json`` (every run; the library's test runs and ``benchmarks/bench_deepsi.py`` write it:
:mod:`ssm_ms.forecasting.benchmark_results`), the published baselines and the hand-written notes beside it.

The table has one row per method, its score over the seeds run as mean ± sample standard deviation, beside the
validation score that kept each run's epoch (the held-out end of the training recording: what a choice between
methods may use). Published rows come from ``<experiment>.published.json`` beside it when that file exists
(``{"source": ..., "rows": {name: {test: rmse}}}``), and a hand-written ``<experiment>.notes.md`` is appended as the
Notes. ``python cli.py test`` renders the ``.md`` of each results file it wrote (:mod:`experiments.cli`); after
editing the notes:

    python -m experiments.benchmark_results   # re-render every results/benchmarks/<experiment>.md
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from experiments.registry import ROOT
from ssm_ms.forecasting.results import load, replace_text
from ssm_ms.runtime.machine import SHARED_CORES

RESULTS_DIR = ROOT / "results" / "benchmarks"  # the benchmarks' test configs' results_dir


def is_benchmark_results(data: dict[str, Any]) -> bool:
    """Whether a results file's content is a benchmark's: runs scored per test recording (``tests``), where the
    forecasting protocol's hold a ``summary`` (:mod:`experiments.results`)."""
    runs = data.get("runs")
    return isinstance(runs, dict) and bool(runs) and all("tests" in run for run in runs.values())


def published(results_dir: Path, experiment: str) -> dict[str, Any] | None:
    """The published baselines beside a results file (``<experiment>.published.json``: ``{"source", "rows"}``), or
    None."""
    path = Path(results_dir) / f"{experiment}.published.json"
    return json.loads(path.read_text()) if path.is_file() else None


def methods(data: dict[str, Any]) -> dict[str, list[dict[str, Any]]]:
    """The runs of a results file by method (their seeds), in the order the methods first appear."""
    out: dict[str, list[dict[str, Any]]] = {}
    for run in data["runs"].values():
        out.setdefault(run["info"]["method"], []).append(run)
    return out


def over_seeds(runs: list[dict[str, Any]], test: str) -> dict[str, Any] | None:
    """One method's score on one test recording over its runs: ``{"n", "diverged", "mean", "std", "values"}``
    (``std`` the sample standard deviation, ``None`` for one run; ``mean`` ``None`` where every run diverged), or
    ``None`` where no run has that recording."""
    rows = [run["tests"][test] for run in runs if test in run["tests"]]
    if not rows:
        return None
    values = [row["rmse"] for row in rows if row.get("diverged_at") is None and row.get("rmse") is not None]
    return {
        "n": len(rows),
        "diverged": len(rows) - len(values),
        "mean": float(np.mean(values)) if values else None,
        "std": float(np.std(values, ddof=1)) if len(values) > 1 else None,
        "values": values,
        "diverged_at": [row["diverged_at"] for row in rows if row.get("diverged_at") is not None],
    }


def validation_over_seeds(runs: list[dict[str, Any]]) -> float | None:
    """The mean over a method's runs of the validation score that kept each run's epoch (``None``: not recorded)."""
    return _mean_of_validation(runs, "val_sim_rmse")


CROSS_VALIDATED = "cross-validated (mean over the folds)"  # the key experiments.reproduce's --folds records


def cross_validated(run: dict[str, Any]) -> float | None:
    """A run's cross-validated score (``make reproduce ... --folds K``: the mean validation score of its K fits, of the
    order it tested), ``None`` where it was not cross-validated."""
    selection = run["info"].get("selection") or {}
    means = selection.get(CROSS_VALIDATED)
    if not means:
        return None
    chosen = selection.get("chosen")
    return means.get("" if chosen is None else str(chosen))


def cross_validated_over_seeds(runs: list[dict[str, Any]]) -> float | None:
    """The mean of a method's cross-validated scores over its runs that have one (``None``: none has): K fits per
    seed make one cross-validated seed a judge worth its cost."""
    values = [v for v in (cross_validated(run) for run in runs) if v is not None]
    return float(np.mean(values)) if values else None


def seconds_to_kept(runs: list[dict[str, Any]]) -> float | None:
    """The mean over a method's runs of the training seconds until the model it kept (``None``: not recorded)."""
    return _mean_of_validation(runs, "seconds")


def _mean_of_validation(runs: list[dict[str, Any]], key: str) -> float | None:
    values = [(run["info"].get("validation") or {}).get(key) for run in runs]
    return float(np.mean(values)) if values and all(v is not None for v in values) else None


def summary_cell(summary: dict[str, Any] | None, digits: int = 4) -> str:
    """``0.98``, ``0.98 ± 0.02`` over seeds, ``diverged at sample N``, ``... (1 of 3 diverged)``."""
    if summary is None:
        return ""
    if summary["mean"] is None:
        where = summary["diverged_at"]
        return f"diverged at sample {where[0]}" if len(where) == 1 else f"all {summary['n']} diverged"
    cell = f"{summary['mean']:.{digits}g}"
    if summary["std"] is not None:
        cell += f" ± {summary['std']:.2g}"
    if summary["diverged"]:
        cell += f" ({summary['diverged']} of {summary['n']} diverged)"
    return cell


def _cell(value: Any) -> str:
    return "—" if value is None else f"{value:.4g}" if isinstance(value, float) else str(value)


def render(data: dict[str, Any], results_dir: Path) -> str:
    """The experiment's markdown: the RMSE of each run on each test recording (diverged runs say where), then the
    published rows, then each run's details and the notes."""
    runs = data["runs"]
    tests = list(dict.fromkeys(t for run in runs.values() for t in run["tests"]))
    unit = next((run["info"].get("unit") for run in runs.values() if run["info"].get("unit")), "")
    lines = [f"# {data['experiment']}: free-run simulation RMSE ({unit or 'data units'})", ""]
    folded = any(cross_validated(run) is not None for run in runs.values())  # a column only where a run has it
    lines += [
        "| method | seeds | validation | "
        + "cross-validated | " * folded
        + "kept after (s) | "
        + " | ".join(tests)
        + " |",
        "|---|---|---|" + "---|" * folded + "---|" + "---|" * len(tests),
    ]
    for method, group in methods(data).items():
        seeds = ", ".join(str(run["info"].get("seed", "—")) for run in group)
        cells = [summary_cell(over_seeds(group, t)) for t in tests]
        seconds = seconds_to_kept(group)
        cv = f"{_cell(cross_validated_over_seeds(group))} | " if folded else ""
        lines.append(
            f"| {method} | {seeds} | {_cell(validation_over_seeds(group))} | {cv}"
            f"{'—' if seconds is None else f'{seconds:.0f}'} | " + " | ".join(cells) + " |"
        )
    pub = published(results_dir, data["experiment"])
    if pub is not None:
        for method, values in pub["rows"].items():
            empty = "| | | | " + "| " * folded
            lines.append(f"| {method} (published) {empty}" + " | ".join(_cell(values.get(t)) for t in tests) + " |")
        lines += ["", f"Published rows: {pub['source']}."]
    lines += [
        "",
        "Over several seeds: mean ± sample standard deviation. Validation: the free-run RMSE of the held-out end of the "
        "training recording at the epoch it kept (mean over the seeds; what a choice between methods may use); kept "
        "after: the training seconds until that model (mean over the seeds)."
        + (
            " Cross-validated: the mean validation score of fits that each held out another part of the training "
            "recording (`make reproduce ... --folds K`; the end's fit is the one tested), mean over the seeds that "
            "have one; where every method has one, the choice between methods uses it."
            if folded
            else ""
        ),
    ]
    lines += ["", "## Runs", ""]
    for method, run in runs.items():
        info = run["info"]
        stability = info.get("stability") or {}
        kept = info.get("validation") or {}
        lines += [
            f"### {method}",
            "",
            f"- model: {info.get('model')}, state_dim {info.get('state_dim')}, from `{info.get('ssm_checkpoint')}`",
            f"- state estimate: {info.get('inference')}",
            f"- machine: {info.get('machine')}; date {info.get('date')}; test {info.get('test_seconds')} s",
            f"- command: `{info.get('command')}`",
        ]
        if kept.get("val_sim_rmse") is not None:
            when = f" after {kept['seconds']:.0f} s of its fit" if kept.get("seconds") is not None else ""
            at = f" at epoch {kept['epoch']}" if kept.get("epoch") is not None else ""
            lines.append(f"- validation: {_cell(kept['val_sim_rmse'])} {unit}{at}{when}, the epoch kept")
        if (kept.get("cpu_others") or 0.0) > SHARED_CORES:
            lines.append(
                f"- **a shared CPU**: other processes kept {kept['cpu_others']:.2f} cores busy on average during its "
                "fit, which trained fewer epochs in its time budget than it would alone"
            )
        if info.get("selection"):
            held = "the held-out end of the training recording"
            held = "each held-out part of the training recording in turn" if "folds" in info["selection"] else held
            lines.append(f"- chosen on validation ({held}): {info['selection']}")
        if stability:
            lines.append(
                f"- f's local stability (spectral radius of df/dx at {stability['states']} training states): median "
                f"{stability['median']:.4g}, 90th percentile {stability['p90']:.4g}, max {stability['max']:.4g}, "
                f"above 1 at {100 * stability['share_above_1']:.0f}%"
            )
        for t, row in run["tests"].items():
            lines.append(
                f"- {t}: {row['samples']} samples (state from the first {row['n_init']}); RMSE {_cell(row['rmse'])}, "
                f"NRMSE {_cell(row['nrmse'])}, fit index {_cell(row['fit_index'])}"
                + (f"; diverged at sample {row['diverged_at']}" if row.get("diverged_at") is not None else "")
                + f"; {row['seconds']} s"
            )
        lines.append("")
    notes = results_dir / f"{data['experiment']}.notes.md"
    if notes.exists():
        lines += ["## Notes", "", notes.read_text().strip(), ""]
    return "\n".join(lines)


def render_file(json_path: Path) -> Path:
    """Render ``<experiment>.md`` beside the benchmark's results file ``json_path`` (its runs, the published rows and
    notes beside it), whole or not at all; return the ``.md``'s path."""
    json_path = Path(json_path)
    md_path = json_path.with_suffix(".md")
    replace_text(md_path, render(load(json_path), json_path.parent))
    return md_path


def main(argv: list[str] | None = None) -> int:
    """``python -m experiments.benchmark_results [--results-dir DIR]``: render every results file's markdown anew
    from its JSON, published rows and notes (after editing the notes)."""
    import argparse

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("--results-dir", type=Path, default=RESULTS_DIR)
    opts = parser.parse_args(argv)
    for path in sorted(opts.results_dir.glob("*.json")):
        if not path.name.endswith(".published.json"):
            print(f"rendered {render_file(path)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
