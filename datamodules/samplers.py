"""Samplers whose order is a pure function of ``(seed, epoch)``: one device, and a device's shard of the
one-device batches under data parallelism (resumed runs see the same batches)."""

from __future__ import annotations

import torch
from torch.utils.data import DistributedSampler, Sampler


class EpochSeededSampler(Sampler[int]):
    """A shuffling sampler whose order is a pure function of ``(seed, epoch)``.

    Lightning calls ``set_epoch`` at the start of every epoch, so a run resumed from a checkpoint
    sees the same batches as an uninterrupted one.
    """

    def __init__(self, n: int, seed: int = 0, shuffle: bool = True):
        self.n, self.seed, self.shuffle, self.epoch = n, seed, shuffle, 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return self.n

    def __iter__(self):
        if not self.shuffle:
            return iter(range(self.n))
        g = torch.Generator().manual_seed(self.seed * 100_003 + self.epoch)
        return iter(torch.randperm(self.n, generator=g).tolist())


class GlobalBatchShardSampler(DistributedSampler):
    """This rank's share of the one-device batches, for data parallelism.

    The order of an epoch is :class:`EpochSeededSampler`'s; it is cut into global batches of
    ``batch_size`` trajectories, and each global batch into ``num_replicas`` contiguous shards whose
    sizes differ by at most one: shard ``rank`` is this rank's batch. The ranks together see exactly
    the one-device batches, with no trajectory repeated or dropped. (Lightning's own
    ``DistributedSamplerWrapper``, used otherwise, deals the order out in turns with batches of
    ``batch_size`` per rank, so the global batch grows with the number of devices, and pads the
    epoch by repeating trajectories when it does not divide.) A subclass of ``DistributedSampler`` so
    that Lightning leaves it in place.
    """

    def __init__(self, n: int, batch_size: int, num_replicas: int, rank: int, seed: int = 0, shuffle: bool = True):
        super().__init__(range(n), num_replicas=num_replicas, rank=rank, shuffle=False)
        if batch_size % num_replicas != 0:
            raise ValueError(
                f"data.batch_size={batch_size} is the global batch, split over {num_replicas} devices: choose a "
                f"multiple of {num_replicas} (e.g. {batch_size - batch_size % num_replicas or num_replicas})"
            )
        last = n % batch_size
        if 0 < last < num_replicas:
            raise ValueError(
                f"the last global batch of an epoch holds {last} of {n} trajectories, fewer than the {num_replicas} "
                f"devices: choose data.batch_size so that {n} % batch_size is 0 or at least {num_replicas}"
            )
        self.order = EpochSeededSampler(n, seed, shuffle)
        self.n, self.batch_size = n, batch_size

    def set_epoch(self, epoch: int) -> None:
        super().set_epoch(epoch)
        self.order.set_epoch(epoch)

    def _shard(self, start: int) -> tuple[int, int]:
        size = min(self.batch_size, self.n - start)
        base, extra = divmod(size, self.num_replicas)
        lo = start + self.rank * base + min(self.rank, extra)
        return lo, lo + base + (1 if self.rank < extra else 0)

    def __iter__(self):
        order = list(self.order)
        return iter([i for start in range(0, self.n, self.batch_size) for i in order[slice(*self._shard(start))]])

    def __len__(self) -> int:
        return sum(hi - lo for lo, hi in map(self._shard, range(0, self.n, self.batch_size)))
