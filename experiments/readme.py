"""The results tables of the README and of docs/results.md, generated from the results files (``results/*.json``):
one source for every score.

    python -m experiments.readme            # rewrite the tables between the documents' markers
    python -m experiments.readme --check    # exit status 1 (naming the tables) where a document is stale

Each table sits in one of :data:`DOCUMENTS` between ``<!-- results:begin NAME -->`` and ``<!-- results:end -->``
(NAME one of the registry's ``readme_tables``, configs/experiments.yaml, each in exactly one document); everything outside the markers is prose a person writes.
A table is built from the runs of the results files (``runs``: each method's scores and analysis) and the pipelines
that produced them (``pipelines``: the ``make reproduce`` command, each stage's command and seconds): ours ``mean ±
std`` over the test sequences, the paper's cell beside it (the registry's ``paper_tables``), the mean valid
prediction time, and the command that produced the row with each training stage's epoch budget (its
``--trainer.max_epochs``, where the pipeline set one) and duration. ``tests/test_readme_tables.py`` regenerates the
tables in memory and fails where a document differs: after a new result, run this command.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import shlex
import sys
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

from experiments.registry import paper_cell, paper_table, read_registry
from experiments.results import paper_row, score_cell, sig

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = (ROOT / "README.md", ROOT / "docs" / "results.md")  # the documents whose tables are generated
BEGIN = "<!-- results:begin {name} -->"
END = "<!-- results:end -->"
MARKER = re.compile(r"^<!-- results:begin (?P<name>[\w-]+) -->\n(?P<body>.*?)^<!-- results:end -->$", re.M | re.S)


# ------------------------------------------------------------------------------------------------- reading
class Results:
    """The results files of one directory, read once each."""

    def __init__(self, results_dir: Path):
        self.dir = Path(results_dir)
        self._files: dict[str, dict[str, Any]] = {}

    def file(self, experiment: str) -> dict[str, Any]:
        if experiment not in self._files:
            path = self.dir / f"{experiment}.json"
            if not path.is_file():
                raise FileNotFoundError(f"{path}: a README table reads it, and it is missing")
            self._files[experiment] = json.loads(path.read_text())
        return self._files[experiment]

    def run(self, experiment: str, method: str) -> dict[str, Any]:
        runs = self.file(experiment).get("runs", {})
        if method not in runs:
            raise KeyError(f"{self.dir / experiment}.json has no run {method!r} (it has {sorted(runs)})")
        return runs[method]

    def pipeline(self, experiment: str, method: str) -> dict[str, Any] | None:
        """The pipeline record that produced a run: the one with a test stage whose command is the run's (or a
        prefix of it: options a later re-test appended); of several, the one recorded closest to the run."""
        run = self.run(experiment, method)
        command = "python " + run["info"].get("command", "")
        found = [
            p
            for p in (self.file(experiment).get("pipelines") or {}).values()
            if any(command.startswith(s["command"]) for s in p.get("stages", []) if " test " in s["command"])
        ]
        if not found:
            return None
        when = _date(run["info"].get("date"))
        return min(found, key=lambda p: abs((_date(p.get("date")) - when).total_seconds()))


def _date(text: str | None) -> datetime:
    return datetime.fromisoformat(text) if text else datetime.fromisoformat("1970-01-01T00:00:00+00:00")


# ------------------------------------------------------------------------------------------------- formatting
def reference(entry: dict[str, Any] | None) -> str:
    """A reference's score (the mean training frame, the last estimate repeated): its mean."""
    return "—" if entry is None else sig(entry["mean"], 4)


def minutes(seconds: float) -> str:
    if seconds >= 120 * 60:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 60:.1f} min" if seconds < 10 * 60 else f"{seconds / 60:.0f} min"


def _option(command: str, name: str) -> str | None:
    words = shlex.split(command)
    return words[words.index(name) + 1] if name in words[:-1] else None


def stage_label(command: str) -> str:
    """What a fit stage trains, from its config's name: the SSM, its encoder, or a baseline."""
    stem = Path(_option(command, "--config") or "").stem
    if stem.endswith("_lstm"):
        return "LSTM"
    if stem.endswith("_rkn"):
        return "RKN"
    return "encoder" if stem.endswith("_encoder") else "SSM"


def training(pipeline: dict[str, Any]) -> str:
    """Its fit stages: what each trained, its epoch budget where the command set one, how long it took."""
    parts = []
    for stage in pipeline.get("stages", []):
        command = stage["command"]
        if not command.startswith("python cli.py fit "):
            continue
        epochs = _option(command, "--trainer.max_epochs")
        runs = stage.get("runs", 1)
        resumed = " resumed" if "--ckpt_path" in command.split() else ""
        parts.append(
            f"{stage_label(command)}{resumed}"
            + (f" {epochs} epochs" if epochs else "")
            + f" {minutes(stage['seconds'])}"
            + (f" in {runs} runs" if runs > 1 else "")
        )
    return ", ".join(parts)


def produced(pipeline: dict[str, Any] | None, run: dict[str, Any]) -> str:
    """The command that produced a row and its training; a run no pipeline recorded: its test command."""
    if pipeline is None:
        return f"`python {run['info'].get('command', '')}`"
    fits = training(pipeline)
    many = sum(s["command"].startswith("python cli.py fit ") for s in pipeline.get("stages", [])) > 1
    total = f" ({minutes(pipeline['total_seconds'])} in all)" if many and pipeline.get("total_seconds") else ""
    return f"`{pipeline['command']}`{total}" + (f": {fits}" if fits else "")


def valid(run: dict[str, Any]) -> str:
    vt = (run.get("analysis") or {}).get("valid_time")
    return sig(vt["mean_steps"], 3) if vt else "—"


def paper_cells(experiment: str, run: dict[str, Any], metrics: tuple[str, ...]) -> str:
    paper = paper_table(experiment)
    name = paper_row(paper, run["info"]) if paper else None
    if name is None:
        return "not in the paper"
    return " / ".join(paper_cell(paper["rows"][name].get(m)) for m in metrics)


# ------------------------------------------------------------------------------------------------- the tables
@dataclass(frozen=True)
class Group:
    """Rows of one experiment: ``(results file, method)`` per row, then its reference row."""

    title: str
    metrics: tuple[str, ...]  # "<target>/<metric>" as the protocol writes them
    rows: tuple[tuple[str, str], ...]
    reference: tuple[str, str, str, str]  # (label, results file, method, reference row: mean or last)


def method_table(results: Results, groups: list[Group], with_valid: bool) -> list[str]:
    """``experiment | method | ours | paper [| valid] | produced by``, one group after the other; a command that
    produced the row above is not repeated."""
    head = ["experiment", "method", "ours", "paper", *(["valid (frames)"] if with_valid else []), "produced by"]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for group in groups:
        previous = None
        for i, (experiment, method) in enumerate(group.rows):
            run = results.run(experiment, method)
            summary = run["summary"]
            pipeline = results.pipeline(experiment, method)
            same = pipeline is not None and pipeline is previous
            cells = [
                group.title if i == 0 else "",
                run["info"].get("label", method),
                " / ".join(score_cell(summary.get(f"{method}/{m}")) for m in group.metrics),
                paper_cells(experiment, run, group.metrics),
                *([valid(run)] if with_valid else []),
                "the same command" if same else produced(pipeline, run),
            ]
            lines.append("| " + " | ".join(cells) + " |")
            previous = pipeline
        label, experiment, method, row = group.reference
        summary = results.run(experiment, method)["summary"]
        cells = [
            "",
            f"*{label}*",
            " / ".join(reference(summary.get(f"{row}/{m}")) for m in group.metrics),
            "",
            *([""] if with_valid else []),
            "",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def methods(results: Results, spec: dict[str, Any]) -> list[str]:
    """A ``kind: methods`` table of the registry's ``readme_tables`` (Tables 1 and 2 at the paper's size and Table
    4's runs at its data size; the image experiments' CPU-sized twins): its groups of rows."""
    groups = [
        Group(
            group["title"],
            tuple(group["metrics"]),
            tuple((experiment, method) for experiment, method in group["rows"]),
            (
                group["reference"]["label"],
                group["reference"]["file"],
                group["reference"]["method"],
                group["reference"]["of"],
            ),
        )
        for group in spec["groups"]
    ]
    return method_table(results, groups, with_valid=bool(spec.get("valid")))


def _f_alone(run: dict[str, Any]) -> str:
    """What the SSM's f does alone: its largest Lyapunov exponent, how many free runs visit both wings."""
    dyn = (run.get("analysis") or {}).get("dynamics") or {}
    largest = (dyn.get("lyapunov") or {}).get("largest")
    free = dyn.get("free_run") or {}
    exponent = "diverges" if largest is None or not math.isfinite(largest) else sig(largest, 2)
    wings = free.get("both_wings_share")
    return exponent + (f"; {round(wings * free['runs'])} of {free['runs']}" if wings is not None else "")


def lorenz_sweep(results: Results, spec: dict[str, Any]) -> list[str]:
    """Table 4's sweep over the training piece length T at CPU size (a ``kind: sweep`` table of the registry's
    ``readme_tables``: its results file per T, its methods): ours / the paper's, then how each T ran."""
    files, metric, (ukf_m, enc_m, lstm_m, rkn_m) = spec["files"], spec["metric"], spec["methods"]
    columns, main = list(files), spec["main"]
    true = results.run(files[main], ukf_m).get("analysis", {}).get("true_system", {}).get("largest")
    head = ["method", *(f"T = {t:,}" for t in columns)]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]

    def row(label: str, cell: Callable[[int], str]) -> None:
        lines.append("| " + " | ".join([label, *(cell(t) for t in columns)]) + " |")

    def versus(method: str) -> Callable[[int], str]:
        def cell(t: int) -> str:
            run = results.run(files[t], method)
            return f"{score_cell(run['summary'].get(f'{method}/{metric}'))} / {paper_cells(files[t], run, (metric,))}"

        return cell

    for method in (ukf_m, enc_m):
        row(results.run(files[main], method)["info"]["label"], versus(method))
    row(
        f"*the learned f alone: largest Lyapunov exponent (true {sig(true, 2)}); free runs on both wings*",
        lambda t: _f_alone(results.run(files[t], ukf_m)),
    )
    for method in (lstm_m, rkn_m):
        row(results.run(files[main], method)["info"]["label"], versus(method))
    row(
        "*repeat the last estimate (reference, with the UKF)*",
        lambda t: reference(results.run(files[t], ukf_m)["summary"].get(f"last/{metric}")),
    )
    row(
        "*valid prediction time (steps): UKF / encoder / LSTM / RKN*",
        lambda t: " / ".join(valid(results.run(files[t], m)) for m in spec["methods"]),
    )
    noise_free, words = spec["noise_free"]["file"], spec["noise_free"]["paper"]
    ukf = results.run(noise_free, ukf_m)
    row(
        "SSM-LL + UKF, noise-free measurements",
        lambda t: (
            f"{score_cell(ukf['summary'].get(f'{ukf_m}/{metric}'))}, valid {valid(ukf)} steps / {words} "
            f"({produced(results.pipeline(noise_free, ukf_m), ukf)})"
            if t == main
            else "—"
        ),
    )

    def commands(t: int) -> str:
        pipelines: list[dict[str, Any]] = []
        for method in spec["methods"]:
            found = results.pipeline(files[t], method)
            if found is not None and all(found is not p for p in pipelines):
                pipelines.append(found)
        return "; ".join(produced(p, {}) for p in pipelines)

    row("*produced by*", commands)
    return lines


def benchmarks(results: Results, spec: dict[str, Any]) -> list[str]:
    """The identification benchmarks (``results/benchmarks/*.json``), one row per test recording: ssm-ms's method that
    validated best (the lowest mean validation RMSE over its seeds: the choice the test data do not make), deepSI's
    SUBNET (its model best on its own validation, and its last), the best published row; machine and date of the chosen
    method's last run, and SUBNET's where they differ (then the two columns are not one run's). Where every method
    was cross-validated (``--folds``), the choice uses those scores instead of the held-out end's."""
    from experiments.benchmark_results import (
        cross_validated_over_seeds,
        methods,
        over_seeds,
        published,
        summary_cell,
        validation_over_seeds,
    )

    folder = results.dir / "benchmarks"
    lines = [
        "| benchmark | test recording | ssm-ms, chosen on validation | deepSI SUBNET, best on its validation / last "
        "| best published | run on |",
        "|---|---|---|---|---|---|",
    ]
    for path in sorted(folder.glob("*.json")):
        if path.name.endswith(".published.json"):
            continue
        data = json.loads(path.read_text())
        pub = (published(folder, path.stem) or {}).get("rows", {})
        groups = methods(data)
        runs = data["runs"]
        unit = next((r["info"].get("unit") for r in runs.values() if r["info"].get("unit")), "")
        tests = list(dict.fromkeys(t for r in runs.values() for t in r["tests"]))
        ours_groups = {m: g for m, g in groups.items() if g[0]["info"].get("model") != "SUBNET"}
        folded = {m: cross_validated_over_seeds(g) for m, g in ours_groups.items()}
        if not folded or any(v is None for v in folded.values()):  # one judge for every method: the held-out end's
            folded = {m: validation_over_seeds(g) for m, g in ours_groups.items()}
        validated = {m: v for m, v in folded.items() if v is not None}
        chosen = min(validated, key=validated.get) if validated else None
        ours = [r for r in runs.values() if r["info"].get("model") != "SUBNET"]
        for i, test in enumerate(tests):
            if chosen is None:
                mine = "— (no run records its validation)"
            else:
                n = len(groups[chosen])
                mine = f"{summary_cell(over_seeds(groups[chosen], test), 3)} ({chosen}, {n} seed{'s' * (n > 1)})"
            peer = " / ".join(
                summary_cell(over_seeds(groups[m], test), 3) if m in groups else "—"
                for m in ("deepSI SUBNET, best on validation", "deepSI SUBNET, last model")
            )
            values = {name: v[test] for name, v in pub.items() if test in v}
            best = min(values, key=values.get) if values else None
            theirs = f"{sig(values[best], 3)} ({best})" if best else ""
            info = (groups[chosen] if chosen else ours or list(runs.values()))[-1]["info"]  # where the row shown ran
            when = f"{info.get('machine', '')}, {str(info.get('date', ''))[:10]}" if i == 0 else ""
            peers = [r["info"] for r in runs.values() if r["info"].get("model") == "SUBNET"]
            if i == 0 and peers and peers[-1].get("machine") != info.get("machine"):  # not one run's comparison
                when += f"; SUBNET: {peers[-1].get('machine', '')}, {str(peers[-1].get('date', ''))[:10]}"
            name = f"{data['experiment']} ({unit})" if i == 0 else ""
            lines.append(f"| {name} | {test} | {mine} | {peer} | {theirs} | {when} |")
    return lines


# the kinds of table of the registry's readme_tables (configs/experiments.yaml), each drawn from its entry there
KINDS: dict[str, Callable[[Results, dict[str, Any]], list[str]]] = {
    "methods": methods,
    "sweep": lorenz_sweep,
    "benchmarks": benchmarks,
}


def tables() -> dict[str, dict[str, Any]]:
    """The generated tables by name: the registry's ``readme_tables``."""
    return read_registry().get("readme_tables") or {}


# ------------------------------------------------------------------------------------------------- the documents
def render(text: str, results_dir: Path = ROOT / "results") -> str:
    """``text`` (one of :data:`DOCUMENTS`) with every marked table generated anew from the results files."""
    results = Results(results_dir)
    specs = tables()
    seen = []

    def fill(match: re.Match) -> str:
        name = match.group("name")
        if name not in specs:
            raise KeyError(
                f"marker {BEGIN.format(name=name)}: no such table in the registry's readme_tables (known: {sorted(specs)})"
            )
        seen.append(name)
        spec = specs[name]
        return "\n".join([BEGIN.format(name=name), *KINDS[spec["kind"]](results, spec), END])

    out = MARKER.sub(fill, text)
    if len(re.findall(r"^<!-- results:begin", text, re.M)) != len(seen):  # markers open a line; prose may quote one
        raise ValueError("a marker <!-- results:begin NAME --> without its <!-- results:end -->")
    return out


def stale(text: str, results_dir: Path = ROOT / "results") -> list[str]:
    """The names of the tables of ``text`` that differ from what the results files give."""
    new = {m.group("name"): m.group("body") for m in MARKER.finditer(render(text, results_dir))}
    return [m.group("name") for m in MARKER.finditer(text) if m.group("body") != new[m.group("name")]]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("documents", nargs="*", type=Path, default=list(DOCUMENTS), help="default: DOCUMENTS")
    parser.add_argument("--results-dir", type=Path, default=ROOT / "results")
    parser.add_argument("--check", action="store_true", help="change nothing; exit status 1 where a table is stale")
    opts = parser.parse_args(argv)
    status = 0
    for document in opts.documents:
        text = document.read_text(encoding="utf-8")
        if opts.check:
            names = stale(text, opts.results_dir)
            if names:
                print(
                    f"{document}: tables differ from {opts.results_dir}/*.json: {', '.join(names)} "
                    "(python -m experiments.readme rewrites them)",
                    file=sys.stderr,
                )
                status = 1
            continue
        new = render(text, opts.results_dir)
        if new != text:
            document.write_text(new, encoding="utf-8")
        print(
            f"{document}: {len(MARKER.findall(new))} tables from {opts.results_dir}/*.json"
            + ("" if new != text else " (unchanged)")
        )
    return status


if __name__ == "__main__":
    sys.exit(main())
