"""Time the generation of the paper's Lorenz data sets; writes benchmarks/results/lorenz_data.md.

Run from the repository root: ``python benchmarks/bench_lorenz_data.py [--repeats 3]``.
Measures ``LorenzDataModule.generate`` (RK4 + noise, in memory) for the training set (1000 x 10,000)
and the test set (1000 x 2000), then one full ``prepare_data`` (generation + writing the cache) and
``setup`` (memory-mapping, NaN check, normalisation statistics) into a temporary folder.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from benchmarks.report import provenance, write  # noqa: E402
from datamodules.lorenz import LorenzDataModule  # noqa: E402


def timed(fn) -> tuple[float, object]:
    start = time.perf_counter()
    out = fn()
    return time.perf_counter() - start, out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="runs per in-memory measurement (median reported)")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "lorenz_data.md"))
    args = parser.parse_args()

    dm = LorenzDataModule(data_dir=tempfile.gettempdir())  # paper defaults
    rows = []
    for split, n, steps in (("train", dm.n_train, dm.train_steps), ("test", dm.n_test, dm.test_steps)):
        times = []
        for _ in range(args.repeats):
            seconds, arrays = timed(lambda split=split: dm.generate(split))
            times.append(seconds)
            nbytes = sum(a.nbytes for a in arrays.values())
            del arrays
        rows.append((f"`generate('{split}')`, {n} x {steps} samples", times, nbytes))

    with tempfile.TemporaryDirectory() as tmp:
        cached = LorenzDataModule(data_dir=tmp)
        t_prepare, _ = timed(cached.prepare_data)
        t_setup, _ = timed(cached.setup)
        cut = LorenzDataModule(data_dir=tmp, piece_length=10)
        t_setup_cut, _ = timed(cut.setup)
        disk = sum(f.stat().st_size for f in Path(tmp).rglob("*.npy"))
        assert len(cut.datasets["train"]) == 1_000_000

    lines = [
        "# Lorenz data generation",
        "",
        *provenance(
            "benchmarks/bench_lorenz_data.py", None, f"Python {platform.python_version()}, numpy {np.__version__}"
        ),
        "- Set-up: paper defaults (RK4, dt = 0.005, float64 integration, float32 storage of y, y_clean, state).",
        "",
        "| What | median (s) | runs (s) | arrays (MB) |",
        "|---|---:|---|---:|",
    ]
    for what, times, nbytes in rows:
        runs = ", ".join(f"{t:.2f}" for t in times)
        lines.append(f"| {what} | {statistics.median(times):.2f} | {runs} | {nbytes / 1e6:.0f} |")
    lines += [
        f"| `prepare_data()`: generate both splits + write the cache (one run) | {t_prepare:.2f} | {t_prepare:.2f} | {disk / 1e6:.0f} on disk |",
        f"| `setup()`: memory-map, NaN check, normalisation statistics, piece_length 10000 (one run) | {t_setup:.2f} | {t_setup:.2f} | |",
        f"| `setup()` of the same cache cut into 10^6 pieces, piece_length 10 (one run) | {t_setup_cut:.2f} | {t_setup_cut:.2f} | |",
    ]
    write(args.out, lines)


if __name__ == "__main__":
    main()
