"""Recordings of any lengths cut into training windows of one length (numpy only).

Recordings ``r = 0 .. R-1`` have lengths ``T_r``. With a window ``W`` and a stride ``S`` (default ``S = W``: windows
side by side), the windows of recording ``r`` start at ``0, S, 2S, ...`` while ``start + W <= T_r``; where the last of
these does not end at ``T_r``, one more window ends there (it starts at ``T_r - W`` and overlaps the one before), so
that with ``S <= W`` every sample of the recording is in some window. A recording shorter than ``W`` gives no window
(:attr:`Windows.too_short` names it); a window longer than every recording is refused.

Default window (:func:`default_window`): none, the recordings served whole, when there are several recordings of one
length; otherwise (one recording, or recordings of different lengths) the shortest recording's length, capped at
:data:`MAX_WINDOW` and rounded down to a multiple of :data:`WINDOW_MULTIPLE` where it has that many samples (so that
every recording gives a window and the shooting pieces of the paper's sizes, 10 to 25 samples, divide it).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import reduce

import numpy as np

MAX_WINDOW = 200  # the default window's cap: 8 pieces of 25 samples (the paper's pendulum pieces), 20 of 10
WINDOW_MULTIPLE = 10  # the default window is a multiple of 10: pieces of 10 samples (the paper's Lorenz) divide it


def default_window(lengths: Sequence[int]) -> int | None:
    """The window of recordings of these lengths when none is given; ``None``: several recordings of one length,
    served whole (not cut)."""
    lengths = [int(t) for t in lengths]
    if len(lengths) > 1 and len(set(lengths)) == 1:
        return None
    w = min(MAX_WINDOW, min(lengths))
    return w - w % WINDOW_MULTIPLE if w >= WINDOW_MULTIPLE else w


def window_starts(length: int, window: int, stride: int) -> list[int]:
    """The starts of the windows of one recording of ``length`` samples (none if it is shorter than ``window``)."""
    if length < window:
        return []
    starts = list(range(0, length - window + 1, stride))
    if starts[-1] + window != length:
        starts.append(length - window)
    return starts


@dataclass(frozen=True, eq=False)
class Windows:
    """Where the windows of some recordings start, and how to cut any arrays aligned with those recordings.

    ``origins[i] = (recording, start)`` of window ``i``, ordered by recording, then start; each window holds
    ``window`` samples. ``too_short``: the recordings shorter than the window (they give none).
    """

    origins: np.ndarray  # [N, 2] int64
    window: int
    stride: int
    lengths: tuple[int, ...]
    too_short: tuple[int, ...]

    def __len__(self) -> int:
        return len(self.origins)

    @property
    def whole(self) -> bool:
        """Every recording is exactly one window: the recordings are served as they are (nothing cut)."""
        return len(self.origins) == len(self.lengths) and all(t == self.window for t in self.lengths)

    def note(self, what: str = "recordings") -> str | None:
        """What the cut left out, in words (``None``: nothing)."""
        if not self.too_short:
            return None
        short = ", ".join(f"{r} ({self.lengths[r]} samples)" for r in self.too_short)
        return f"{what}: recordings {short} are shorter than the window of {self.window} samples and give no window"

    def subset(self, indices: np.ndarray) -> Windows:
        """The windows ``indices`` of these (in that order)."""
        return Windows(self.origins[np.asarray(indices, dtype=np.int64)], self.window, self.stride, self.lengths, ())

    def gather(self, recordings: Sequence[np.ndarray], dtype: np.dtype | None = None) -> np.ndarray:
        """The windows of arrays aligned with the recordings (``recordings[r]``: ``[T_r, ...]``), stacked:
        ``[N, window, ...]`` (a copy, in ``dtype`` if given, else the recordings' common dtype)."""
        if len(recordings) != len(self.lengths):
            raise ValueError(f"{len(recordings)} arrays for {len(self.lengths)} recordings")
        for r, a in enumerate(recordings):
            if len(a) != self.lengths[r]:
                raise ValueError(f"recording {r}: an array of {len(a)} samples for a recording of {self.lengths[r]}")
        inner = np.shape(recordings[0])[1:]
        dtype = reduce(np.promote_types, [a.dtype for a in recordings]) if dtype is None else np.dtype(dtype)
        out = np.empty((len(self.origins), self.window, *inner), dtype=dtype)
        for i, (r, start) in enumerate(self.origins.tolist()):
            out[i] = recordings[r][start : start + self.window]
        return out

    def split_last(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Hold out the last ``n`` windows: ``(kept, held_out)`` indices, ``kept`` without the windows that share a
        sample with a held-out one (a test window never overlaps a training window)."""
        cut = len(self.origins) - n
        held = np.arange(cut, len(self.origins))
        kept = np.arange(cut)
        if n > 0 and cut > 0:
            r, start = self.origins[cut]
            overlaps = (self.origins[:cut, 0] == r) & (self.origins[:cut, 1] + self.window > start)
            kept = kept[~overlaps]
        return kept, held


def cut_windows(
    lengths: Sequence[int], window: int | None = None, stride: int | None = None, what: str = "recordings"
) -> Windows:
    """The windows of recordings of ``lengths`` (see the module's docstring; ``window=None``: :func:`default_window`,
    ``stride=None``: the window). ``what`` names the recordings in error messages."""
    lengths = tuple(int(t) for t in lengths)
    if not lengths:
        raise ValueError(f"{what}: no recordings: give at least one")
    if window is not None and int(window) < 1:
        raise ValueError(f"window must be >= 1 samples (or None: the default), got {window}")
    if stride is not None and int(stride) < 1:
        raise ValueError(f"stride must be >= 1 samples (or None: the window, windows side by side), got {stride}")
    if window is None:
        window = default_window(lengths)
        if window is None:  # several recordings of one length: served whole
            if stride is not None:
                raise ValueError(
                    f"stride={stride} is given, but the {len(lengths)} recordings of {lengths[0]} samples are served "
                    "whole: give a window too (e.g. window=50), or no stride"
                )
            window = lengths[0]
    window = int(window)
    stride = window if stride is None else int(stride)
    if window > max(lengths):
        raise ValueError(
            f"window={window} is longer than every recording ({what}: the longest has {max(lengths)} samples): "
            f"give window <= {max(lengths)}"
        )
    origins = [(r, s) for r, t in enumerate(lengths) for s in window_starts(t, window, stride)]
    too_short = tuple(r for r, t in enumerate(lengths) if t < window)
    return Windows(np.asarray(origins, dtype=np.int64).reshape(-1, 2), window, stride, lengths, too_short)
