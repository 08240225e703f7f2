"""Seconds per optimizer step: ssm-ms beside the reference implementation's structure, in one run.

    python benchmarks/bench_train_step.py [--rounds 6] [--discard 2] [--steps 3] [--threads 2] [--models SSM-LL SSM-FC]
    python benchmarks/bench_train_step.py --tiny --out /tmp/x.md      # seconds, for `make test`
    python benchmarks/bench_train_step.py --device cuda --compiled --out benchmarks/results/train_step_cuda.md

The paper's simple-pendulum step: batch 40, m = 4 shooting nodes, n = 25 steps per sub-trajectory,
state 10, 24x24 images, SSM-LL with K = 32 and 1024 hidden (or SSM-FC, 3 x 512), Adam, alpha 1000.
Each implementation runs in its own worker process (the allocator setting is process-wide: the
reference's process uses glibc's defaults, ours calls ``ssm_ms.runtime.perf.configure_allocator`` as
``cli.py`` does). The workers wait on a pipe; the parent asks each in turn for ``--steps`` timed steps,
``--rounds`` times (after ``--discard`` untimed rounds), so that a shared machine's load falls on all of them
alike. Reported: median seconds per step of each, and the median over rounds of the same-round ratio
``reference / ours``.

Implementations:

* ``reference``: :mod:`benchmarks.reference_structure` (its networks, its per-step ``loss_function``,
  a dense node tensor, default allocator);
* ``ours``: ``MultipleShootingModule.shooting_loss`` + its Adam, float32 (the decoder's fused native kernels,
  ``backend="native"``, where they compile: :mod:`ssm_ms.nets.native`);
* ``ours-torch``: the same with ``ConvDecoder(backend="torch")``, the torch-only decoder;
* ``ours-bf16``: the same under ``torch.autocast(device, bfloat16)``, what ``trainer.precision: bf16-mixed``
  does (only where the device has native bfloat16 instructions; else it is reported as skipped);
* ``ours-inputs`` (``--inputs``): float32, ``f(x, u)`` with one input per step (the torque-driven pendulum's
  shape), the inputs sliced per piece as training does; its ratio to ``ours`` is the cost of inputs;
* ``ours-compiled`` (``--compiled``): float32 with ``compile_rollout`` (``reduce-overhead`` on a GPU:
  torch.compile and CUDA graphs; ``default`` on CPU); its first (compiling) steps are in the warm-up.

``--device cuda`` runs every implementation on the GPU (the loss read back each step synchronises it).

Results go to benchmarks/results/train_step.md with the machine, command and date.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

FULL = {"batch": 40, "m": 4, "n": 25, "d": 10, "k": 32, "hidden": 1024, "fc": 512, "n_train": 1000}
TINY = {"batch": 2, "m": 2, "n": 3, "d": 4, "k": 4, "hidden": 16, "fc": 16, "n_train": 4}
LABELS = {
    "reference": "reference structure (NCHW decoder, g per time step, default allocator)",
    "ours": "ssm-ms, float32",
    "ours-torch": "ssm-ms, float32, torch-only decoder (native kernels off)",
    "ours-bf16": "ssm-ms, bf16-mixed (autocast bfloat16)",
    "ours-compiled": "ssm-ms, float32, compiled rollout",
    "ours-inputs": "ssm-ms, float32, driven: f(x, u) with one input per step",
}


def build(impl: str, model: str, size: dict, device: str = "cpu"):
    """A ``step()`` closure of one implementation on a fixed random batch."""
    import torch

    torch.manual_seed(0)
    b, m, n, d = size["batch"], size["m"], size["n"], size["d"]
    gen = torch.Generator().manual_seed(1)
    y = torch.rand(b, m * n, 1, 24, 24, generator=gen).to(device)
    index = torch.arange(b)
    if impl == "reference":
        from benchmarks.reference_structure import RefDecoder, RefFullyConnected, RefLocallyLinear, RefTrainer

        f = RefLocallyLinear(d, size["k"], size["hidden"]) if model == "SSM-LL" else RefFullyConnected(d, size["fc"])
        trainer = RefTrainer(f, RefDecoder(d), size["n_train"], m, d, device=device)
        y_flat, idx = y.view(b, m * n, -1), index.numpy()
        return lambda: trainer.step(idx, y_flat)

    from ssm_ms.module import MultipleShootingModule
    from ssm_ms.nets import ConvDecoder, FullyConnectedTransition, LocallyLinearTransition, native

    inputs = 1 if impl == "ours-inputs" else 0
    f = (
        LocallyLinearTransition(d, size["k"], size["hidden"], input_dim=inputs)
        if model == "SSM-LL"
        else FullyConnectedTransition(d, (size["fc"],) * 3, input_dim=inputs)
    )
    compiled = ("reduce-overhead" if device == "cuda" else "default") if impl == "ours-compiled" else None
    kernels = "native" if device == "cpu" and native.library() is not None else "torch"
    g = ConvDecoder(d, "pendulum", backend="torch" if impl == "ours-torch" else kernels)
    module = MultipleShootingModule(f, g, d, num_trajectories=size["n_train"], n_nodes=m, compile_rollout=compiled).to(
        device
    )
    with torch.no_grad():
        module.nodes.weight.normal_(0.0, 0.1)
    opt = module.configure_optimizers()
    batch = {"index": index.to(device), "y": y}
    if inputs:
        batch["u"] = torch.randn(b, m * n, inputs, generator=gen).to(device)
    bf16 = impl == "ours-bf16"

    def step() -> float:
        opt.zero_grad()
        with torch.autocast(device, dtype=torch.bfloat16, enabled=bf16):
            fit, gap = module.shooting_loss(batch)
            loss = fit + 1000.0 * gap
        loss.backward()
        opt.step()
        return float(loss.detach())

    return step


# Warm-up steps per worker, then untimed interleaved rounds: the reference's first rounds after start ran slower
# (SSM-LL, 2 threads: 0.51 s, 0.48 s, then 0.42 s a step) whatever the warm-up steps (3, 10 and 20 tried), while
# ours ran steady, which inflated the early rounds' ratios (3.2-3.3 against 2.7 later).
WARMUP = 3


def worker(impl: str, model: str, tiny: bool, threads: int, device: str = "cpu") -> None:
    """Build, warm up, then answer ``run K`` lines with the seconds of K steps (JSON), until EOF."""
    if impl != "reference":
        from ssm_ms.runtime.perf import configure_allocator

        configure_allocator()
    import torch

    torch.set_num_threads(threads)
    step = build(impl, model, TINY if tiny else FULL, device)
    for _ in range(1 if tiny else WARMUP):
        step()
    print(json.dumps({"ready": True}), flush=True)
    for line in sys.stdin:
        k = int(line.split()[1])
        times, losses = [], []
        for _ in range(k):
            t0 = time.perf_counter()
            losses.append(step())
            times.append(time.perf_counter() - t0)
        print(json.dumps({"times": times, "loss": losses[-1]}), flush=True)


class Worker:
    """One implementation's worker process (``env``: variables added to its environment)."""

    def __init__(
        self, impl: str, model: str, tiny: bool, threads: int, device: str = "cpu", env: dict[str, str] | None = None
    ):
        self.impl = impl
        cmd = [
            sys.executable,
            str(Path(__file__).resolve()),
            "--worker",
            impl,
            model,
            "--threads",
            str(threads),
            "--device",
            device,
        ]
        self.proc = subprocess.Popen(
            cmd + (["--tiny"] if tiny else []),
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            cwd=ROOT,
            env={**os.environ, **(env or {})},
        )
        self._read()

    def _read(self) -> dict:
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"benchmark worker {self.impl!r} died (exit code {self.proc.wait()})")
        return json.loads(line)

    def start(self, k: int) -> None:
        """Ask for ``k`` timed steps; :meth:`times` reads them (several workers can run at once)."""
        self.proc.stdin.write(f"run {k}\n")
        self.proc.stdin.flush()

    def times(self) -> list[float]:
        return self._read()["times"]

    def run(self, k: int) -> list[float]:
        self.start(k)
        return self.times()

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait()


def bf16_native(device: str = "cpu") -> bool:
    from ssm_ms.runtime.perf import bf16_support

    return bf16_support(device)[0]


def measure(
    model: str,
    impls: list[str],
    rounds: int,
    steps: int,
    threads: int,
    tiny: bool,
    device: str = "cpu",
    discard: int = 2,
) -> dict:
    workers = [Worker(impl, model, tiny, threads, device) for impl in impls]
    times: dict[str, list[float]] = {impl: [] for impl in impls}
    per_round: dict[str, list[float]] = {impl: [] for impl in impls}
    try:
        for r in range(-discard, rounds):  # the first `discard` rounds are not kept
            order = workers if r % 2 == 0 else workers[::-1]  # alternate who goes first
            for w in order:
                ts = w.run(steps)
                if r >= 0:
                    times[w.impl] += ts
                    per_round[w.impl].append(statistics.median(ts))
            if r >= 0:
                print(
                    f"{model} round {r + 1}: " + "  ".join(f"{k} {v[-1]:.3f}" for k, v in per_round.items()), flush=True
                )
    finally:
        for w in workers:
            w.close()
    return {"times": times, "per_round": per_round}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=6)
    parser.add_argument("--steps", type=int, default=3, help="timed steps per implementation per round")
    parser.add_argument("--discard", type=int, default=2, help="untimed interleaved rounds before the timed ones")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--models", nargs="+", default=["SSM-LL", "SSM-FC"], choices=["SSM-LL", "SSM-FC"])
    parser.add_argument("--no-bf16", action="store_true", help="leave out the bf16-mixed variant")
    parser.add_argument("--compiled", action="store_true", help="add the compiled-rollout variant")
    parser.add_argument("--inputs", action="store_true", help="add the driven model f(x, u), one input per step")
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    parser.add_argument("--tiny", action="store_true", help="tiny sizes, to check that the script runs")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "train_step.md"))
    parser.add_argument("--worker", nargs=2, metavar=("IMPL", "MODEL"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        worker(args.worker[0], args.worker[1], args.tiny, args.threads, args.device)
        return
    import torch

    from benchmarks.report import provenance, write
    from ssm_ms.runtime.machine import CpuWatch, quiet_note
    from ssm_ms.training.shooting import compile_unavailable_reason

    if args.device == "cuda" and not torch.cuda.is_available():  # before any worker starts (and dies)
        parser.error("--device cuda: torch sees no CUDA device here; run on a machine with a GPU or leave --device out")
    if args.compiled:
        why = compile_unavailable_reason("reduce-overhead" if args.device == "cuda" else "default")
        if why is not None:
            parser.error(f"--compiled: {why}")

    impls = ["reference", "ours", "ours-torch"]
    bf16_note = ""
    if not args.no_bf16:
        if bf16_native(args.device):
            impls.append("ours-bf16")
        else:
            bf16_note = f"bf16-mixed not measured: this {args.device} has no native bfloat16 instructions"
    if args.compiled:
        impls.append("ours-compiled")
    if args.inputs:
        impls.append("ours-inputs")
    watch = CpuWatch()
    discard = 0 if args.tiny else args.discard
    results = {
        model: measure(model, impls, args.rounds, args.steps, args.threads, args.tiny, args.device, discard)
        for model in args.models
    }
    others = watch.others()  # the workers have exited
    size = TINY if args.tiny else FULL
    lines = [
        "# Training step: ssm-ms beside the reference implementation's structure, one run, interleaved",
        "",
        *provenance(
            "benchmarks/bench_train_step.py",
            argv,
            f"Python {sys.version.split()[0]}, {args.threads} torch threads per worker, device {args.device}; "
            f"{quiet_note(others)} (one benchmark worker runs at a time)",
        ),
        f"- set-up: {'TINY sizes (smoke test) ' if args.tiny else ''}batch {size['batch']}, m {size['m']}, "
        f"n {size['n']}, state {size['d']}, SSM-LL K {size['k']} hidden {size['hidden']}, SSM-FC 3 x {size['fc']}, "
        "24x24 images, Adam, loss fit + 1000 gap",
        f"- {args.rounds} rounds; in each, every implementation (its own process, waiting while the others run) "
        f"makes {args.steps} timed steps after {1 if args.tiny else WARMUP} warm-up steps and {discard} untimed "
        "rounds; seconds per optimizer step (forward, backward, Adam)",
        "- ratio = reference / this implementation, per round (medians of that round), median over rounds",
    ]
    if bf16_note:
        lines.append(f"- {bf16_note}")
    lines += [
        "",
        "| model | implementation | median s / step | min s | ratio reference / this (per-round median) | "
        "per-round ratios |",
        "|---|---|---:|---:|---:|---|",
    ]
    for model, res in results.items():
        ref = res["per_round"]["reference"]
        for impl in impls:
            ts = res["times"][impl]
            ratios = [a / b for a, b in zip(ref, res["per_round"][impl])]
            lines.append(
                f"| {model} | {LABELS[impl]} | {statistics.median(ts):.3f} | {min(ts):.3f} | "
                f"{statistics.median(ratios):.2f} | {', '.join(f'{r:.2f}' for r in ratios)} |"
            )
    if args.inputs:
        lines.append("")
        for model, res in results.items():
            rel = [a / b for a, b in zip(res["per_round"]["ours-inputs"], res["per_round"]["ours"])]
            lines.append(
                f"- {model}, the driven model's step over the same model without inputs (per-round medians): "
                f"median {statistics.median(rel):.3f} ({', '.join(f'{r:.3f}' for r in rel)})"
            )
    write(args.out, lines)


if __name__ == "__main__":
    main()
