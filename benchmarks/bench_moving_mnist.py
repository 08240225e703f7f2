"""Moving MNIST on the fly: memory of the 100,000-trajectory training set and loader throughput.

Run from the repository root::

    python benchmarks/bench_moving_mnist.py [--mnist-root PATH] [--runs 3] [--batches 300]

Writes benchmarks/results/moving_mnist.md. Figures only: the targets (at most 200 MB added to the
peak memory, at least 1,000 trajectories per second with 2 workers and batch 50) are stated next
to them for reference.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import resource
import shlex
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from datamodules.moving_mnist import MovingMNISTDataModule, render, trajectory  # noqa: E402

DEFAULT_ROOT = REPO.parent / "shared" / "data"


def maxrss_mb(who: int = resource.RUSAGE_SELF) -> float:
    """Peak resident set size in MiB (ru_maxrss is in KiB on Linux)."""
    return resource.getrusage(who).ru_maxrss / 1024


def proc_status(pid: int | str = "self") -> dict[str, float]:
    """VmRSS / RssAnon / RssFile / RssShmem of a process in MiB (from /proc/<pid>/status)."""
    out = {}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            key, _, rest = line.partition(":")
            if key in ("VmRSS", "RssAnon", "RssFile", "RssShmem"):
                out[key] = int(rest.split()[0]) / 1024
    except OSError:
        pass
    return out


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def time_us(fn, n: int, repeats: int = 5) -> float:
    """Median over ``repeats`` of the mean time of ``n`` calls, in microseconds."""
    runs = []
    for _ in range(repeats):
        t = time.perf_counter()
        for _ in range(n):
            fn()
        runs.append((time.perf_counter() - t) / n * 1e6)
    return statistics.median(runs)


def throughput(dm: MovingMNISTDataModule, warmup: int, batches: int, desc: str) -> tuple[float, dict]:
    """Trajectories per second over ``batches`` batches after ``warmup`` (fresh loader, fresh workers)."""
    loader = dm.train_dataloader()
    it = iter(loader)
    for _ in range(warmup):
        next(it)
    n = 0
    t = time.perf_counter()
    for _ in tqdm(range(batches), desc=desc, leave=False, mininterval=2.0):
        n += len(next(it)["index"])
    rate = n / (time.perf_counter() - t)
    workers = {}
    for k, w in enumerate(getattr(it, "_workers", [])):
        workers[k] = proc_status(w.pid)
    del it, loader  # shuts the workers down
    return rate, workers


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mnist-root", default=str(DEFAULT_ROOT), help="folder holding MNIST/raw/ (default: %(default)s)")
    ap.add_argument("--n-train", type=int, default=100_000)
    ap.add_argument("--batch-size", type=int, default=50)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--runs", type=int, default=3, help="throughput runs (median reported)")
    ap.add_argument("--batches", type=int, default=300, help="timed batches per run")
    ap.add_argument("--warmup", type=int, default=20, help="batches before timing (worker start-up)")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "moving_mnist.md"))
    args = ap.parse_args()

    command = "python " + " ".join(shlex.quote(a) for a in sys.argv)
    rows: list[tuple[str, str]] = []

    # ---------------------------------------------------------------- memory of setup
    rss0, st0 = maxrss_mb(), proc_status()
    dm = MovingMNISTDataModule(
        mnist_root=args.mnist_root, n_train=args.n_train, batch_size=args.batch_size, num_workers=0, seed=0
    )
    dm.prepare_data()
    t = time.perf_counter()
    dm.setup()
    setup_s = time.perf_counter() - t
    rss1, st1 = maxrss_mb(), proc_status()
    train = dm.datasets["train"]
    it = iter(dm.train_dataloader())
    for _ in tqdm(range(100), desc="memory: 100 batches, workers=0", leave=False, mininterval=2.0):
        next(it)
    del it
    rss2, st2 = maxrss_mb(), proc_status()

    # ---------------------------------------------------------------- per-item costs
    digits = train.digits.numpy()
    tr = train.trajectory(12345)
    t_traj = time_us(lambda: trajectory(0, "train", 12345, len(digits)), 2000)
    t_render = time_us(lambda: render(digits, tr["digit_indices"], tr["top_left"], 64), 2000)
    t_item = time_us(lambda: train[12345], 1000)

    # ---------------------------------------------------------------- loader throughput
    rates0 = [throughput(dm, 5, max(args.batches // 3, 10), "workers=0")[0]]
    dm_w = MovingMNISTDataModule(
        mnist_root=args.mnist_root, n_train=args.n_train, batch_size=args.batch_size, num_workers=args.workers
    )
    dm_w.datasets = dm.datasets  # same data sets (same digits in memory), other loader settings
    rates, worker_mem = [], {}
    for r in range(args.runs):
        rate, worker_mem = throughput(dm_w, args.warmup, args.batches, f"workers={args.workers} run {r + 1}")
        rates.append(rate)
    rss3, st3 = maxrss_mb(), proc_status()
    children = maxrss_mb(resource.RUSAGE_CHILDREN)

    # ---------------------------------------------------------------- report
    def mb(x: float) -> str:
        return f"{x:.1f} MiB"

    rows += [
        ("peak RSS (ru_maxrss) after imports", mb(rss0)),
        ("peak RSS after setup() of train + test", mb(rss1)),
        ("peak RSS after 100 training batches (workers=0)", mb(rss2)),
        (f"peak RSS after the {args.workers}-worker runs (main process)", mb(rss3)),
        ("**added to peak by setup + 100 batches** (target <= 200 MiB)", f"**{mb(rss2 - rss0)}**"),
        ("current RSS before setup / after setup / after batches",
         " / ".join(mb(s.get("VmRSS", float("nan"))) for s in (st0, st1, st2))),
        ("digits held (train + test, uint8)",
         mb((train.digits.numel() + dm.datasets["test"].digits.numel()) / 2**20)),
        ("setup() time (read + check both MNIST splits)", f"{setup_s:.2f} s"),
        ("trajectory(): seeded RNG + motion, per item", f"{t_traj:.0f} us"),
        ("render(): 2 digits x 20 frames, per item", f"{t_render:.0f} us"),
        ("dataset[i] (motion + render + float32), per item", f"{t_item:.0f} us"),
        ("loader throughput, workers=0 (1 run)", f"{rates0[0]:.0f} trajectories/s"),
        (f"**loader throughput, workers={args.workers}, batch {args.batch_size}** (median of {args.runs}; "
         "target >= 1000)", f"**{statistics.median(rates):.0f} trajectories/s**"),
        (f"  the {args.runs} runs", ", ".join(f"{r:.0f}" for r in rates)),
        ("worker RSS at the end of the last run (VmRSS / RssAnon / RssShmem)",
         "; ".join(f"w{k}: {s.get('VmRSS', 0):.0f} / {s.get('RssAnon', 0):.0f} / {s.get('RssShmem', 0):.0f} MiB"
                   for k, s in worker_mem.items()) or "n/a"),
        ("peak RSS of the largest finished worker (RUSAGE_CHILDREN)", mb(children)),
    ]
    n_cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    lines = [
        "# Moving MNIST on the fly: memory and loader throughput",
        "",
        f"- Date: {datetime.datetime.now().astimezone().isoformat(timespec='seconds')}",
        f"- Command: `{command}` (from the repository root)",
        f"- Machine: {cpu_model()}, {n_cores} usable cores ({os.cpu_count()} logical), "
        f"load average at the end {', '.join(f'{x:.2f}' for x in os.getloadavg())}",
        f"- Software: Python {platform.python_version()}, torch {torch.__version__} "
        f"({torch.get_num_threads()} intra-op threads), numpy {np.__version__}",
        f"- Data: n_train={args.n_train}, n_test=10000, seq_len=20, 64x64, 2 digits, step 3.6 px; "
        f"MNIST from `{args.mnist_root}`",
        f"- Throughput: {args.batches} batches of {args.batch_size} timed after {args.warmup} warm-up batches, "
        f"fresh DataLoader per run, shuffled sampler; memory: ru_maxrss of this process before/after `setup()` "
        f"and after iterating",
        "",
        "| quantity | value |",
        "|---|---|",
        *[f"| {k} | {v} |" for k, v in rows],
        "",
    ]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines))
    print("\n".join(lines))
    print(f"written to {out}")


if __name__ == "__main__":
    main()
