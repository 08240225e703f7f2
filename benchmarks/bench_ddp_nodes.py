"""What one training step communicates for the node table under DDP, measured on 2 CPU processes (gloo).

dense  (node_optimizer: dense): the table's gradient [N, m*d] goes through DDP's all-reduce every step.
sparse (node_optimizer: sparse): the ranks all-gather only the batch's (index, row gradient)
        (ssm_ms.training.distributed.all_gather_rows), B_global x m*d numbers.

    python benchmarks/bench_ddp_nodes.py [--reps 10]   -> benchmarks/results/ddp_nodes.md
"""

from __future__ import annotations

import argparse
import os
import queue as queue_module
import statistics
import sys
import time
from pathlib import Path

import torch
import torch.distributed as dist
import torch.multiprocessing as mp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.report import provenance  # noqa: E402
from ssm_ms.training.distributed import all_gather_rows  # noqa: E402

# (name, trajectories N, m * d, global batch B): the paper-size tables
CASES = [
    ("simple pendulum (1000 x 4 nodes x 10)", 1000, 40, 40),
    ("Lorenz T=1000 CPU twin (1000 pieces x 20 x 3)", 1000, 60, 40),
    ("Lorenz T=10 (1000 x 10,000 / 10 pieces x 1 x 3)", 1_000_000, 3, 40),
    ("Moving MNIST (100,000 x 2 x 100)", 100_000, 200, 50),
]


def _worker(rank: int, world: int, reps: int, port: int, queue) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    torch.set_num_threads(1)
    dist.init_process_group("gloo", rank=rank, world_size=world)
    results = []
    for name, n, width, batch in CASES:
        table_grad = torch.randn(n, width)
        local = batch // world
        index = torch.randint(0, n, (local,))
        rows = torch.randn(local, width)
        dense, sparse = [], []
        for _ in range(reps):
            dist.barrier()
            t = time.perf_counter()
            dist.all_reduce(table_grad)
            dense.append(time.perf_counter() - t)
            dist.barrier()
            t = time.perf_counter()
            all_gather_rows(index, rows)
            sparse.append(time.perf_counter() - t)
        results.append((name, n, width, batch, statistics.median(dense), statistics.median(sparse)))
    if rank == 0:
        queue.put(results)
    dist.destroy_process_group()


def gather_results(procs: list, queue, poll: float = 1.0) -> list:
    """Rank 0's results from ``queue``, then every rank joined. A rank that exits without them (an error, printed
    above by the rank itself; its peer is then stuck in a collective) ends the run at once: the other ranks are
    terminated and a ``RuntimeError`` names the exit codes (``queue.get()`` alone would wait forever)."""
    while True:
        try:
            results = queue.get(timeout=poll)
            break
        except queue_module.Empty:
            failed = [(r, p.exitcode) for r, p in enumerate(procs) if p.exitcode not in (None, 0)]
            if failed or all(p.exitcode is not None for p in procs):
                try:  # rank 0 may have put its results just before it exited
                    results = queue.get(timeout=poll)
                    break
                except queue_module.Empty:
                    pass
                for p in procs:
                    if p.is_alive():
                        p.terminate()
                for p in procs:
                    p.join()
                said = ", ".join(f"rank {r} exited with code {c}" for r, c in failed) or "every rank exited"
                raise RuntimeError(f"bench_ddp_nodes: {said} without the results (see its error above)") from None
    for p in procs:
        p.join()
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reps", type=int, default=10)
    parser.add_argument("--out", default="benchmarks/results/ddp_nodes.md")
    args = parser.parse_args()
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    port = 29500 + os.getpid() % 1000
    procs = [ctx.Process(target=_worker, args=(r, 2, args.reps, port, queue)) for r in range(2)]
    for p in procs:
        p.start()
    results = gather_results(procs, queue)
    lines = [
        "# Node-table communication per step under DDP (2 CPU processes, gloo)",
        "",
        *provenance("benchmarks/bench_ddp_nodes.py", None),
        f"- Each figure: the median of {args.reps} repetitions.",
        "",
        "dense: all-reduce of the table's gradient (what DDP does with `node_optimizer: dense`); sparse: all-gather "
        "of the batch's indices and row gradients (`node_optimizer: sparse`). float32.",
        "",
        "| table | N x m*d | global batch | dense all-reduce: MB, ms | sparse all-gather: MB, ms |",
        "|---|---|---|---|---|",
    ]
    for name, n, width, batch, dense, sparse in results:
        lines.append(
            f"| {name} | {n:,} x {width} | {batch} | {n * width * 4 / 1e6:.3g} MB, {dense * 1e3:.3g} ms | "
            f"{batch * (width * 4 + 8) / 1e6:.2g} MB, {sparse * 1e3:.3g} ms |"
        )
    text = "\n".join(lines) + "\n"
    Path(args.out).write_text(text)
    print(text)


if __name__ == "__main__":
    main()
