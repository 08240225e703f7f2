"""The results files of the identification benchmarks: ``<results_dir>/<experiment>.json``, every run of an
experiment (the one source of its scores), and a figure per test recording (measured and simulated output over a
window, the error along the whole recording).

A run is keyed by its method name and seed (``SSM-LL (d = 4) + UKF, seed 1``; a later run of the same key replaces
it), its scores per test recording (``tests``) in the order the benchmark lists them. The file is merged by the
forecasting results' writer (:func:`ssm_ms.forecasting.results.update_results`: whole or not at all, its path
recorded in ``WRITTEN``); the library writes JSON only: the markdown table beside published baselines is the
application's (:mod:`experiments.benchmark_results`; ``python cli.py test`` renders it beside each file a run wrote).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ssm_ms.forecasting.results import update_results


def write_benchmark_results(
    results_dir: Path,
    info: dict[str, Any],
    rows: dict[str, dict[str, Any]],
    figures: dict[str, tuple[np.ndarray, np.ndarray]],
    figures_dir: str | None,
    n_init: int,
) -> Path:
    """Merge this run (``info``: what was run where; ``rows``: ``{test recording: scores}``) into the experiment's
    JSON, draw the figures; return the JSON's path."""
    name = info["experiment"]

    def merge(data: dict[str, Any]) -> None:
        data.setdefault("experiment", name)  # a new file: the experiment first, then its runs
        data.setdefault("runs", {})[run_key(info)] = {"info": info, "tests": rows}

    # keys in order: the runs as they came, the test recordings as the benchmark lists them
    path = update_results(results_dir, name, merge, sort_keys=False, end="\n")
    if figures_dir is not None:
        for test, (truth, model) in figures.items():
            figure = Path(figures_dir) / f"{name}_{_slug(info['method'])}_{_slug(test)}.png"
            if info.get("seed") in (None, 0) or not figure.exists():  # a method's figure: its first seed's run
                draw(figure, truth, model, n_init, test, info)
    return path


def run_key(info: dict[str, Any]) -> str:
    """A run's key in the results file: its method, and its seed where the fit recorded one."""
    seed = info.get("seed")
    return info["method"] if seed is None else f"{info['method']}, seed {seed}"


def _slug(text: str) -> str:
    """``SSM-LL (d = 4) + UKF`` -> ``ssm_ll_d_4_ukf``."""
    return "_".join("".join(c if c.isalnum() else " " for c in text.lower()).split())


def draw(path: Path, truth: np.ndarray, model: np.ndarray, n_init: int, test: str, info: dict[str, Any]) -> None:
    """Measured and simulated output over the first 1000 simulated samples, and the error along the whole recording
    (its RMS over windows of 1% of it)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path.parent.mkdir(parents=True, exist_ok=True)
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(10, 6))
    end = min(len(truth), n_init + 1000)
    steps = np.arange(len(truth))
    top.plot(steps[:end], truth[:end, 0], label="measured", lw=1)
    top.plot(steps[:end], model[:end, 0], label="simulated", lw=1)
    top.axvline(n_init, color="grey", ls=":", lw=1)
    top.set_title(f"{info['experiment']}, {test}: {info['method']}")
    top.legend(loc="upper right")
    error = np.abs(model[n_init:, 0] - truth[n_init:, 0])
    window = max(1, len(error) // 100)
    rms = np.sqrt(np.convolve(np.nan_to_num(error, nan=np.inf) ** 2, np.ones(window) / window, mode="valid"))
    bottom.plot(steps[n_init : n_init + len(rms)], rms, lw=1)
    bottom.set_ylabel(f"|error| RMS over {window} samples ({info.get('unit') or 'units'})")
    bottom.set_xlabel("sample")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
