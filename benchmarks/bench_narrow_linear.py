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
A second table times the weight gradient of a layer from 3 inputs alone, in the two forms autograd takes for them.
Writes benchmarks/results/narrow_linear.md, a row per machine (this run's replace this machine's earlier ones), with
the machine, command and date of each machine's run.
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


def rollouts(f: nn.Module, x0: torch.Tensor, steps: int, repeats: int) -> None:
    """``repeats`` rollouts of ``steps`` steps from ``x0``, each with its backward."""
    for _ in range(repeats):
        x, states = x0, []
        for _ in range(steps):
            x = f(x)
            states.append(x)
        torch.stack(states).pow(2).mean().backward()


def weight_gradients(dy: torch.Tensor, x: torch.Tensor, as_narrow: bool) -> None:
    """Ten weight gradients ``dy^T x`` as ``nn.Linear``'s autograd forms them, or as ``(x^T dy)^T`` (``NarrowLinear``)."""
    for _ in range(10):
        (x.t() @ dy).t() if as_narrow else dy.t() @ x


def interleaved(variants: dict, rounds: int, run) -> tuple[dict[str, float], float]:
    """Median seconds of ``run(*variant)`` per variant over ``rounds`` rounds (order alternating), and the median
    per-round ratio first / second variant."""
    times: dict[str, list[float]] = {name: [] for name in variants}
    for value in variants.values():  # warm-up
        run(*value)
    for r in range(rounds):
        for name in variants if r % 2 == 0 else list(variants)[::-1]:
            start = time.perf_counter()
            run(*variants[name])
            times[name].append(time.perf_counter() - start)
    first, second = times.values()
    return {name: statistics.median(t) for name, t in times.items()}, statistics.median(
        a / b for a, b in zip(first, second)
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--tiny", action="store_true", help="a tiny case, to check that the script runs")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "narrow_linear.md"))
    args = parser.parse_args(argv)
    if args.rounds < 1 or args.threads < 1:
        parser.error(f"--rounds and --threads must be at least 1, got {args.rounds} and {args.threads}")

    from benchmarks.report import provenance, write_by_machine
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
        repeats = 1 if rows * steps >= 100_000 else 5
        variants = {
            name: (with_first_layer(f, cls), x0, steps, repeats)
            for name, cls in (("nn.Linear", nn.Linear), ("NarrowLinear", NarrowLinear))
        }
        med, ratio = interleaved(variants, args.rounds, rollouts)
        med = {name: t / repeats * 1e3 for name, t in med.items()}
        rows_out.append(
            f"| {label} | {d} | {rows} | {steps} | {med['nn.Linear']:.1f} | {med['NarrowLinear']:.1f} | "
            f"{ratio:.2f} | {'NarrowLinear' if d <= NARROW_MAX else 'nn.Linear'} |"
        )
        print(rows_out[-1], flush=True)
    products = []  # the weight gradient of a [rows, 3] -> [rows, hidden] layer alone, as each variant forms it
    for rows in (8,) if args.tiny else (800, 8000):
        torch.manual_seed(0)
        x, dy = torch.randn(rows, 3), torch.randn(rows, hidden)
        forms = {"dy^T x": (dy, x, False), "(x^T dy)^T": (dy, x, True)}
        med, ratio = interleaved(forms, args.rounds * 4, weight_gradients)
        products.append(f"| {rows} | {med['dy^T x'] * 100:.3f} | {med['(x^T dy)^T'] * 100:.3f} | {ratio:.2f} |")
        print(products[-1], flush=True)
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
        "",
        f"The weight gradient alone of a layer from 3 to {hidden} (no rollout): `dy^T x` (`[{hidden}, rows] @ [rows, 3]`, "
        "as autograd forms it for `nn.Linear`) and `(x^T dy)^T` (`[3, rows] @ [rows, "
        f"{hidden}]`, for `NarrowLinear`), 10 products per timing, {args.rounds * 4} rounds:",
        "",
        "| rows | dy^T x (ms) | (x^T dy)^T (ms) | ratio |",
        "|---:|---:|---:|---:|",
        *products,
    ]
    write_by_machine(args.out, lines)


if __name__ == "__main__":
    main()
