"""SSM-LL's rollout with its first beta layer as ``nn.Linear`` and as ``NarrowLinear``, in one process.

    python benchmarks/bench_narrow_linear.py [--rounds 5] [--threads 2]
    python benchmarks/bench_narrow_linear.py --tiny --out /tmp/x.md      # seconds, for `make test`

Times what a training step spends in ``f``: a rollout of ``steps`` steps of ``LocallyLinearTransition`` (K = 32,
1024 hidden) from ``rows`` states, then the backward of a squared mean over every step's state. The two variants
hold the same weights; each round times both, in alternating order; the ratio is ``nn.Linear / NarrowLinear``
(seconds), per round, median over rounds. The cases are the paper's shapes: Lorenz (state 3; 40 pieces of T
steps, 50 steps per node: 800 rows at T = 1000, 8000 at T = 10,000), the simple pendulum (state 10) and the
quadruple pendulum (state 40) (40 pieces x 4 nodes, 25 steps), and widths between, which place the threshold
``NARROW_MAX`` under which ``LocallyLinearTransition`` uses ``NarrowLinear`` (``ssm_ms/nets/transition.py``).
Writes benchmarks/results/narrow_linear.md with the machine, command and date.
"""

from __future__ import annotations

import argparse
import copy
import statistics
import sys
import time
from pathlib import Path

import torch
from torch import nn

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

# (label, state width, rows, rollout steps)
CASES = [
    ("Lorenz T = 10,000", 3, 8000, 50),
    ("Lorenz T = 1000", 3, 800, 50),
    ("state 3, pendulum rows", 3, 160, 25),
    ("simple pendulum", 10, 160, 25),
    ("state 12", 12, 160, 25),
    ("state 16", 16, 160, 25),
    ("state 24", 24, 160, 25),
    ("quadruple pendulum", 40, 160, 25),
    ("state 10, 800 rows", 10, 800, 50),
    ("state 16, 800 rows", 16, 800, 50),
    ("state 40, 800 rows", 40, 800, 50),
]
TINY = [("tiny", 3, 8, 3)]


def with_first_layer(f: nn.Module, cls: type[nn.Linear]) -> nn.Module:
    """A copy of ``f`` whose first beta layer is a ``cls`` holding the same weights."""
    f = copy.deepcopy(f)
    layer = cls(f.beta[0].in_features, f.beta[0].out_features)
    layer.load_state_dict(f.beta[0].state_dict())
    f.beta[0] = layer
    return f


def rollout_seconds(f: nn.Module, x0: torch.Tensor, steps: int, repeats: int) -> float:
    """Mean seconds of ``repeats`` rollouts of ``steps`` steps from ``x0`` and their backward."""
    start = time.perf_counter()
    for _ in range(repeats):
        x, states = x0, []
        for _ in range(steps):
            x = f(x)
            states.append(x)
        torch.stack(states).pow(2).mean().backward()
    return (time.perf_counter() - start) / repeats


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--tiny", action="store_true", help="a tiny case, to check that the script runs")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "narrow_linear.md"))
    args = parser.parse_args(argv)

    from benchmarks.report import provenance, write
    from ssm_ms.nets.linear import NarrowLinear
    from ssm_ms.nets.transition import NARROW_MAX, LocallyLinearTransition
    from ssm_ms.runtime.machine import CpuWatch, quiet_note
    from ssm_ms.runtime.perf import configure_allocator

    configure_allocator()  # as cli.py does
    torch.set_num_threads(args.threads)
    hidden, k = (16, 4) if args.tiny else (1024, 32)
    rows_out = []
    watch = CpuWatch()
    for label, d, rows, steps in TINY if args.tiny else CASES:
        torch.manual_seed(0)
        f = LocallyLinearTransition(d, k, hidden)
        x0 = torch.randn(rows, d, requires_grad=True)
        variants = {
            name: (with_first_layer(f, cls), x0)
            for name, cls in (("nn.Linear", nn.Linear), ("NarrowLinear", NarrowLinear))
        }
        repeats = 1 if rows * steps >= 100_000 else 5
        times: dict[str, list[float]] = {name: [] for name in variants}
        for f, x0 in variants.values():  # warm-up
            rollout_seconds(f, x0, steps, 1)
        for r in range(args.rounds):
            for name in variants if r % 2 == 0 else list(variants)[::-1]:
                f, x0 = variants[name]
                times[name].append(rollout_seconds(f, x0, steps, repeats))
        ratios = [a / b for a, b in zip(times["nn.Linear"], times["NarrowLinear"])]
        med = {name: statistics.median(t) * 1e3 for name, t in times.items()}
        rows_out.append(
            f"| {label} | {d} | {rows} | {steps} | {med['nn.Linear']:.1f} | {med['NarrowLinear']:.1f} | "
            f"{statistics.median(ratios):.2f} | {'NarrowLinear' if d <= NARROW_MAX else 'nn.Linear'} |"
        )
        print(rows_out[-1], flush=True)
    others = watch.others()

    lines = [
        "# SSM-LL's first beta layer: `nn.Linear` or `NarrowLinear` (a rollout and its backward)",
        "",
        *provenance(
            "benchmarks/bench_narrow_linear.py",
            argv,
            f"{args.threads} threads; {quiet_note(others)}",
        ),
        f"- {'TINY sizes (smoke test): ' if args.tiny else ''}K = {k}, {hidden} hidden units; {args.rounds} rounds, each timing both variants (same weights) in "
        "alternating order; ratio = nn.Linear / NarrowLinear (seconds), per round, median over rounds",
        f"- shipped: `NarrowLinear` where the layer's input width (state + inputs) is at most {NARROW_MAX}",
        "",
        "| case | input width | rows | steps | nn.Linear (ms) | NarrowLinear (ms) | ratio | shipped |",
        "|---|---:|---:|---:|---:|---:|---:|---|",
        *rows_out,
    ]
    write(args.out, lines)


if __name__ == "__main__":
    main()
