"""How fast a learned model simulates a benchmark's free run: 10^5 steps from the inputs alone, ssm-ms's SSM (its
protocol's chunked rollout, :func:`ssm_ms.inference.simulation.free_run`) beside deepSI's SUBNET of the same results
file where bench_deepsi.py saved one (``--deepsi``), in one run, as a ratio. Writes
benchmarks/results/simulation_<experiment>.md.

    python benchmarks/bench_simulation.py --checkpoint runs/silverbox/version_0/checkpoints/best.ckpt [--steps 100000]

The inputs: the benchmark's test recordings' inputs repeated to ``--steps`` (normalised as the model was trained);
the state: the mean shooting node (zero for a model whose nodes come from its node encoder: the speed does not depend on
it). Each timing is the median of ``--rounds`` runs after one warm-up, 2 torch threads.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import torch  # noqa: E402

from benchmarks.report import provenance, write  # noqa: E402
from ssm_ms.inference.simulation import free_run, model_name  # noqa: E402
from ssm_ms.loading import load_ssm  # noqa: E402


def timed(fn, rounds: int) -> float:
    """The median wall time of ``rounds`` calls of ``fn`` after one warm-up."""
    fn()
    times = []
    for _ in range(rounds):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--checkpoint", required=True, help="an SSM checkpoint of a benchmark (its best.ckpt)")
    parser.add_argument(
        "--deepsi",
        default=None,
        help="a SUBNET bench_deepsi.py --benchmarks saved (runs/bench_deepsi/<name>-subnet-best.pt)",
    )
    parser.add_argument("--steps", type=int, default=100_000)
    parser.add_argument("--chunk", type=int, default=10_000)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--out", default=None, help="default benchmarks/results/simulation_<experiment>.md")
    args = parser.parse_args(argv)
    if args.steps < 2 or args.rounds < 1:
        parser.error("--steps must be >= 2 and --rounds >= 1")
    torch.set_num_threads(2)
    ssm, _ = load_ssm(args.checkpoint)
    name = (ssm.data_state or {}).get("name", "benchmark")
    generator = torch.Generator().manual_seed(0)
    u = torch.randn(1, args.steps, ssm.input_dim, generator=generator) if ssm.input_dim else None
    if ssm.nodes is not None:
        x = ssm.nodes.weight.detach().view(-1, ssm.state_dim).mean(0, keepdim=True)
    else:  # amortised nodes: no free node to start from
        x = torch.zeros(1, ssm.state_dim, dtype=ssm.alpha.dtype)

    def ours() -> None:
        with torch.no_grad():
            free_run(ssm.f, ssm.g, x, args.steps, u, args.chunk, ssm.hparams.decode_chunk)

    rows = [(f"ssm-ms {model_name(ssm)}", timed(ours, args.rounds))]
    if args.deepsi:
        model = torch.load(args.deepsi, weights_only=False).eval()
        k = max(model.na, model.nb)
        past_u = torch.zeros(1, k, ssm.input_dim)
        past_y = torch.zeros(1, k, 1)

        def theirs() -> None:
            with torch.no_grad():
                model(past_u, past_y, u)

        rows.append(("deepSI SUBNET", timed(theirs, args.rounds)))
    lines = [
        f"# A free run of {args.steps:,} steps: {name}",
        "",
        *provenance("benchmarks/bench_simulation.py", argv),
        f"- Model: `{args.checkpoint}`; inputs: N(0, 1) in the model's units; chunks of {args.chunk}; median of "
        f"{args.rounds} runs after a warm-up; 2 torch threads.",
        "",
        "| model | seconds | steps per second | / ssm-ms |",
        "|---|---:|---:|---:|",
    ]
    for label, seconds in rows:
        lines.append(f"| {label} | {seconds:.3f} | {args.steps / seconds:,.0f} | {seconds / rows[0][1]:.2f} |")
    write(args.out or ROOT / "benchmarks" / "results" / f"simulation_{name}.md", lines)


if __name__ == "__main__":
    main()
