"""Trajectories held as arrays, served as the batches of the data contract of :mod:`datamodules.base`.

:class:`TrajectoryDataset` serves arrays ``[N, T, ...]`` (possibly memory-mapped) as ``{"index", "y", ...}``
dictionaries: one sensor's measurements normalised with a :class:`~datamodules.normalizer.Normalizer`, several
sensors' streams packed into one ``y``, a whole batch read at once (``__getitems__``); :func:`collate` is the
DataLoader's ``collate_fn`` that passes such a batch through. The cache, the splits and the normalisation's
statistics are the DataModule's.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset, default_collate

from datamodules.normalizer import Normalizer, to_float


class TrajectoryDataset(Dataset):
    """Trajectories held as arrays ``[N, T, ...]`` (possibly memory-mapped), served as dicts.

    ``y`` and ``y_clean`` are converted to float and normalised per item; ``state`` is served as is.
    ``indices`` restricts the data set to some trajectories while keeping their original index
    (the validation subset of the training set uses this).

    Several sensors (``streams``, their names in order): the first stream is stored as ``y`` / ``y_clean``, the
    others as ``y_<name>`` / ``y_clean_<name>`` ``[N, T, *shape]`` (NaN where a stream did not sample); a batch's
    ``y`` (and ``y_clean``) is every stream flattened and concatenated, ``[B, T, P]``, in that order.
    """

    def __init__(
        self,
        arrays: Mapping[str, np.ndarray],
        normalizer: Normalizer | None = None,
        indices: Sequence[int] | None = None,
        input_normalizer: Normalizer | None = None,
        streams: Sequence[str] | None = None,
    ):
        if "y" not in arrays:
            raise ValueError(f"a trajectory data set needs a 'y' array, got keys {sorted(arrays)}")
        n = len(arrays["y"])
        for key, a in arrays.items():
            if len(a) != n:
                raise ValueError(f"array '{key}' holds {len(a)} trajectories but 'y' holds {n}")
        self.arrays = dict(arrays)
        self.normalizer = normalizer
        self.input_normalizer = input_normalizer  # of the inputs "u" [N, T, m], where the data have them
        self.indices = np.arange(n) if indices is None else np.asarray(indices, dtype=np.int64)
        self.streams = list(streams) if streams and len(streams) > 1 else None
        for name in self.streams or []:
            if name != self.streams[0] and f"y_{name}" not in self.arrays:
                raise ValueError(f"stream {name!r} has no array 'y_{name}' (keys: {sorted(self.arrays)})")

    def __len__(self) -> int:
        return len(self.indices)

    @property
    def seq_len(self) -> int:
        return int(self.arrays["y"].shape[1])

    @property
    def obs_shape(self) -> tuple[int, ...]:
        if self.streams:
            return (sum(int(np.prod(self._stream_array("y", n).shape[2:])) for n in self.streams),)
        return tuple(int(s) for s in self.arrays["y"].shape[2:])

    def _stream_array(self, kind: str, name: str) -> np.ndarray:
        return self.arrays[kind if name == self.streams[0] else f"{kind}_{name}"]

    def _fetch(self, j: np.ndarray | int) -> dict[str, torch.Tensor]:
        item: dict[str, Any] = {"index": torch.as_tensor(j, dtype=torch.long)}
        packed = {f"{kind}_{n}" for kind in ("y", "y_clean") for n in (self.streams or [])[1:]}
        for key, a in self.arrays.items():
            if key in packed:
                continue
            t = to_float(a[j])
            if key in ("y", "y_clean") and self.streams:
                if key == "y_clean" and any(f"y_clean_{n}" not in self.arrays for n in self.streams[1:]):
                    continue  # some stream has no noiseless copy: no packed y_clean
                lead = t.dim() - (a.ndim - 2)
                t = torch.cat(
                    [t.flatten(lead)]
                    + [to_float(self.arrays[f"{key}_{n}"][j]).flatten(lead) for n in self.streams[1:]],
                    dim=-1,
                )
            elif key in ("y", "y_clean") and self.normalizer is not None:
                t = self.normalizer.normalize(t)
            elif key == "u" and self.input_normalizer is not None:
                t = self.input_normalizer.normalize(t)
            item[key] = t
        return item

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        return self._fetch(int(self.indices[i]))

    def __getitems__(self, items: list[int]) -> dict[str, torch.Tensor]:
        """A whole batch with one (sorted) fancy-indexed read per array, already collated.

        The DataLoader calls this instead of ``__getitem__`` once per item: with a million short
        trajectories (Lorenz cut into pieces of 10) per-item fetching would dominate an epoch.
        """
        j = self.indices[np.asarray(items, dtype=np.int64)]
        order = np.argsort(j, kind="stable")
        batch = self._fetch(j[order])
        inverse = torch.from_numpy(np.argsort(order, kind="stable"))
        return {key: value[inverse] for key, value in batch.items()}


def collate(batch: Any) -> Any:
    """Collate items, or pass through a batch that ``__getitems__`` already assembled."""
    return batch if isinstance(batch, dict) else default_collate(batch)
