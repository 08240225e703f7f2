"""Seconds per optimizer step of the paper's simple-pendulum configurations (batch 40, m = 4, n = 25).

    python benchmarks/bench_train_step.py [--steps 20] [--repeats 3] [--threads 2]

Each variant runs in its own process (the allocator setting is process-wide), ``--repeats`` times;
the figure is the median over all timed steps of all repeats. Variants:

* ``ours``: ``multiple_shooting_loss`` (all sub-trajectories rolled out at once, one call of g),
  with ``ssm_ms.perf.configure_allocator`` as ``cli.py`` does;
* ``ours, decoder in NCHW layout``: ``ConvDecoder(channels_last=False)``;
* ``ours, default allocator``: the same code without it;
* ``ours, decode_chunk=N``: decoding in chunks of N states;
* ``per-step decoding``: the reference implementation's structure (g called once per time step on
  the B*m states, loss accumulated per step), same networks, with the allocator setting.

Results go to benchmarks/results/train_step.md with the machine, command and date.
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
from datetime import datetime, timezone
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ssm_ms.machine import cpu_model  # noqa: E402


def worker(model: str, variant: str, steps: int, threads: int) -> dict:
    if variant != "default-allocator":
        from ssm_ms.perf import configure_allocator

        configure_allocator()
    import torch
    import torch.nn.functional as F

    from ssm_ms.nets import ConvDecoder, FullyConnectedTransition, LocallyLinearTransition
    from ssm_ms.shooting import multiple_shooting_loss

    torch.set_num_threads(threads)
    torch.manual_seed(0)
    d, b, m, n = 10, 40, 4, 25
    f = LocallyLinearTransition(d) if model == "SSM-LL" else FullyConnectedTransition(d)
    g = ConvDecoder(d, "pendulum", channels_last=variant != "nchw")
    nodes = torch.nn.Parameter(0.1 * torch.randn(b, m, d))
    y = torch.rand(b, m * n, 1, 24, 24)
    opt = torch.optim.Adam([*f.parameters(), *g.parameters(), nodes], lr=1e-3)
    chunk = int(variant.split("=")[1]) if variant.startswith("chunk=") else None

    def per_step_loss():
        x = nodes.reshape(b * m, d)
        yw = y.view(b, m, n, 1, 24, 24).reshape(b * m, n, 1, 24, 24)
        fit = 0.0
        for k in range(n):
            fit = fit + F.mse_loss(g(x), yw[:, k])
            x = f(x)
        gap = (nodes[:, 1:] - x.view(b, m, d)[:, :-1]).pow(2).mean()
        return fit / n, gap

    def step():
        opt.zero_grad()
        if variant == "per-step":
            fit, gap = per_step_loss()
        else:
            fit, gap = multiple_shooting_loss(f, g, nodes, y, decode_chunk=chunk)
        (fit + 1000.0 * gap).backward()
        opt.step()

    for _ in range(5):
        step()
    faults0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    times = []
    for _ in range(steps):
        t0 = time.perf_counter()
        step()
        times.append(time.perf_counter() - t0)
    faults = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults0) / steps
    return {"times": times, "faults_per_step": faults}


VARIANTS = [
    ("ours", "ours"),
    ("nchw", "ours, decoder in NCHW layout"),
    ("default-allocator", "ours, default allocator"),
    ("chunk=1000", "ours, decode_chunk=1000"),
    ("per-step", "per-step decoding (reference structure)"),
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--models", nargs="+", default=["SSM-LL", "SSM-FC"])
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "train_step.md"))
    parser.add_argument("--worker", nargs=2, metavar=("MODEL", "VARIANT"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(worker(args.worker[0], args.worker[1], args.steps, args.threads)))
        return
    import torch

    rows = []
    for model in args.models:
        for key, label in VARIANTS:
            times, faults = [], []
            for _ in range(args.repeats):
                out = subprocess.run(
                    [sys.executable, __file__, "--worker", model, key, "--steps", str(args.steps),
                     "--threads", str(args.threads)],
                    check=True, capture_output=True, text=True, cwd=ROOT,
                )
                res = json.loads(out.stdout.strip().splitlines()[-1])
                times += res["times"]
                faults.append(res["faults_per_step"])
            med = statistics.median(times)
            rows.append((model, label, med, min(times), max(times), statistics.median(faults)))
            print(f"{model:7s} {label:42s} median {med:.3f} s  min {min(times):.3f}  max {max(times):.3f}  "
                  f"faults/step {statistics.median(faults):,.0f}", flush=True)
    load = os.getloadavg()
    lines = [
        "# Training step: paper simple-pendulum configuration (batch 40, m = 4, n = 25, 24x24 frames)",
        "",
        f"- machine: {os.cpu_count()} cores, {cpu_model()}, Python {platform.python_version()}, torch {torch.__version__}, {args.threads} threads",
        f"- command: `python benchmarks/bench_train_step.py {' '.join(sys.argv[1:])}`".replace("  ", " "),
        f"- date: {datetime.now(timezone.utc).isoformat(timespec='seconds')}",
        f"- load average at the end (1, 5, 15 min): {load[0]:.2f}, {load[1]:.2f}, {load[2]:.2f}",
        f"- {args.repeats} processes x {args.steps} timed steps per variant (after 5 warm-up steps); "
        "seconds per optimizer step (forward, backward, Adam)",
        "- paper's reference code on this machine (2 threads), as quoted in the issue: SSM-LL 0.64 s, SSM-FC 0.78 s",
        "",
        "| model | variant | median s | min s | max s | minor page faults / step | median vs ours |",
        "|---|---|---|---|---|---|---|",
    ]
    ours = {m: med for m, label, med, *_ in rows if label == "ours"}
    for model, label, med, lo, hi, faults in rows:
        lines.append(f"| {model} | {label} | {med:.3f} | {lo:.3f} | {hi:.3f} | {faults:,.0f} | {med / ours[model]:.2f} |")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
