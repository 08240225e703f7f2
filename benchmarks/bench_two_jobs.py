"""Two torch jobs on the same cores: how much each slows the other, and what the OpenMP settings change.

    python benchmarks/bench_two_jobs.py [--rounds 4] [--steps 8] [--discard 1]
    python benchmarks/bench_two_jobs.py --tiny --out /tmp/x.md      # seconds, for `make test`

Sessions on the 2-core machines saw a second torch process (a test beside a training run, `make test` beside an
encoder fit) slow both far more than twice: an encoder epoch took 66 s instead of 11, a 20-s test 339 s. torch's
CPU wheel runs its threads on GNU OpenMP, whose idle threads spin before they sleep; with two processes of
``torch.get_num_threads()`` threads each on as many cores, each one's spinning holds a core the other needs.

Each variant is one or two worker processes of ``benchmarks/bench_train_step.py`` (ssm-ms's paper-size SSM-LL
pendulum step: batch 40, m = 4, n = 25, 24x24 images, Adam), started once and kept waiting on a pipe. In each round
every variant in turn runs ``--steps`` timed steps in each of its workers at the same time (the other variants'
workers wait, idle). Reported per variant: the median seconds per step of its jobs, its throughput (steps per
second, all its jobs together), and, per round, that throughput over the lone 2-thread job's of the same round
(median over rounds).

Results go to benchmarks/results/two_jobs.md with the machine, command and date.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.bench_train_step import FULL, TINY, WARMUP, Worker  # noqa: E402

# (label, threads per job, number of jobs, environment added)
VARIANTS = [
    ("one job, 2 threads", 2, 1, {}),
    ("one job, 2 threads, OMP_WAIT_POLICY=PASSIVE", 2, 1, {"OMP_WAIT_POLICY": "PASSIVE"}),
    ("two jobs, 2 threads each", 2, 2, {}),
    ("two jobs, 2 threads each, OMP_WAIT_POLICY=PASSIVE", 2, 2, {"OMP_WAIT_POLICY": "PASSIVE"}),
    ("two jobs, 1 thread each", 1, 2, {}),
]


def measure(rounds: int, steps: int, discard: int, tiny: bool) -> dict[str, dict[str, list[float]]]:
    """Per variant: ``times`` (every timed step of every job) and ``throughput`` (steps per second, per round)."""
    workers = {
        label: [Worker("ours", "SSM-LL", tiny, threads, env=env) for _ in range(jobs)]
        for label, threads, jobs, env in VARIANTS
    }
    out = {label: {"times": [], "throughput": []} for label in workers}
    try:
        for r in range(-discard, rounds):
            order = list(workers) if r % 2 == 0 else list(workers)[::-1]
            for label in order:
                start = time.perf_counter()
                for w in workers[label]:
                    w.start(steps)
                times = [w.times() for w in workers[label]]
                wall = time.perf_counter() - start
                if r >= 0:
                    out[label]["times"] += [t for ts in times for t in ts]
                    out[label]["throughput"].append(steps * len(times) / wall)
            if r >= 0:
                print(
                    f"round {r + 1}: " + "  ".join(f"{k}: {v['throughput'][-1]:.2f}/s" for k, v in out.items()),
                    flush=True,
                )
    finally:
        for ws in workers.values():
            for w in ws:
                w.close()
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--steps", type=int, default=8, help="timed steps per job per round")
    parser.add_argument("--discard", type=int, default=1, help="untimed rounds before the timed ones")
    parser.add_argument("--tiny", action="store_true", help="tiny sizes, to check that the script runs")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "two_jobs.md"))
    args = parser.parse_args(argv)
    small = [f"--{k} {getattr(args, k)}" for k in ("rounds", "steps") if getattr(args, k) < 1]
    if small or args.discard < 0:
        parser.error(
            f"{', '.join(small) or f'--discard {args.discard}'}: give at least 1 round and 1 step "
            "(and 0 or more untimed rounds)"
        )

    from benchmarks.report import provenance, write
    from ssm_ms.runtime.machine import CpuWatch, quiet_note

    watch = CpuWatch()
    discard = 0 if args.tiny else args.discard
    res = measure(args.rounds, args.steps, discard, args.tiny)
    others = watch.others()
    size = TINY if args.tiny else FULL
    alone = res[VARIANTS[0][0]]["throughput"]
    lines = [
        "# Two torch jobs on the same cores",
        "",
        *provenance("benchmarks/bench_two_jobs.py", argv, f"Python {sys.version.split()[0]}; {quiet_note(others)}"),
        f"- job: {'TINY sizes (smoke test) ' if args.tiny else ''}the SSM-LL training step of "
        f"benchmarks/bench_train_step.py (batch {size['batch']}, m {size['m']}, n {size['n']}, state {size['d']}, "
        f"K {size['k']}, hidden {size['hidden']}), {WARMUP} warm-up steps per job",
        f"- {args.rounds} rounds after {discard} untimed; in each, every variant in turn runs {args.steps} timed steps "
        "in each of its jobs at once; throughput = steps of all its jobs / wall seconds of the round",
        "",
        "| variant | median s / step (each job) | throughput, steps / s (all jobs) | throughput / one 2-thread job's "
        "(per-round median) |",
        "|---|---:|---:|---:|",
    ]
    for label, *_ in VARIANTS:
        ratios = [a / b for a, b in zip(res[label]["throughput"], alone)]
        lines.append(
            f"| {label} | {statistics.median(res[label]['times']):.3f} | "
            f"{statistics.median(res[label]['throughput']):.2f} | {statistics.median(ratios):.2f} |"
        )
    write(args.out, lines)


if __name__ == "__main__":
    main()
