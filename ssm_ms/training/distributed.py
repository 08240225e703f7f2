"""What the node table needs under data parallelism (Lightning DDP), as small functions.

Design. The shooting nodes (and the augmented-Lagrangian multipliers) are a table with one row per
training trajectory, replicated on every rank. A step touches only the rows of its batch, so the
table is kept out of DDP's gradient all-reduce: each rank computes the gradient of its own batch
rows, the ranks all-gather ``(index, rows)`` (``B_global x m x d`` numbers instead of the whole
``N x m x d`` table), and every rank applies the same update to the same rows. The tables stay
identical on every rank without ever being communicated whole. (The f and g parameters go through
DDP's ordinary all-reduce.)

A global batch of ``B`` trajectories is split into contiguous shards, one per rank (sizes differ by
at most one in a last, partial batch); each rank's loss is weighted by ``n_rank * W / B`` so that
DDP's average of the ranks' gradients is the gradient of the mean over the global batch, as on one
device.
"""

from __future__ import annotations

import torch
import torch.distributed as dist


def world_size() -> int:
    """Number of processes in the default process group (1 without one)."""
    return dist.get_world_size() if dist.is_available() and dist.is_initialized() else 1


def all_gather_rows(*tensors: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Concatenate, in rank order, every rank's tensors (same trailing shapes, any first dimension).

    Without a process group, returns the tensors unchanged.
    """
    w = world_size()
    if w == 1:
        return tensors
    n = torch.tensor([len(tensors[0])], device=tensors[0].device)
    counts = [torch.zeros_like(n) for _ in range(w)]
    dist.all_gather(counts, n)
    counts_ = [int(c) for c in counts]
    most = max(counts_)
    out = []
    for t in tensors:
        padded = t.new_zeros((most, *t.shape[1:]))
        padded[: len(t)] = t
        parts = [torch.empty_like(padded) for _ in range(w)]
        dist.all_gather(parts, padded.contiguous())
        out.append(torch.cat([p[:c] for p, c in zip(parts, counts_)]))
    return tuple(out)


def shard_weight(n_local: int, device: torch.device | None = None) -> float:
    """``n_local * W / n_global``: the factor that makes DDP's gradient average equal the gradient of
    the mean over the global batch when the ranks hold different numbers of trajectories (1 when they
    hold the same number, and without a process group)."""
    w = world_size()
    if w == 1:
        return 1.0
    total = torch.tensor([float(n_local)], device=device)
    dist.all_reduce(total)
    return n_local * w / float(total.item())


def table_signature(table: torch.Tensor) -> list[torch.Tensor]:
    """Every rank's ``(rows, columns, sum, sum of squares)`` of a table (one entry per rank)."""
    t = table.detach().double()
    mine = torch.stack([torch.tensor(float(table.shape[0])), torch.tensor(float(table.shape[1]))]).to(t)
    mine = torch.cat([mine, torch.stack([t.sum(), t.pow(2).sum()])])
    w = world_size()
    if w == 1:
        return [mine]
    out = [torch.zeros_like(mine) for _ in range(w)]
    dist.all_gather(out, mine)
    return out
