"""Time the batched UKF on Lorenz with an SSM-LL transition; writes benchmarks/results/ukf.md.

Run from the repository root: ``python benchmarks/bench_ukf.py [--repeats 5] [--threads 2] [--device cpu]``.
Set-up of the paper's comparison: 200 Lorenz trajectories x 2000 steps, measurement = the x component
(variance 0.5, normalised units), ``f = LocallyLinearTransition(3, n_matrices=32, hidden=1024)`` (random
weights: the cost does not depend on training), ``g = Projection([0])``, float32, ``torch.inference_mode``.
Variants run in interleaved rounds (one full filter run of each per round, ``--repeats`` rounds) so that a
shared machine's load falls on all of them alike; reports the median ms per filter step, ratios to the
default in the same run, the split between ``f`` (timed alone on the same ``[B * 7, 3]`` input, as many
calls as the filter makes) and the filter's own algebra (the filter with an identity ``f``), how far the
bfloat16 estimates are from the float32 ones, and a profiler table of one run.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import shlex
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import torch  # noqa: E402
from torch import nn  # noqa: E402

from ssm_ms.machine import cpu_model  # noqa: E402
from ssm_ms.inference.shared import call_model  # noqa: E402
from ssm_ms.inference.ukf import UnscentedKalmanFilter  # noqa: E402
from ssm_ms.nets.observation import Projection  # noqa: E402
from ssm_ms.nets.transition import LocallyLinearTransition  # noqa: E402
from ssm_ms.perf import configure_allocator  # noqa: E402

PAPER_REFERENCE_MS = 6.7  # the paper's reference code on this machine, per step for the batch (brief)




def load() -> str:
    try:
        return "/".join(f"{v:.2f}" for v in os.getloadavg())
    except OSError:
        return "n/a"


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trajectories", type=int, default=200)
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--repeats", type=int, default=5, help="interleaved rounds (median reported)")
    parser.add_argument("--threads", type=int, default=2, help="torch.set_num_threads")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "ukf.md"))
    args = parser.parse_args()

    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    tuned = configure_allocator()  # what cli.py does
    device = torch.device(args.device)
    dtype = torch.float32
    b, steps = args.trajectories, args.steps
    y = lorenz_measurements(b, steps).to(dtype=dtype, device=device)
    f = LocallyLinearTransition(3, n_matrices=32, hidden=1024).to(device=device, dtype=dtype)
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
        "UKF, float32, `g` through sigma points (a function, not known to be linear)":
            UnscentedKalmanFilter(f, g.forward, state_dim=3).filter,
        "UKF, `f` and `g` under autocast(bfloat16)": UnscentedKalmanFilter(f, g, **bf16).filter,
        "UKF, autocast(bfloat16) and beta=0 (cubature rule: 6 points, `f` on [%d, 3])" % (b * 6):
            UnscentedKalmanFilter(f, g, beta=0.0, **bf16).filter,
        "filter algebra alone (identity `f`), float32": UnscentedKalmanFilter(nn.Identity(), g, state_dim=3).filter,
        f"`f` alone on [{b * 7}, 3], float32": f_alone(None),
        f"`f` alone on [{b * 7}, 3], autocast(bfloat16)": f_alone(torch.bfloat16),
    }
    default = next(iter(variants))
    times: dict[str, list[float]] = {name: [] for name in variants}
    loads = [load()]
    with torch.inference_mode():
        for run in variants.values():  # warm-up (allocator, kernels)
            run(y[:, :50])
        for _ in range(args.repeats):
            for name, run in variants.items():
                sync(device)
                start = time.perf_counter()
                run(y)
                sync(device)
                times[name].append((time.perf_counter() - start) * 1e3 / steps)
            print(" ".join(f"{statistics.median(v):.3f}" for v in times.values()), flush=True)
        loads.append(load())

        full = UnscentedKalmanFilter(f, g).filter(y[:, :500])
        finite = bool(torch.isfinite(full.means).all() and torch.isfinite(full.covs).all())

        from torch.profiler import ProfilerActivity, profile

        activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
        with profile(activities=activities) as prof:
            UnscentedKalmanFilter(f, g).filter(y[:, :200])
        sort = "self_cuda_time_total" if device.type == "cuda" else "self_cpu_time_total"
        table = prof.key_averages().table(sort_by=sort, row_limit=15, max_name_column_width=36)

    med = {name: statistics.median(v) for name, v in times.items()}
    cmd = "python " + " ".join(shlex.quote(a) for a in [os.path.relpath(sys.argv[0], ROOT), *sys.argv[1:]])
    dev_name = torch.cuda.get_device_name(device) if device.type == "cuda" else f"CPU, {args.threads} torch threads"
    lines = [
        "# Batched UKF: Lorenz, SSM-LL transition",
        "",
        f"- Date: {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC",
        f"- Machine: {cpu_model()}, {os.cpu_count()} logical cores (`os.cpu_count()`), Python "
        f"{platform.python_version()}, torch {torch.__version__}; device: {dev_name}; glibc malloc "
        f"{'tuned as cli.py does' if tuned else 'not tunable here'}",
        f"- Load average (1/5/15 min) before: {loads[0]}, after: {loads[1]} (the machine is shared: figures "
        "under load are slower than on a quiet one; this benchmark's own threads add about 2 to the 1-min figure)",
        f"- Command: `{cmd}`",
        f"- Set-up: {b} trajectories x {steps} steps, state dim 3, measurement = x component, "
        "`LocallyLinearTransition(3, n_matrices=32, hidden=1024)` (random weights), `Projection([0])`, "
        "float32 measurements, `torch.inference_mode()`, paper's noise settings, 7 sigma points per "
        "trajectory (alpha=1, beta=2, kappa=0) unless stated. Each step: one `f` on "
        f"[{b * 7}, 3], a linear measurement update, two batched 3x3 Cholesky.",
        f"- {args.repeats} interleaved rounds, one full {steps}-step run of every variant per round.",
        f"- Paper's reference code: {PAPER_REFERENCE_MS} ms per step for the batch (figure from the issue).",
        f"- Outputs finite: {finite}. The random `f` says nothing about accuracy: for the effect of bfloat16 on "
        "forecasts with a trained model see `results/lorenz_T1000_cpu.md` (methods `ukf` and `ukf_bf16`).",
        "",
        "| What | median ms / step | min | vs default (medians) | vs paper's 6.7 ms | rounds (ms / step) |",
        "|---|---:|---:|---:|---:|---|",
    ]
    for name, runs in times.items():
        lines.append(
            f"| {name} | {med[name]:.3f} | {min(runs):.3f} | {med[name] / med[default]:.2f} | "
            f"{med[name] / PAPER_REFERENCE_MS:.2f} | {', '.join(f'{r:.3f}' for r in runs)} |"
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
