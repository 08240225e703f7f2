"""One experiment over several seeds: ``results/<experiment>.json`` (the configs' own seed) and every
``results/<experiment>_seed<N>.json`` (``make reproduce EXP=... SEED=N``), gathered as mean ± std over seeds.

    python -m experiments.seeds lorenz_T1000_cpu            # -> results/lorenz_T1000_cpu_seeds.md / .json
    python -m experiments.seeds lorenz_T1000_cpu --results-dir results

Per seed and method it reads the method's own scores (``<method>/<target>/<metric>``, the mean over the test
sequences) and its valid prediction time; and, once per seed, what the SSM's ``f`` does alone (W1 of x over the
free runs, largest Lyapunov exponent, share of free runs that visit both wings) with the true system's exponent.
The std over seeds is the sample standard deviation (``n - 1``); a quantity a seed lacks is left out of its mean.
"""

from __future__ import annotations

import argparse
import json
import math
import re
from pathlib import Path
from typing import Any

from ssm_ms.forecasting.metrics import flat_scalars

# (row label, key in the flattened analysis): once per method / once per seed (the SSM's f is one per seed)
PER_METHOD = [("valid time (steps)", "valid_time/mean_steps")]
PER_SEED = [
    ("f: W1 of x over the free runs", "dynamics/free_run/wasserstein/0"),
    ("f: largest Lyapunov exponent", "dynamics/lyapunov/largest"),
    ("f: free runs visiting both wings", "dynamics/free_run/both_wings_share"),
    ("true system: largest Lyapunov exponent", "true_system/largest"),
]
NON_FINITE = ", non-finite sequences"  # suffix of the row that counts a score's diverged forecasts


def seed_files(results_dir: Path, experiment: str) -> dict[str, Path]:
    """``{column label: results json}``: the experiment's own file (``"config seed"``), then ``seed<N>`` by N."""
    files = {}
    base = results_dir / f"{experiment}.json"
    if base.is_file():
        files["config seed"] = base
    pattern = re.compile(re.escape(experiment) + r"_seed(\d+)")
    seeded = [
        (int(m.group(1)), p) for p in results_dir.glob(f"{experiment}_seed*.json") if (m := pattern.fullmatch(p.stem))
    ]
    files.update({f"seed{n}": p for n, p in sorted(seeded)})
    return files


def read_quantities(data: dict[str, Any]) -> dict[str, float]:
    """``{row label: value}`` of one seed's results (the json of :mod:`ssm_ms.forecasting.results`)."""
    out: dict[str, float] = {}
    per_seed: dict[str, float] = {}
    for method, run in sorted(data.get("runs", {}).items()):
        for key, entry in sorted(run.get("summary", {}).items()):
            row, rest = key.split("/", 1)
            if row == method and isinstance(entry, dict) and isinstance(entry.get("mean"), (int, float)):
                out[f"{method}: {rest}"] = float(entry["mean"])  # over the finite sequences
                if entry.get("non_finite"):  # diverged forecasts, left out of that mean: say how many, per seed
                    out[f"{method}: {rest}{NON_FINITE}"] = float(entry["non_finite"])
        flat = flat_scalars(run.get("analysis") or {})
        for label, key in PER_METHOD:
            if key in flat:
                out[f"{method}: {label}"] = flat[key]
        for label, key in PER_SEED:
            if key in flat:
                per_seed.setdefault(label, flat[key])
    out.update({label: per_seed[label] for label, _ in PER_SEED if label in per_seed})
    return out


def mean_std(values: list[float]) -> tuple[float, float | None]:
    """Mean and sample standard deviation (``None`` for a single value)."""
    mean = sum(values) / len(values)
    if len(values) < 2:
        return mean, None
    return mean, math.sqrt(sum((v - mean) ** 2 for v in values) / (len(values) - 1))


def gather(results_dir: Path, experiment: str) -> dict[str, Any]:
    """The table: ``{"seeds": [labels], "rows": {label: {seed: value}}, "summary": {label: {mean, std, n}}}``."""
    files = seed_files(results_dir, experiment)
    if not files:
        raise SystemExit(
            f"no results for {experiment!r} in {results_dir}: expected {experiment}.json or "
            f"{experiment}_seed<N>.json (make reproduce EXP=... SEED=N writes them)"
        )
    rows: dict[str, dict[str, float]] = {}
    for seed, path in files.items():
        for label, value in read_quantities(json.loads(path.read_text())).items():
            rows.setdefault(label, {})[seed] = value
    for label in [label for label in rows if label.endswith(NON_FINITE)]:  # where one seed diverged somewhere,
        scored = rows.get(label[: -len(NON_FINITE)], {})  # the seeds that have the score and no such count had none
        rows[label] = {seed: rows[label].get(seed, 0.0) for seed in files if seed in scored or seed in rows[label]}
    summary = {}
    for label, values in rows.items():
        finite = [v for v in values.values() if math.isfinite(v)]
        mean, std = mean_std(finite) if finite else (math.nan, None)
        summary[label] = {"mean": mean, "std": std, "n": len(finite)}
    return {
        "experiment": experiment,
        "seeds": list(files),
        "files": {s: p.name for s, p in files.items()},
        "rows": rows,
        "summary": summary,
    }


def _num(value: float | None) -> str:
    return "—" if value is None or not math.isfinite(value) else f"{value:.4g}"


def render(table: dict[str, Any]) -> str:
    seeds = table["seeds"]
    lines = [
        f"# {table['experiment']} over {len(seeds)} seeds",
        "",
        "Each seed's results file: "
        + ", ".join(f"{s}: `{f}`" for s, f in table["files"].items())
        + ". Scores are each run's mean over its test sequences (the finite ones: a row `..., non-finite sequences` "
        "counts, per seed, those whose forecast diverged, where any seed's did); the last column is the mean ± sample std over "
        "seeds (`n`: seeds with a finite value). Made by `python -m experiments.seeds "
        f"{table['experiment']}`.",
        "",
        "| quantity | " + " | ".join(seeds) + " | mean ± std over seeds |",
        "|---" * (len(seeds) + 2) + "|",
    ]
    for label, values in table["rows"].items():
        s = table["summary"][label]
        spread = f"{_num(s['mean'])} ± {_num(s['std'])} (n = {s['n']})"
        lines.append(f"| {label} | " + " | ".join(_num(values.get(seed)) for seed in seeds) + f" | {spread} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("experiment", help="e.g. lorenz_T1000_cpu (the name of its results file)")
    parser.add_argument("--results-dir", default="results")
    opts = parser.parse_args(argv)
    results_dir = Path(opts.results_dir)
    table = gather(results_dir, opts.experiment)
    (results_dir / f"{opts.experiment}_seeds.json").write_text(json.dumps(table, indent=2, sort_keys=True))
    md = results_dir / f"{opts.experiment}_seeds.md"
    md.write_text(render(table))
    print(md.read_text())
    return md


if __name__ == "__main__":
    main()
