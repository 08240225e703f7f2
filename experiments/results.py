"""The markdown report of a results file: ``results/<experiment>.md``, rendered from ``<experiment>.json`` (which the
library's test runs write: :mod:`ssm_ms.forecasting.results`) and the hand-written ``<experiment>.notes.md``.

Every forecaster of one experiment (SSM + encoder, SSM + UKF, the LSTM and RKN baselines) lands in
the same files: each test run replaces its own method's entry and the table is rebuilt from all
(``python cli.py test`` renders the ``.md`` of each results file it wrote: :mod:`experiments.cli`).

The paper's tables (Jordana et al. 2021, Tables 1-4) are in the experiment registry, ``configs/experiments.yaml``
(``paper_tables``), each naming the experiments scored against it: rows of ``{column: value}`` where a value is
``(mean, std)`` (``std`` ``None`` where the paper gives none) or a string ("did not converge"). Columns are
``"<target>/<metric>"`` as the protocol produces them, so each of our rows shows the paper's row of the same method
beside it (:func:`paper_row`); a results file of an experiment no table names has no paper rows.

The ``.md`` is rendered from the ``.json`` and the hand-written ``<experiment>.notes.md``; after editing notes:

    python -m experiments.results pendulum quad   # re-render those experiments' .md (none named: all)
    python -m experiments.results --check         # exit status 1 (naming them) where an .md is stale
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from experiments.registry import paper_cell, paper_table
from ssm_ms.forecasting.results import load, replace_text, update_results


def paper_row(paper: dict[str, Any], info: dict[str, Any]) -> str | None:
    """The paper's row for one of our runs (``paper``: its table, :func:`experiments.registry.paper_table`): the same
    model with the same kind of inference.

    Image tables name the SSM by its transition (``SSM-LL``, ``SSM-FC``, state inferred by the CNN-LSTM); a table
    with ``inference_rows`` (Table 4) names it by its inference (``SSM-RNN``: the encoder, ``SSM-UKF``); baselines by
    their name.
    """
    rows = paper["rows"]
    model, inference = info.get("model"), info.get("inference")
    if model in ("LSTM", "RKN"):
        name = model
    elif paper["inference_rows"]:
        name = paper["inference_rows"].get(inference)
    else:
        name = model if inference == "encoder" else None
    return name if name in rows else None


def sig(value: float, digits: int) -> str:
    """``digits`` significant figures; plain digits up to 10,000 (``190``, not ``1.9e+02``)."""
    text = f"{value:.{digits}g}"
    if "e+" in text and abs(value) < 1e4:
        text = f"{float(text):.0f}"
    return text


def score_cell(entry: dict[str, float] | None) -> str:
    """A score over the test sequences, as results files and the README print it: ``mean ± std``, saying how many
    diverged (a NaN or inf score) and were left out; a rate with its confidence interval (``ci95``: a share of
    successes) as ``k/n = rate (95% CI lo-hi)``."""
    if entry is None:
        return "—"
    if "ci95" in entry:
        n, (lo, hi) = entry["n"], entry["ci95"]
        return f"{round(entry['mean'] * n)}/{n} = {entry['mean']:.2f} (95% CI {lo:.2f}-{hi:.2f})"
    bad, n = entry.get("non_finite", 0), entry.get("n")
    if bad and bad == n:
        return f"non-finite on all {n}"
    cell = f"{sig(entry['mean'], 4)} ± {sig(entry['std'], 2)}"
    return f"{cell} ({bad} of {n} non-finite, left out)" if bad else cell


def render_markdown(
    experiment: str,
    runs: dict[str, dict[str, Any]],
    pipelines: dict[str, dict[str, Any]] | None = None,
    heading: dict[str, str] | None = None,
) -> str:
    """The markdown report of an experiment from its runs ``{method: {"info": ..., "summary": ...}}`` (``heading``:
    ``{"title", "intro"}`` of a results file that is not the forecasting protocol's, e.g. closed-loop control)."""
    heading = heading or {
        "title": "Forecasting results",
        "intro": "Mean ± std over test sequences. `last`: repeat the method's estimate of the last given frame; "
        "`mean`: the mean training frame (references, computed by the same code).",
    }
    lines = [f"# {heading['title']}: {experiment}", ""]
    paper = paper_table(experiment)
    columns = sorted({k.split("/", 1)[1] for run in runs.values() for k in run["summary"]})
    pcols = sorted({c for r in paper["rows"].values() for c in r}) if paper else []
    lines.append(heading["intro"])
    if paper:
        lines.append(
            f"Beside each method, the paper's row for the same method ({paper['table'].split(' (')[0]}, below)."
        )
    if experiment.endswith("_cpu") or "_cpu_" in experiment:
        lines.append(
            "This is a CPU-sized twin (`configs/cpu/`: less data, smaller networks, fewer epochs than the "
            "paper); the paper's figures are for its full-size setting."
        )
    lines.append("")
    head = ["method", *columns] + (["paper row", *(f"paper {c}" for c in pcols)] if paper else [])
    lines.append("| " + " | ".join(head) + " |")
    lines.append("|---" * len(head) + "|")
    # the SSMs first, then the baselines (the paper's order), each group by label
    ordered = sorted(
        runs.items(),
        key=lambda item: (item[1]["info"].get("model") in ("LSTM", "RKN"), item[1]["info"].get("label", item[0])),
    )
    for method, run in ordered:
        info = run["info"]
        per_row: dict[str, dict[str, dict[str, float]]] = {}
        for k, value in run["summary"].items():
            row, col = k.split("/", 1)
            per_row.setdefault(row, {})[col] = value
        label = info.get("label", method)
        for row in sorted(per_row, key=lambda r: (r in ("last", "mean"), r)):  # the method, then its references
            own = row == method
            cells = [label if own else f"{row} (reference, with {label})"]
            cells += [score_cell(per_row[row].get(c)) for c in columns]
            if paper:
                name = paper_row(paper, info) if own else None
                cells.append(name or "")
                cells += [paper_cell(paper["rows"][name].get(c)) if name else "" for c in pcols]
            lines.append("| " + " | ".join(cells) + " |")
    lines.append("")
    if paper:
        lines += [f"## The paper: {paper['table']}", ""]
        lines.append("| method | " + " | ".join(pcols) + " |")
        lines.append("|---" * (len(pcols) + 1) + "|")
        for name, values in paper["rows"].items():
            lines.append(f"| {name} | " + " | ".join(paper_cell(values.get(c)) for c in pcols) + " |")
        lines.append("")
        if paper.get("notes"):
            lines += [*paper["notes"], ""]
    lines += render_analysis(ordered)
    lines += ["## Runs", ""]
    for method, run in ordered:
        info = run["info"]
        lines.append(f"- **{info.get('label', method)}** (`{method}`): `{info.get('command', '')}`")
        for field in (
            "date",
            "machine",
            "ssm_checkpoint",
            "checkpoint",
            "test_sequences",
            "data",
            "n_filter",
            "n_predict",
            "bce_reduction",
            "bce_clamp",
            "original_units",
            "inference_settings",
            "test_seconds",
        ):
            if info.get(field) is not None:
                lines.append(f"  - {field}: {info[field]}")
    lines.append("")
    if pipelines:
        lines += ["## How this was produced", ""]
        for pipeline in sorted(pipelines.values(), key=lambda p: p.get("date", "")):
            lines += [
                f"`{pipeline.get('command', '')}` on {pipeline.get('machine', '?')}, "
                f"{pipeline.get('date', '?')}: {pipeline.get('total_seconds', '?')} s in all.",
                "",
            ]
            lines += ["| stage | seconds |", "|---|---|"]
            lines += [
                f"| `{st['command']}` | {st['seconds']}"
                + (f" (in {st['runs']} runs: resumed from its last completed epoch)" if st.get("runs", 1) > 1 else "")
                + " |"
                for st in pipeline.get("stages", [])
            ]
            lines.append("")
    return "\n".join(lines)


def _num(value: Any, digits: int = 3) -> str:
    if value is None:
        return "—"
    if isinstance(value, float) and value == float("inf"):
        return "inf"
    if isinstance(value, (int, float)) and 10**digits <= abs(value) < 1e9:
        return f"{value:.0f}"  # whole steps read better than 1e+03
    return f"{value:.{digits}g}" if isinstance(value, (int, float)) else str(value)


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    """A markdown table less the columns after the first that read "—" on every row (a Lorenz-only statistic in an
    image experiment's file, say)."""
    keep = [0] + [j for j in range(1, len(header)) if any(row[j] != "—" for row in rows)]
    return [
        "| " + " | ".join(header[j] for j in keep) + " |",
        "|" + "---|" * len(keep),
        *("| " + " | ".join(row[j] for j in keep) + " |" for row in rows),
    ]


def render_analysis(ordered: list[tuple[str, dict[str, Any]]]) -> list[str]:
    """The ``## Analysis`` section: valid prediction times of every method, then what each SSM's ``f`` does alone."""
    runs = [(run["info"].get("label", method), run["analysis"]) for method, run in ordered if run.get("analysis")]
    if not runs:
        return []
    lines = ["## Analysis", ""]
    true = next((a["true_system"] for _, a in runs if a.get("true_system")), None)
    timed = [(label, a["valid_time"]) for label, a in runs if a.get("valid_time")]
    if timed:
        vt0 = timed[0][1]
        lines.append(
            f"**Valid prediction time**: steps until the forecast's normalised error "
            f"`sqrt(mean((pred - truth)^2 / std^2))` exceeds {vt0['threshold']} (the reservoir-computing convention), "
            f"against the {vt0['truth']} measurements, after {vt0['n_filter']} given steps, over a horizon of "
            f"{vt0['horizon']} steps; `censored`: share of sequences still valid at the horizon (their time is "
            f"counted as the horizon: a lower bound). Lyapunov times use the true system's largest exponent"
            + (f" ({true['largest']:.3g} per time unit, {true['source']})." if true else " (not known here).")
        )
        lines.append(
            " `error at step`: the normalised error averaged over sequences at those forecast steps (how it grows)."
        )
        if any(vt.get("given_error") is not None for _, vt in timed):
            lines.append(
                " Images: the error counted is the part above the sequence's own reconstruction error on its last "
                "10 given frames (`given`: that floor, normalised the same way), since a decoder's blur alone "
                "would read as invalid from the first frame."
            )
        rows = []
        for label, vt in timed:
            steps = sorted((vt.get("error_at_step") or {}).items(), key=lambda kv: int(kv[0]))  # JSON keys are strings
            growth = ", ".join(f"{k}: {_num(v, 2)}" for k, v in steps)
            rows.append(
                [
                    label,
                    f"{_num(vt['mean_steps'])} ± {_num(vt['std_steps'], 2)}",
                    _num(vt["median_steps"]),
                    _num(vt.get("mean_seconds")),
                    _num(vt.get("mean_lyapunov_times")),
                    _num(vt["censored_share"], 2),
                    (growth or "—")
                    + (f"; given: {_num(vt['given_error'], 2)}" if vt.get("given_error") is not None else ""),
                ]
            )
        lines += [
            "",
            *_table(
                [
                    "method",
                    "mean ± std (steps)",
                    "median (steps)",
                    "mean (s)",
                    "mean (Lyapunov times)",
                    "censored",
                    "error at step",
                ],
                rows,
            ),
            "",
        ]
    dyn = [(label, a["dynamics"]) for label, a in runs if a.get("dynamics")]
    if dyn:
        lines.append(
            "**The learned f on its own**, iterated from shooting nodes (the same for every inference method "
            "of one SSM): Lyapunov exponents per time unit (Benettin QR on the Jacobians of f), and long free "
            "runs decoded by g against the data's noiseless training measurements."
        )
        rows = []
        for label, d in dyn:
            ly, fr = d["lyapunov"], d.get("free_run", {})
            truth = d.get("lyapunov_true", true) or {}
            rows.append(
                [
                    label,
                    ", ".join(_num(e) for e in ly["exponents"]),
                    f"{_num(ly['largest'])} ({_num(truth.get('largest'))})",
                    f"{fr.get('runs', '—')} x {fr.get('steps', '—')}",
                    _num(fr["model_mean"][0]) + " ± " + _num(fr["model_std"][0]) if "model_mean" in fr else "—",
                    _num(fr["reference_mean"][0]) + " ± " + _num(fr["reference_std"][0])
                    if "reference_mean" in fr
                    else "—",
                    _num(fr["wasserstein"][0]) if "wasserstein" in fr else "—",
                    _num(fr.get("both_wings_share"), 2),
                ]
            )
        lines += [
            "",
            *_table(
                [
                    "SSM (via)",
                    "Lyapunov exponents",
                    "largest (true)",
                    "free runs",
                    "x: model mean ± std",
                    "x: data mean ± std",
                    "W1 (x)",
                    "both wings",
                ],
                rows,
            ),
            "",
        ]
        periodic = [(label, d["oscillation"]) for label, d in dyn if d.get("oscillation")]
        if periodic:
            lines += [
                "**Period and amplitude** of the free runs of f from the nodes of training trajectories, decoded, "
                "against the data generator simulated from the same initial states over the same horizon "
                "(amplitude ratio: std of the last window over the first; 1 = energy kept).",
                "",
                "| SSM (via) | runs | horizon (steps) | period error, median | within 5% | amplitude ratio, model "
                "(median) | amplitude ratio, truth (median) | valid steps from the node (median) |",
                "|---|---|---|---|---|---|---|---|",
            ]
            for label, o in periodic:
                lines.append(
                    f"| {label} | {o['runs']} | {o['horizon']} | {_num(o['median_period_error'])} | "
                    f"{_num(o['share_within_5_percent'], 2)} | {_num(o['median_amplitude_ratio_model'])} | "
                    f"{_num(o['median_amplitude_ratio_truth'])} | {_num(o['median_valid_steps'])} |"
                )
            lines.append("")
    return lines


NOTES_SUFFIX = ".notes.md"  # results/<experiment>.notes.md: hand-written notes appended to <experiment>.md


def _rendered(results_dir: Path, experiment: str, data: dict[str, Any]) -> str:
    """The ``.md`` text of ``data`` with the experiment's notes appended."""
    text = render_markdown(experiment, data.get("runs", {}), data.get("pipelines"), data.get("heading"))
    notes = results_dir / f"{experiment}{NOTES_SUFFIX}"
    if notes.is_file():  # what a person wrote about the runs (pauses, measurements beside them): kept on every rewrite
        text += f"\n## Notes\n\n(from `{notes.name}`, written by hand)\n\n{notes.read_text().strip()}\n"
    return text


def render_file(json_path: Path) -> Path:
    """Render ``<experiment>.md`` beside the results file ``json_path`` (its runs, pipelines and notes); return the
    ``.md``'s path."""
    json_path = Path(json_path)
    md_path = json_path.with_suffix(".md")
    replace_text(md_path, _rendered(json_path.parent, json_path.stem, load(json_path)))
    return md_path


def experiments(results_dir: Path) -> list[str]:
    """The experiments with a results file in ``results_dir`` (``<name>.json`` holding ``runs``; not the seed
    summaries of :mod:`experiments.seeds`)."""
    names = []
    for path in sorted(results_dir.glob("*.json")):
        try:
            data = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError):
            continue
        if isinstance(data, dict) and "runs" in data:
            names.append(path.stem)
    return names


def _stale_renders(results_dir: Path, names: list[str] | None = None) -> dict[str, str]:
    """``{name: text}`` for those of ``names`` (all :func:`experiments`) whose ``.md`` differs from ``text``, what
    their ``.json`` and notes render."""
    out = {}
    for name in experiments(results_dir) if names is None else names:
        md = results_dir / f"{name}.md"
        text = _rendered(results_dir, name, load(results_dir / f"{name}.json"))
        if not md.is_file() or md.read_text() != text:
            out[name] = text
    return out


def stale(results_dir: Path, names: list[str] | None = None) -> list[str]:
    """Those of ``names`` (all :func:`experiments`) whose ``.md`` differs from what their ``.json`` and notes render."""
    return list(_stale_renders(results_dir, names))


def write_pipeline(
    results_dir: Path, experiment: str, command: str, pipeline: dict[str, Any], replaces: str | None = None
) -> Path:
    """Record how (part of) the experiment was produced -- the stages of one ``make reproduce`` command, their
    durations, the machine -- and rewrite the table. Each command keeps its own record; ``replaces`` names the
    command of a record this one supersedes (the same run, resumed with a larger epoch budget)."""

    def merge(data: dict[str, Any]) -> None:
        data.pop("pipeline", None)  # the single record of earlier versions
        if replaces is not None:
            data.get("pipelines", {}).pop(replaces, None)
        data.setdefault("pipelines", {})[command] = pipeline

    return render_file(update_results(results_dir, experiment, merge))


def main(argv: list[str] | None = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("experiments", nargs="*", help="names of results/<name>.json (default: every one)")
    parser.add_argument("--results-dir", type=Path, default=Path(__file__).resolve().parents[1] / "results")
    parser.add_argument("--check", action="store_true", help="change nothing; exit status 1 where an .md is stale")
    opts = parser.parse_args(argv)
    if not opts.results_dir.is_dir():
        parser.error(f"no folder {opts.results_dir}: give the results folder with --results-dir")
    known = experiments(opts.results_dir)
    unknown = [name for name in opts.experiments if name not in known]
    if unknown:
        parser.error(f"no results file {', '.join(unknown)} in {opts.results_dir} (there: {', '.join(known)})")
    renders = _stale_renders(opts.results_dir, opts.experiments or None)
    names = list(renders)
    if opts.check:
        if names:
            print(
                f"{opts.results_dir}: stale .md beside its .json and notes: {', '.join(names)} "
                "(python -m experiments.results re-renders them)",
                file=sys.stderr,
            )
        return 1 if names else 0
    for name, text in renders.items():
        md = opts.results_dir / f"{name}.md"
        replace_text(md, text)
        print(f"re-rendered {md}")
    print(f"{len(names)} of {len(opts.experiments or known)} .md files re-rendered")
    return 0


if __name__ == "__main__":
    sys.exit(main())
