"""Time the batched UKF on Lorenz with an SSM-LL transition; writes benchmarks/results/ukf.md.

Run from the repository root: ``python benchmarks/bench_ukf.py [--repeats 5] [--threads 2] [--device cpu]``.
Set-up of the paper's comparison: 200 Lorenz trajectories x 2000 steps, measurement = the x component
(variance 0.5, normalised units), ``f = LocallyLinearTransition(3, n_matrices=32, hidden=1024)`` (random
weights: the cost does not depend on training), ``g = Projection([0])``, float32, ``torch.inference_mode``.
Reports the median ms per filter step over ``--repeats`` full runs, and the split between ``f`` (timed alone
on the same ``[B * 7, 3]`` input, as many calls as the filter makes) and the filter's own algebra (the
filter with an identity ``f``), plus a profiler table of one run.
"""

from __future__ import annotations

import argparse
import copy
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
    parser.add_argument("--repeats", type=int, default=5, help="full filter runs (median reported)")
    parser.add_argument("--threads", type=int, default=2, help="torch.set_num_threads")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--skip-default-malloc", action="store_true", help="only time with tuned malloc")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "ukf.md"))
    args = parser.parse_args()

    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    device = torch.device(args.device)
    dtype = torch.float32
    b, steps = args.trajectories, args.steps
    y = lorenz_measurements(b, steps).to(dtype=dtype, device=device)
    f = LocallyLinearTransition(3, n_matrices=32, hidden=1024).to(device=device, dtype=dtype)
    g = Projection([0]).to(device)
    ukf = UnscentedKalmanFilter(f, g)  # paper's defaults: P0 = 0.1 I, R = 0.5, Q = 1e-6
    ukf_identity = UnscentedKalmanFilter(nn.Identity(), g, state_dim=3)
    x_sigma = torch.randn(b * 7, 3, dtype=dtype, device=device)
    load_before = load()

    def f_only():
        for _ in range(steps - 1):
            f(x_sigma)

    ukf_cubature = UnscentedKalmanFilter(f, g, beta=0.0)
    # What-if for f itself (not the filter): the same network with an in-place ReLU after the first layer.
    f_inplace = copy.deepcopy(f)
    relus = [m for m in f_inplace.modules() if isinstance(m, nn.ReLU)]
    for m in relus:
        m.inplace = True
    ukf_inplace = UnscentedKalmanFilter(f_inplace, g)
    with torch.inference_mode():
        same = torch.equal(f(x_sigma), f_inplace(x_sigma))

    def f_inplace_only():
        for _ in range(steps - 1):
            f_inplace(x_sigma)

    rows = []

    def record(name: str, fn) -> float:
        before = os.getloadavg()[0]
        med, runs = median_ms_per_step(fn, steps, args.repeats, device)
        rows.append((name, med, runs, f"{before:.2f}/{os.getloadavg()[0]:.2f}"))
        print(f"{name}: median {med:.3f} ms/step, min {min(runs):.3f}", flush=True)
        return med

    with torch.inference_mode():
        ukf.filter(y[:, :50])  # warm-up (allocator, kernels)
        ukf_identity.filter(y[:, :50])
        if not args.skip_default_malloc:
            record("UKF step, whole (f, g, algebra), default glibc malloc", lambda: ukf.filter(y))
            record(f"`f` alone on [{b * 7}, 3], default glibc malloc", f_only)
        tuned = configure_allocator()  # what cli.py does
        tag = "malloc tuned" if tuned else "malloc tuning unavailable"
        total = record(f"**UKF step, whole (f, g, algebra), {tag}**", lambda: ukf.filter(y))
        f_ms = record(f"`f` alone on [{b * 7}, 3], {tag}", f_only)
        record(f"filter algebra + g (identity f), {tag}", lambda: ukf_identity.filter(y))
        name = f"UKF step with beta=0 (cubature rule, 6 points, f on [{b * 6}, 3]), {tag}"
        record(name, lambda: ukf_cubature.filter(y))
        if relus:
            record(f"what-if: UKF step, `f` with in-place ReLU, {tag}", lambda: ukf_inplace.filter(y))
            record(f"what-if: `f` with in-place ReLU alone, {tag}", f_inplace_only)

        from torch.profiler import ProfilerActivity, profile

        activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
        with profile(activities=activities) as prof:
            ukf.filter(y[:, :200])
        sort = "self_cuda_time_total" if device.type == "cuda" else "self_cpu_time_total"
        table = prof.key_averages().table(sort_by=sort, row_limit=15, max_name_column_width=36)
    load_after = load()

    # accuracy check that the run did real work: the filter with the untrained f on these data
    with torch.inference_mode():
        means, covs = ukf.filter(y[:4, :100])
        finite = bool(torch.isfinite(means).all() and torch.isfinite(covs).all())

    cmd = "python " + " ".join(shlex.quote(a) for a in [os.path.relpath(sys.argv[0], ROOT), *sys.argv[1:]])
    dev_name = torch.cuda.get_device_name(device) if device.type == "cuda" else f"CPU, {args.threads} torch threads"
    lines = [
        "# Batched UKF: Lorenz, SSM-LL transition",
        "",
        f"- Date: {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC",
        f"- Machine: {cpu_model()}, {os.cpu_count()} logical cores (`os.cpu_count()`), Python "
        f"{platform.python_version()}, torch {torch.__version__}; device: {dev_name}",
        f"- Load average (1/5/15 min) before: {load_before}, after: {load_after} (the machine is shared: "
        "figures under load are slower than on a quiet machine; this benchmark's own 2 threads add about 2 "
        "to the 1-min figure while it runs)",
        f"- Command: `{cmd}`",
        f"- Set-up: {b} trajectories x {steps} steps, state dim 3, measurement = x component, "
        "`LocallyLinearTransition(3, n_matrices=32, hidden=1024)` (random weights), `Projection([0])`, "
        "float32, `torch.inference_mode()`, paper's noise settings, 7 sigma points per trajectory "
        f"(alpha=1, beta=2, kappa=0). Each step: one `f` on [{b * 7}, 3], one `g`, two batched 3x3 Cholesky.",
        f"- Paper's reference code: {PAPER_REFERENCE_MS} ms per step for the batch (figure from the brief).",
        f"- Outputs finite: {finite}. In-place-ReLU copy of `f` gives identical outputs: {same}.",
        "",
        "| What | median ms / step | min | runs (ms / step) | 1-min load before/after |",
        "|---|---:|---:|---|---|",
    ]
    for name, med, runs, ld in rows:
        lines.append(f"| {name} | {med:.3f} | {min(runs):.3f} | {', '.join(f'{r:.3f}' for r in runs)} | {ld} |")
    lines += [
        "",
        f"With {tag}: `f` is {100 * f_ms / total:.0f}% of the whole step; the algebra figure includes `g` and "
        "the Python-level work of a step. \"malloc tuned\": `ssm_ms.perf.configure_allocator()` (as `cli.py`), "
        "glibc keeps freed memory, so the 5.7 MB hidden activations of `f` are not page-faulted in again "
        "every step; a process-wide setting, not part of the filter.",
        "",
        f"## Profile of 200 filter steps, {tag} (torch.profiler, self time)",
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
