"""Time the generation of the paper's pendulum data sets and measure the integrator's energy drift.

    python benchmarks/bench_pendulum_data.py [--repeats R] [--fraction F] [--out PATH]

Generates the simple pendulum (1 link, 24x24, 1000 + 1000 trajectories) and the quadruple pendulum
(4 links, 48x48, 2000 + 2000 trajectories, damping 0.1) into a temporary folder with the default
``workers`` (all available cores), ``prepare_data`` end to end (simulation, rendering, noise,
writing the cache). Also measures the per-trajectory cost of dynamics / rendering / noise in one
process, and the energy drift of undamped trajectories at the default RK4 step. Writes
``benchmarks/results/pendulum_data.md``. ``--fraction 0.05`` makes a quick smoke run.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pinocchio as pin

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.report import provenance, write  # noqa: E402
from datamodules.pendulum import PendulumDataModule  # noqa: E402
from datamodules.pendulum_generation import CHUNK_SIZE, available_cores  # noqa: E402
from datamodules.pendulum_render import quantize, render  # noqa: E402
from datamodules.pendulum_sim import GRAVITY, pendulum_model, simulate  # noqa: E402

CONFIGS = {
    "simple (1 link, 24x24)": dict(n_links=1, image_size=24, n_train=1000, n_test=1000),
    "quadruple (4 links, 48x48)": dict(
        n_links=4, image_size=48, n_train=2000, n_test=2000, damping=0.1, max_velocity=0.0
    ),
}


def chain_energy(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Energy of unit point masses on unit links (relative angles ``[..., n]``)."""
    phi, dphi = np.cumsum(q, -1), np.cumsum(v, -1)
    vx, vz = np.cumsum(dphi * np.cos(phi), -1), np.cumsum(dphi * np.sin(phi), -1)
    return 0.5 * (vx**2 + vz**2).sum(-1) - GRAVITY * np.cumsum(np.cos(phi), -1).sum(-1)


def energy_drift(n: int, max_velocity: float, step: float, count: int = 48) -> tuple[float, float]:
    """Median and max over trajectories of max_t |E(t) - E(0)| / (g * sum of heights), 10 s undamped."""
    rng = np.random.default_rng(12345)
    q0 = rng.uniform(-math.pi, math.pi, (count, n))
    v0 = rng.uniform(-max_velocity, max_velocity, (count, n))
    model = pendulum_model(n)
    q, v, _ = simulate(model, model.createData(), q0, v0, 101, int(round(0.1 / step)), step)
    e = chain_energy(q, v)
    drift = np.abs(e - e[:, :1]).max(1) / (GRAVITY * n * (n + 1) / 2)
    return float(np.median(drift)), float(drift.max())


def cost_split(cfg: dict, count: int = CHUNK_SIZE, repeats: int = 3) -> dict[str, float]:
    """Milliseconds per trajectory of dynamics, rendering and noise in one process (median of repeats)."""
    dm = PendulumDataModule(**cfg)
    params = dm.generator_params()
    model = pendulum_model(dm.n_links)
    data = model.createData()
    rng = np.random.default_rng(0)
    times: dict[str, list[float]] = {"dynamics": [], "rendering": [], "noise + quantisation": []}
    for _ in range(repeats):
        q0 = rng.uniform(-dm.max_angle, dm.max_angle, (count, dm.n_links))
        v0 = rng.uniform(-dm.max_velocity, dm.max_velocity, (count, dm.n_links))
        t = time.perf_counter()
        q, _, _ = simulate(model, data, q0, v0, dm.n_frames, int(round(dm.frame_dt / dm.dt)), dm.dt, dm.damping)
        times["dynamics"].append(time.perf_counter() - t)
        t = time.perf_counter()
        clean = [render(q[j], dm.image_size, dm.line_width, dm.rendering) for j in range(count)]
        times["rendering"].append(time.perf_counter() - t)
        t = time.perf_counter()
        for c in clean:
            noise = rng.standard_normal(c.shape, dtype=np.float32) * np.float32(params["noise_std"]) + c
            quantize(np.clip(noise, 0, 1))
            quantize(c)
        times["noise + quantisation"].append(time.perf_counter() - t)
    return {k: 1e3 * statistics.median(v) / count for k, v in times.items()}


def time_generation(cfg: dict, repeats: int) -> tuple[list[float], float, int]:
    """Wall seconds of prepare_data (fresh cache each repeat), seconds of a cached re-run, workers."""
    runs, cached, workers = [], math.nan, 0
    for _ in range(repeats):
        tmp = tempfile.mkdtemp(prefix="bench_pendulum_")
        try:
            dm = PendulumDataModule(data_dir=tmp, **cfg)
            workers = dm.workers
            t = time.perf_counter()
            dm.prepare_data()
            runs.append(time.perf_counter() - t)
            t = time.perf_counter()
            PendulumDataModule(data_dir=tmp, **cfg).prepare_data()
            cached = time.perf_counter() - t
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    return runs, cached, workers


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=1, help="timed generations per data set (median reported)")
    parser.add_argument("--fraction", type=float, default=1.0, help="scale the trajectory counts (smoke runs)")
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "pendulum_data.md"))
    args = parser.parse_args()

    step = PendulumDataModule().dt
    load_before = os.getloadavg()
    lines = [
        "# Pendulum data generation",
        "",
        *provenance(
            "benchmarks/bench_pendulum_data.py",
            None,
            f"{available_cores()} available cores; Python {platform.python_version()}, numpy {np.__version__}, "
            f"pinocchio {pin.__version__}",
        ),
        f"- integrator: RK4, dt = {step} s, frames every 0.1 s, 100 frames; trajectories simulated in chunks of "
        f"{CHUNK_SIZE} per worker task",
        "",
        "## Generation (prepare_data: simulate, render, noise, write the cache)",
        "",
        "| data set | trajectories | workers | seconds (median) | runs | trajectories/s | cached re-run (s) |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, cfg in CONFIGS.items():
        cfg = dict(cfg)
        if args.fraction != 1.0:
            cfg["n_train"] = max(1, round(cfg["n_train"] * args.fraction))
            cfg["n_test"] = max(1, round(cfg["n_test"] * args.fraction))
        total = cfg["n_train"] + cfg["n_test"]
        print(f"generating {name}: {total} trajectories", flush=True)
        runs, cached, workers = time_generation(cfg, args.repeats)
        med = statistics.median(runs)
        lines.append(
            f"| {name} | {total} | {workers} | {med:.1f} | {', '.join(f'{r:.1f}' for r in runs)} | "
            f"{total / med:.1f} | {cached:.2f} |"
        )

    lines += [
        "",
        f"## Cost per trajectory in one process (ms, median of 3 batches of {CHUNK_SIZE} trajectories)",
        "",
        "| data set | dynamics | rendering | noise + quantisation |",
        "|---|---|---|---|",
    ]
    for name, cfg in CONFIGS.items():
        split = cost_split(cfg)
        lines.append(f"| {name} | " + " | ".join(f"{split[k]:.1f}" for k in split) + " |")

    lines += [
        "",
        "## Energy drift, undamped, 10 s (48 trajectories drawn like the paper's)",
        "",
        "max over time of |E(t) - E(0)| / (g * sum of mass heights), median and max over trajectories",
        "",
        "| system | RK4 step | median | max |",
        "|---|---|---|---|",
    ]
    for n, vmax, label in ((1, 1.0, "1 link, theta_dot ~ U[-1, 1]"), (4, 0.0, "4 links, at rest")):
        for h in (step, 2 * step):
            med, mx = energy_drift(n, vmax, h)
            lines.append(f"| {label} | {h:g}{' (default)' if h == step else ''} | {med:.1e} | {mx:.1e} |")

    load = [" / ".join(f"{x:.1f}" for x in la) for la in (load_before, os.getloadavg())]
    lines.insert(
        5,  # after the title, its blank line and the three provenance lines
        f"- load average (1 / 5 / 15 min) at start: {load[0]}, at end: {load[1]} "
        "(other processes on the machine slow the figures down)",
    )
    write(args.out, lines)


if __name__ == "__main__":
    main()
