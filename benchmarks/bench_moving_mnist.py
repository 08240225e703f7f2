"""Moving MNIST on the fly: memory of the 100,000-trajectory training set and loader throughput.

Run from the repository root::

    python benchmarks/bench_moving_mnist.py [--mnist-root PATH] [--runs 3] [--batches 300]

Writes benchmarks/results/moving_mnist.md. Figures only: the targets (at most 200 MB added to the
peak memory, at least 1,000 trajectories per second with 2 workers and batch 50) are stated next
to them for reference. Memory is measured in fresh processes (this script with --probe-memory):
ru_maxrss after the imports, after setup() and after iterating training batches.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.report import provenance, write  # noqa: E402
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


def time_us(fn, n: int, repeats: int = 5) -> float:
    """Median over ``repeats`` of the mean time of ``n`` calls, in microseconds."""
    runs = []
    for _ in range(repeats):
        t = time.perf_counter()
        for _ in range(n):
            fn()
        runs.append((time.perf_counter() - t) / n * 1e6)
    return statistics.median(runs)


def throughput(dm: MovingMNISTDataModule, warmup: int, batches: int, desc: str) -> float:
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
    del it, loader  # shuts the workers down
    return rate


def probe_memory(args: argparse.Namespace) -> None:
    """One fresh-process memory measurement, printed as JSON on the last line."""
    rss0 = maxrss_mb()
    dm = MovingMNISTDataModule(
        mnist_root=args.mnist_root, n_train=args.n_train, batch_size=args.batch_size, num_workers=args.probe_memory
    )
    dm.prepare_data()
    t = time.perf_counter()
    dm.setup()
    setup_s = time.perf_counter() - t
    rss1 = maxrss_mb()
    it = iter(dm.train_dataloader())
    for _ in range(args.mem_batches):
        next(it)
    rss2, current = maxrss_mb(), proc_status().get("VmRSS", float("nan"))
    workers = [proc_status(w.pid) for w in getattr(it, "_workers", [])]
    digits_mb = sum(ds.digits.numel() for ds in dm.datasets.values()) / 2**20
    print(
        json.dumps(
            {
                "imports": rss0,
                "setup": rss1 - rss0,
                "batches": rss2 - rss0,
                "current": current - rss0,
                "setup_s": setup_s,
                "digits": digits_mb,
                "workers": workers,
            }
        )
    )


def run_probes(args: argparse.Namespace, workers: int) -> list[dict]:
    out = []
    for _ in tqdm(range(args.mem_runs), desc=f"memory probes, workers={workers}", leave=False):
        cmd = [
            sys.executable,
            str(Path(__file__).resolve()),
            "--probe-memory",
            str(workers),
            "--mnist-root",
            args.mnist_root,
            "--n-train",
            str(args.n_train),
            "--batch-size",
            str(args.batch_size),
            "--mem-batches",
            str(args.mem_batches),
        ]
        res = subprocess.run(cmd, capture_output=True, text=True, check=True)
        out.append(json.loads(res.stdout.strip().splitlines()[-1]))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mnist-root", default=str(DEFAULT_ROOT), help="folder holding MNIST/raw/ (default: %(default)s)")
    ap.add_argument("--n-train", type=int, default=100_000)
    ap.add_argument("--batch-size", type=int, default=50)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--runs", type=int, default=3, help="throughput runs (median reported)")
    ap.add_argument("--batches", type=int, default=300, help="timed batches per run")
    ap.add_argument("--warmup", type=int, default=20, help="batches before timing (worker start-up)")
    ap.add_argument("--mem-runs", type=int, default=3, help="fresh processes per memory measurement (median)")
    ap.add_argument("--mem-batches", type=int, default=100, help="batches iterated in a memory measurement")
    ap.add_argument("--probe-memory", type=int, default=None, metavar="WORKERS", help=argparse.SUPPRESS)
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "moving_mnist.md"))
    args = ap.parse_args()
    if args.probe_memory is not None:
        probe_memory(args)
        return

    # ---------------------------------------------------------------- memory (fresh processes)
    probes = {w: run_probes(args, w) for w in sorted({0, args.workers})}

    # ---------------------------------------------------------------- per-item costs
    dm = MovingMNISTDataModule(
        mnist_root=args.mnist_root, n_train=args.n_train, batch_size=args.batch_size, num_workers=0
    )
    dm.prepare_data()
    dm.setup()
    train = dm.datasets["train"]
    digits = train.digits.numpy()
    tr = train.trajectory(12345)
    t_traj = time_us(lambda: trajectory(0, "train", 12345, len(digits)), 2000)
    t_render = time_us(lambda: render(digits, tr["digit_indices"], tr["top_left"], 64), 2000)
    t_item = time_us(lambda: train[12345], 1000)
    t_batch = time_us(lambda: train.__getitems__(list(range(1000, 1000 + args.batch_size))), 20) / args.batch_size

    # ---------------------------------------------------------------- loader throughput
    rate0 = throughput(dm, 5, max(args.batches // 3, 10), "workers=0")
    dm_w = MovingMNISTDataModule(
        mnist_root=args.mnist_root, n_train=args.n_train, batch_size=args.batch_size, num_workers=args.workers
    )
    dm_w.datasets = dm.datasets  # same data sets (same digits in memory), other loader settings
    rates = []
    for r in range(args.runs):
        rates.append(throughput(dm_w, args.warmup, args.batches, f"workers={args.workers} run {r + 1}"))

    # ---------------------------------------------------------------- report
    def mem(ps: list[dict], key: str) -> str:
        vals = [p[key] for p in ps]
        return f"{statistics.median(vals):.1f} MiB ({', '.join(f'{v:.1f}' for v in vals)})"

    rows: list[tuple[str, str]] = [
        ("peak RSS after imports (torch, lightning, datamodules)", mem(probes[0], "imports")),
        ("added to peak RSS by setup() of train + test", mem(probes[0], "setup")),
        ("digits held (train + test, uint8)", f"{probes[0][0]['digits']:.1f} MiB"),
        (
            f"**added to peak RSS by setup() + {args.mem_batches} batches, workers=0** (target <= 200 MiB)",
            f"**{mem(probes[0], 'batches')}**",
        ),
    ]
    if args.workers:
        pw = probes[args.workers]
        rows += [
            (
                f"added to the main process's peak RSS by setup() + {args.mem_batches} batches, workers={args.workers}",
                mem(pw, "batches"),
            ),
            (
                f"worker RSS after {args.mem_batches} batches, last probe (VmRSS / RssAnon / RssShmem; "
                "fork-shared pages count in each)",
                "; ".join(
                    f"{s.get('VmRSS', 0):.0f} / {s.get('RssAnon', 0):.0f} / {s.get('RssShmem', 0):.0f} MiB"
                    for s in pw[-1]["workers"]
                )
                or "n/a",
            ),
        ]
    rows += [
        (
            "setup() time (read + check both MNIST splits)",
            f"{statistics.median(p['setup_s'] for p in probes[0]):.2f} s",
        ),
        ("trajectory(): seeded RNG + motion, per item", f"{t_traj:.0f} us"),
        ("render(): 2 digits x 20 frames, per item", f"{t_render:.0f} us"),
        ("dataset[i] (motion + render + float32), per item", f"{t_item:.0f} us"),
        (f"dataset.__getitems__ of {args.batch_size} (what the loader calls), per trajectory", f"{t_batch:.0f} us"),
        ("loader throughput, workers=0 (1 run)", f"{rate0:.0f} trajectories/s"),
        (
            f"**loader throughput, workers={args.workers}, batch {args.batch_size}** (median of {args.runs}; "
            "target >= 1000)",
            f"**{statistics.median(rates):.0f} trajectories/s** ({', '.join(f'{r:.0f}' for r in rates)})",
        ),
    ]
    n_cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    lines = [
        "# Moving MNIST on the fly: memory and loader throughput",
        "",
        *provenance(
            "benchmarks/bench_moving_mnist.py",
            None,
            f"{n_cores} usable cores, load average at the end {', '.join(f'{x:.2f}' for x in os.getloadavg())}; "
            f"Python {platform.python_version()}, {torch.get_num_threads()} intra-op threads, numpy {np.__version__}",
        ),
        f"- Data: n_train={args.n_train}, n_test=10000, seq_len=20, 64x64, 2 digits, step 3.6 px, batch "
        f"{args.batch_size}; MNIST from `{args.mnist_root}`",
        f"- Memory: ru_maxrss in {args.mem_runs} fresh processes each (median, then all runs), relative to the "
        f"peak after the imports. Beyond the digits, iterating adds the in-flight batches "
        f"({args.batch_size} x 20 x 64 x 64 float32 = {args.batch_size * 20 * 64 * 64 * 4 / 2**20:.1f} MiB each) "
        "and whatever freed heap glibc keeps (it varies from run to run)",
        f"- Throughput: {args.batches} batches timed after {args.warmup} warm-up batches, fresh DataLoader "
        "(fresh workers) per run, shuffled sampler",
        "",
        "| quantity | value |",
        "|---|---|",
        *[f"| {k} | {v} |" for k, v in rows],
    ]
    write(args.out, lines)


if __name__ == "__main__":
    main()
