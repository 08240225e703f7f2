"""Time the batched UKF on Lorenz with an SSM-LL transition, beside the reference UKF's structure; writes benchmarks/results/ukf.md.

Run from the repository root: ``python benchmarks/bench_ukf.py [--repeats 3] [--threads 2] [--device cpu]``
(``--tiny``: seconds, for ``make test``).
Set-up of the paper's comparison: 200 Lorenz trajectories (x 500 steps here: the cost per step does not depend on T), measurement = the x component
(variance 0.5, normalised units), ``f = LocallyLinearTransition(3, n_matrices=32, hidden=1024)`` (random
weights: the cost does not depend on training), ``g = Projection([0])``, float32, ``torch.inference_mode``.
Variants run in interleaved rounds (one full filter run of each per round, ``--repeats`` rounds) so that a
shared machine's load falls on all of them alike; reports the median ms per filter step, ratios to the
default in the same run, the split between ``f`` (timed alone on the same ``[B * 7, 3]`` input, as many
calls as the filter makes) and the filter's own algebra (the filter with an identity ``f``), and a
profiler table of one run.

The reference structure (``benchmarks/reference_structure.py``: per-trajectory ``scipy.linalg.sqrtm`` of
``d P``, ``2d`` sigma points, ``f`` and ``g`` called once per sigma point, the reference's own SSM-LL
network) runs in its own worker process with glibc's default allocator, once per round between ours, on
the same measurements; it filters the first ``--ref-steps`` steps (its cost per step does not depend on
the step), and every ratio "reference / this" is taken within a round.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import torch  # noqa: E402
from torch import nn  # noqa: E402

from benchmarks.report import provenance  # noqa: E402
from ssm_ms.inference.shared import call_model  # noqa: E402
from ssm_ms.inference.ukf import UnscentedKalmanFilter  # noqa: E402
from ssm_ms.nets.readout import Projection  # noqa: E402
from ssm_ms.nets.transition import LocallyLinearTransition  # noqa: E402
from ssm_ms.runtime.machine import CpuWatch, quiet_note  # noqa: E402
from ssm_ms.runtime.perf import configure_allocator  # noqa: E402

TINY = {"trajectories": 4, "steps": 20, "ref_steps": 5, "repeats": 1, "k": 4, "hidden": 16}


def lorenz_measurements(n: int, steps: int, seed: int = 0) -> torch.Tensor:
    """Noisy x-component of Lorenz trajectories (RK4, dt = 0.005), normalised units, ``[n, steps, 1]``."""
    mean = torch.tensor([0.0, 0.0, 23.5], dtype=torch.float64)
    std = torch.tensor([7.9, 9.0, 8.6], dtype=torch.float64)

    def vf(s):
        a, b, c = s.unbind(-1)
        return torch.stack([10.0 * (b - a), a * (28.0 - c) - b, a * b - 8.0 / 3.0 * c], -1)

    def rk4(s, dt=0.005):
        k1 = vf(s)
        k2 = vf(s + 0.5 * dt * k1)
        k3 = vf(s + 0.5 * dt * k2)
        return s + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + vf(s + dt * k3))

    gen = torch.Generator().manual_seed(seed)
    x = mean + std * torch.randn(n, 3, generator=gen, dtype=torch.float64)
    for _ in range(1000):
        x = rk4(x)
    xs = []
    for _ in range(steps):
        xs.append(x[:, 0])
        x = rk4(x)
    xn = (torch.stack(xs, 1) - mean[0]) / std[0]
    return (xn + 0.5**0.5 * torch.randn(n, steps, generator=gen, dtype=torch.float64)).unsqueeze(-1)


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def median_ms_per_step(fn, steps: int, repeats: int, device: torch.device) -> tuple[float, list[float]]:
    """Median ms per step over ``repeats`` runs of ``fn`` (which makes ``steps`` steps), and all runs."""
    runs = []
    for _ in range(repeats):
        sync(device)
        start = time.perf_counter()
        fn()
        sync(device)
        runs.append((time.perf_counter() - start) * 1e3 / steps)
    return statistics.median(runs), runs


def reference_worker(trajectories: int, steps: int, threads: int, k: int, hidden: int) -> None:
    """The reference UKF in this process (glibc's default allocator): answer ``run`` lines with ms per step."""
    from benchmarks.reference_structure import RefLocallyLinear, ref_ukf

    torch.set_num_threads(threads)
    torch.manual_seed(0)
    y = lorenz_measurements(trajectories, steps).to(torch.float32)
    f = RefLocallyLinear(3, k, hidden)
    g = lambda x: x[:, :1]  # noqa: E731  (the reference's Lorenz observation model)
    with torch.inference_mode():
        ref_ukf(f, g, y[:, : min(steps, 10)], 0.1, 0.5, 1e-6)  # warm-up
        print(json.dumps({"ready": True}), flush=True)
        for _ in sys.stdin:
            start = time.perf_counter()
            means = ref_ukf(f, g, y, 0.1, 0.5, 1e-6)
            ms = (time.perf_counter() - start) * 1e3 / steps
            print(json.dumps({"ms": ms, "finite": bool(torch.isfinite(means).all())}), flush=True)


class ReferenceUKF:
    def __init__(self, trajectories: int, steps: int, threads: int, k: int, hidden: int):
        cmd = [
            sys.executable,
            str(Path(__file__).resolve()),
            "--reference-worker",
            str(trajectories),
            str(steps),
            str(k),
            str(hidden),
            "--threads",
            str(threads),
        ]
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=ROOT)
        self._read()

    def _read(self) -> dict:
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"the reference UKF worker died (exit code {self.proc.wait()})")
        return json.loads(line)

    def run(self) -> dict:
        self.proc.stdin.write("run\n")
        self.proc.stdin.flush()
        return self._read()

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trajectories", type=int, default=200)
    parser.add_argument(
        "--steps", type=int, default=500, help="filter steps per run (the cost per step does not depend on it)"
    )
    parser.add_argument("--ref-steps", type=int, default=200, help="steps of the reference UKF per round")
    parser.add_argument("--repeats", type=int, default=3, help="interleaved rounds (median reported)")
    parser.add_argument("--threads", type=int, default=2, help="torch.set_num_threads")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--tiny", action="store_true", help="tiny sizes, to check that the script runs")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "ukf.md"))
    parser.add_argument("--reference-worker", nargs=4, type=int, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.reference_worker:
        reference_worker(*args.reference_worker[:2], args.threads, *args.reference_worker[2:])
        return
    k, hidden = 32, 1024
    if args.tiny:
        args.trajectories, args.steps, args.ref_steps, args.repeats = (
            TINY[key] for key in ("trajectories", "steps", "ref_steps", "repeats")
        )
        k, hidden = TINY["k"], TINY["hidden"]

    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    tuned = configure_allocator()  # what cli.py does
    device = torch.device(args.device)
    dtype = torch.float32
    b, steps = args.trajectories, args.steps
    y = lorenz_measurements(b, steps).to(dtype=dtype, device=device)
    f = LocallyLinearTransition(3, n_matrices=k, hidden=hidden).to(device=device, dtype=dtype)
    g = Projection([0]).to(device)
    x_sigma = torch.randn(b * 7, 3, dtype=dtype, device=device)
    bf16 = {"autocast": "bfloat16"}

    def f_alone(autocast):
        def run(y):  # as many calls as a filter over y makes
            for _ in range(y.shape[1] - 1):
                call_model(f, x_sigma, autocast)

        return run

    # paper's noise defaults: P0 = 0.1 I, R = 0.5, Q = 1e-6
    variants = {
        "**UKF, float32 (default)**": UnscentedKalmanFilter(f, g).filter,
        "UKF, float32, `g` through sigma points (a function, not known to be linear)": UnscentedKalmanFilter(
            f, g.forward, state_dim=3
        ).filter,
        "UKF, `f` and `g` under autocast(bfloat16)": UnscentedKalmanFilter(f, g, **bf16).filter,
        f"UKF, autocast(bfloat16) and beta=0 (cubature rule: 6 points, `f` on [{b * 6}, 3])": UnscentedKalmanFilter(
            f, g, beta=0.0, **bf16
        ).filter,
        "filter algebra alone (identity `f`), float32": UnscentedKalmanFilter(nn.Identity(), g, state_dim=3).filter,
        f"`f` alone on [{b * 7}, 3], float32": f_alone(None),
        f"`f` alone on [{b * 7}, 3], autocast(bfloat16)": f_alone(torch.bfloat16),
    }
    default = next(iter(variants))
    ref_name = "reference UKF structure (scipy sqrtm per trajectory, loops over 6 sigma points), float32"
    times: dict[str, list[float]] = {name: [] for name in [ref_name, *variants]}
    ref_finite = True
    watch = CpuWatch()
    reference = ReferenceUKF(b, min(args.ref_steps, steps), args.threads, k, hidden) if device.type == "cpu" else None
    try:
        with torch.inference_mode():
            for run in variants.values():  # warm-up (allocator, kernels)
                run(y[:, :50])
            for _ in range(args.repeats):
                if reference is not None:
                    res = reference.run()
                    times[ref_name].append(res["ms"])
                    ref_finite &= res["finite"]
                for name, run in variants.items():
                    sync(device)
                    start = time.perf_counter()
                    run(y)
                    sync(device)
                    times[name].append((time.perf_counter() - start) * 1e3 / steps)
                print(" ".join(f"{statistics.median(v):.3f}" for v in times.values() if v), flush=True)

            full = UnscentedKalmanFilter(f, g).filter(y[:, :500])
            finite = bool(torch.isfinite(full.means).all() and torch.isfinite(full.covs).all())

            from torch.profiler import ProfilerActivity, profile

            activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
            with profile(activities=activities) as prof:
                UnscentedKalmanFilter(f, g).filter(y[:, :200])
            sort = "self_cuda_time_total" if device.type == "cuda" else "self_cpu_time_total"
            table = prof.key_averages().table(sort_by=sort, row_limit=15, max_name_column_width=36)
    finally:
        if reference is not None:
            reference.close()
    others = watch.others()  # the reference's worker has exited
    if not times[ref_name]:
        del times[ref_name]

    med = {name: statistics.median(v) for name, v in times.items()}
    dev_name = torch.cuda.get_device_name(device) if device.type == "cuda" else f"CPU, {args.threads} torch threads"
    lines = [
        "# Batched UKF: Lorenz, SSM-LL transition, beside the reference UKF's structure (one run, interleaved)",
        "",
        *provenance("benchmarks/bench_ukf.py", argv),
        f"- Python {platform.python_version()}; device: {dev_name}; glibc malloc "
        f"{'tuned as cli.py does' if tuned else 'not tunable here'} (the reference's worker: default)",
        f"- Others' CPU use: {quiet_note(others)} (one worker runs at a time)",
        f"- Set-up: {'TINY sizes (smoke test): ' if args.tiny else ''}{b} trajectories x {steps} steps, state dim 3, "
        f"measurement = x component, SSM-LL with K = {k}, hidden {hidden} (random weights), "
        "float32 measurements, `torch.inference_mode()`, the paper's noise settings (P0 = 0.1 I, R = 0.5, "
        "Q = 1e-6), 7 sigma points per trajectory (alpha=1, beta=2, kappa=0) unless stated.",
        f"- Reference structure: `benchmarks/reference_structure.py` (`ref_ukf`), its own SSM-LL network "
        f"(`x beta^T` and one `Linear(K d -> d)`), `g = x[:, :1]`, the first {min(args.ref_steps, steps)} steps "
        "of the same measurements per round, its own process with glibc's default allocator; outputs finite: "
        f"{ref_finite}.",
        f"- {args.repeats} interleaved rounds: the reference, then one full {steps}-step run of every variant of ours.",
        f"- Outputs finite: {finite}. The random `f` says nothing about accuracy: for the effect of bfloat16 on "
        "forecasts with a trained model see `results/lorenz_T1000_cpu.md` (methods `ukf` and `ukf_bf16`).",
        "",
        "| What | median ms / step | min | vs our default (medians) | reference / this (per-round median) | "
        "rounds (ms / step) |",
        "|---|---:|---:|---:|---:|---|",
    ]
    for name, runs in times.items():
        if ref_name in times and "UKF" in name:  # whole filters only, not their parts
            ratio = f"{statistics.median([r / t for r, t in zip(times[ref_name], runs)]):.2f}"
        else:
            ratio = "-"
        lines.append(
            f"| {name} | {med[name]:.3f} | {min(runs):.3f} | {med[name] / med[default]:.2f} | {ratio} | "
            f"{', '.join(f'{r:.3f}' for r in runs)} |"
        )
    lines += [
        "",
        "## Profile of 200 filter steps, float32 default (torch.profiler, self time)",
        "",
        "```",
        table.strip(),
        "```",
        "",
    ]
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
