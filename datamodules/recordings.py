"""Recordings held in memory (numpy arrays or torch tensors), served as training trajectories: the Python API's data.

``Recordings(y=y, u=u, dt=0.05)`` takes one recording, several of one length, or a list of recordings of any lengths,
checks them at construction (one ``ValueError`` naming the fix for each mistake), and cuts them into training windows
of one length (:mod:`datamodules.windows`): each window is a training trajectory with its own shooting nodes. Nothing
is written to disk; the windows are copied into memory (uint8 images stay uint8, served in [0, 1]; anything else is
held as float32).
"""

from __future__ import annotations

import hashlib
import math
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch

from datamodules.arrays import harmonise, stored_dtype
from datamodules.base import TrajectoryDataModule
from datamodules.dataset import TrajectoryDataset
from datamodules.windows import cut_windows

MEASUREMENT_LAYOUTS = (
    "one recording [T] or [T, D], several of one length [N, T, D], images [N, T, H, W] or [N, T, C, H, W], or a list "
    "of recordings [T_i], [T_i, D], [T_i, H, W] or [T_i, C, H, W]"
)
INPUT_LAYOUTS = "one recording's [T] or [T, m], several of one length [N, T, m], or a list of [T_i] or [T_i, m]"


def _numpy(a: Any) -> np.ndarray:
    return a.detach().cpu().numpy() if isinstance(a, torch.Tensor) else np.asarray(a)


def _sample(a: np.ndarray, inputs: bool) -> np.ndarray:
    """One recording ``[T, ...]`` in the served layout ``[T, *obs]``: scalars ``[T]`` as ``[T, 1]``, grey images
    ``[T, H, W]`` as ``[T, 1, H, W]``."""
    if a.ndim == 1 or (a.ndim == 3 and not inputs):
        return a.reshape(a.shape[0], 1, *a.shape[1:])
    return a


def parse_recordings(value: Any, what: str, inputs: bool = False) -> list[np.ndarray]:
    """Measurements (``inputs``: inputs) in any layout of the module's docstring as a list of recordings ``[T_r,
    *obs]``, checked: a layout of the list, a real numeric dtype, samples of one shape, no empty recording."""
    layouts = INPUT_LAYOUTS if inputs else MEASUREMENT_LAYOUTS
    if isinstance(value, (list, tuple)):
        if len(value) == 0:
            raise ValueError(f"{what} is an empty list: give at least one recording ({layouts})")
        recordings = []
        for r, item in enumerate(value):
            a = _numpy(item)
            if a.ndim not in ((1, 2) if inputs else (1, 2, 3, 4)):
                raise ValueError(f"{what}: recording {r} of the list has shape {a.shape}; give {layouts}")
            recordings.append(_sample(a, inputs))
    else:
        a = _numpy(value)
        if a.ndim in (1, 2):
            recordings = [_sample(a, inputs)]
        elif a.ndim in ((3,) if inputs else (3, 4, 5)):
            recordings = [_sample(r, inputs) for r in a]
            if not recordings:
                raise ValueError(f"{what} has shape {a.shape}: no recordings; give at least one ({layouts})")
        else:
            raise ValueError(f"{what} has shape {a.shape} (rank {a.ndim}); give {layouts}")
    for r, a in enumerate(recordings):
        if a.dtype.kind not in "biuf":
            raise ValueError(f"{what}: recording {r} has dtype {a.dtype}; give real numbers (float, int or uint8)")
        if a.size == 0:
            raise ValueError(f"{what}: recording {r} is empty (shape {a.shape}): drop it, or give it samples")
        if a.shape[1:] != recordings[0].shape[1:]:
            raise ValueError(
                f"{what}: recording {r} holds samples of shape {a.shape[1:]} but recording 0 holds "
                f"{recordings[0].shape[1:]}: every recording holds the same kind of measurement"
            )
    return recordings


def check_recordings_finite(recordings: Sequence[np.ndarray], what: str, missing: bool = False) -> None:
    """Refuse NaN or inf in recordings (``missing``: NaN allowed, the samples a sensor did not take; inf refused)."""
    for r, a in enumerate(recordings):
        if a.dtype.kind != "f":
            continue
        bad = (np.isinf(a) if missing else ~np.isfinite(a)).reshape(len(a), -1)
        if bad.any():
            t = int(np.flatnonzero(bad.any(axis=1))[0])
            value = a.reshape(len(a), -1)[t][bad[t]][0]
            raise ValueError(
                f"{what}: recording {r} holds {value} at sample {t}: remove or interpolate missing samples before "
                "training" + ("" if missing else " (several sensors: only the streams after the first may hold NaN)")
            )


def check_aligned(recordings: Sequence[np.ndarray], reference: Sequence[np.ndarray], what: str, ref: str) -> None:
    """Refuse recordings that are not one-to-one with the reference's, sample for sample."""
    if len(recordings) != len(reference):
        raise ValueError(
            f"{what} holds {len(recordings)} recordings but {ref} holds {len(reference)}: give one per recording"
        )
    for r, (a, b) in enumerate(zip(recordings, reference)):
        if len(a) != len(b):
            raise ValueError(
                f"{what}: recording {r} has {len(a)} samples but {ref}'s recording {r} has {len(b)}: give one per "
                f"sample of {ref}"
            )


def _streams(value: Any, what: str) -> dict[str, Any]:
    if isinstance(value, Mapping):
        if not value:
            raise ValueError(f"{what} is an empty dict: give one array (or list) per sensor, {{name: recordings}}")
        bad = [k for k in value if not isinstance(k, str) or not k or k == "clean" or k.startswith("clean_")]
        if bad:
            raise ValueError(
                f"{what}: sensor names must be non-empty strings other than 'clean' / 'clean_*', got {bad}"
            )
        return dict(value)
    return {"y": value}


class Recordings(TrajectoryDataModule):
    """Recordings in memory, cut into training windows: a training split only (validation runs on a subset of it).

    Args:
        y: the measurements: one recording ``[T]`` or ``[T, D]``; several of one length ``[N, T, D]``; image
            sequences ``[N, T, H, W]`` (grey, served as ``(1, H, W)``) or ``[N, T, C, H, W]``; or a list of
            recordings of any lengths, each ``[T_i]``, ``[T_i, D]``, ``[T_i, H, W]`` or ``[T_i, C, H, W]``. numpy
            arrays or torch tensors; uint8 images (0..255) are served in [0, 1]. Several sensors: a dict ``{name:
            such an array or list}``, one stream each, with the same recordings and lengths; a batch's ``y`` packs
            them (the first stream finite, the others NaN where they did not sample).
        u: the inputs, one per measurement sample (``u[t]`` at the time of ``y[t]``, acting between samples ``t`` and
            ``t + 1``): ``[T]`` or ``[T, m]`` for one recording, ``[N, T, m]``, or a list of ``[T_i]`` / ``[T_i, m]``;
            finite real numbers, taken by value.
        y_clean: optional noiseless measurements, in ``y``'s layout and shapes (a dict with ``y``'s names for several
            sensors).
        dt: seconds per sample (:attr:`sample_period`; ``None``: unknown).
        window: samples per training trajectory. Default: several recordings of one length are served whole; one
            recording, or recordings of different lengths, are cut into windows of the shortest recording's length,
            at most 200 and rounded down to a multiple of 10. A recording shorter than the window gives none (a
            warning says which). The model's ``n_nodes`` must divide it.
        stride: samples between the starts of a recording's windows (default: the window, windows side by side; a
            last window ends at the recording's end, so that every sample is trained on).
        normalize: normalise measurements and inputs per component with the training windows' statistics (kept in
            checkpoints). ``None``: on for vector measurements (not uint8) of one sensor, off for images and several
            sensors (served unnormalised).
        noise_std: several sensors: each stream's noise standard deviation ``{name: std}``, which weighs the fit
            (each stream by ``1 / std^2``); a stream not named weighs 1.
        batch_size, eval_batch_size, val_trajectories, shuffle, seed, num_workers: as
            :class:`~datamodules.base.TrajectoryDataModule`'s (counted in windows).

    Attributes:
        window_origins: ``[N, 2]`` int64, ``(recording, start)`` of each training trajectory (window), in order.
        windows: the :class:`~datamodules.windows.Windows` of the cut (``origins``, ``window``, ``stride``, the
            recordings' ``lengths``, ``too_short``: the recordings that gave no window).
    """

    name = "recordings"
    splits = ("train",)

    def __init__(
        self,
        y: Any,
        u: Any = None,
        y_clean: Any = None,
        *,
        dt: float | None = None,
        window: int | None = None,
        stride: int | None = None,
        normalize: bool | None = None,
        noise_std: Mapping[str, float] | None = None,
        batch_size: int = 40,
        eval_batch_size: int | None = None,
        val_trajectories: int = 16,
        shuffle: bool = True,
        seed: int = 0,
        num_workers: int = 0,
    ):
        super().__init__(
            batch_size=batch_size,
            eval_batch_size=eval_batch_size,
            num_workers=num_workers,
            val_trajectories=val_trajectories,
            shuffle=shuffle,
            seed=seed,
        )
        if dt is not None and not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be the seconds per sample, a number > 0 (or None: unknown), got {dt!r}")
        self.dt = None if dt is None else float(dt)

        streams = _streams(y, "y")
        self.streams = list(streams)
        several = len(self.streams) > 1
        label = {n: f"y[{n!r}]" if isinstance(y, Mapping) else "y" for n in self.streams}
        recs = {n: parse_recordings(v, label[n]) for n, v in streams.items()}
        first = self.streams[0]
        for n in self.streams:
            check_aligned(recs[n], recs[first], label[n], label[first])
            check_recordings_finite(recs[n], label[n], missing=n != first)

        clean: dict[str, list[np.ndarray]] = {}
        if y_clean is not None:
            given = _streams(y_clean, "y_clean")
            if list(given) != self.streams:
                raise ValueError(f"y_clean must have y's sensors {self.streams}, got {list(given)}")
            for n, v in given.items():
                what = f"y_clean[{n!r}]" if several else "y_clean"
                clean[n] = parse_recordings(v, what)
                check_aligned(clean[n], recs[n], what, label[n])
                if clean[n][0].shape[1:] != recs[n][0].shape[1:]:
                    raise ValueError(
                        f"{what} holds samples of shape {clean[n][0].shape[1:]} but {label[n]} holds "
                        f"{recs[n][0].shape[1:]}: clean targets have exactly the measurements' shapes"
                    )
                check_recordings_finite(clean[n], what, missing=n != first)

        inputs = None
        if u is not None:
            inputs = parse_recordings(u, "u", inputs=True)
            check_aligned(inputs, recs[first], "u", label[first])
            check_recordings_finite(inputs, "u")

        self.noise_std = {str(k): float(v) for k, v in (noise_std or {}).items()}
        if set(self.noise_std) - set(self.streams) or any(not v > 0 for v in self.noise_std.values()):
            raise ValueError(f"noise_std names sensors of y ({self.streams}) with stds > 0, got {dict(noise_std)}")
        vectors = not several and recs[first][0].ndim == 2 and recs[first][0].dtype != np.uint8
        if normalize and several:
            raise ValueError("several sensors (a dict y) are served unnormalised: leave normalize unset (or False)")
        self.normalize = vectors if normalize is None else bool(normalize)

        self.windows = cut_windows([len(a) for a in recs[first]], window, stride, "y")
        if self.windows.note("y"):
            warnings.warn(self.windows.note("y"), stacklevel=2)
        self.window_origins = self.windows.origins
        self._digest = self._sha1(recs, clean, inputs)
        self._sample_shapes = {n: tuple(int(s) for s in recs[n][0].shape[1:]) for n in self.streams}

        def cut(recordings: list[np.ndarray], dtype: np.dtype | None = None) -> np.ndarray:
            recordings = harmonise(recordings)
            return self.windows.gather(recordings, dtype or stored_dtype(recordings[0].dtype))

        self._arrays = {"y" if n == first else f"y_{n}": cut(recs[n]) for n in self.streams}
        for n, c in clean.items():
            self._arrays["y_clean" if n == first else f"y_clean_{n}"] = cut(c)
        if inputs is not None:
            self._arrays["u"] = cut(inputs, np.dtype(np.float32))

    @staticmethod
    def _sha1(recs: dict[str, list[np.ndarray]], clean: dict[str, list[np.ndarray]], u: list | None) -> str:
        """A sha1 digest of every recording's dtype, shape and bytes (the measurements, clean targets, inputs)."""
        h = hashlib.sha1()
        for kind, group in (("y", recs), ("y_clean", clean), ("u", {"u": u} if u is not None else {})):
            for name, recordings in group.items():
                for a in recordings:
                    h.update(f"{kind}:{name}:{a.dtype.str}:{a.shape};".encode())
                    h.update(np.ascontiguousarray(a).data)
        return h.hexdigest()

    # ------------------------------------------------------------------ sizes, known at construction
    @property
    def num_train_trajectories(self) -> int:
        return len(self.windows)

    @property
    def seq_len(self) -> int:
        return self.windows.window

    @property
    def window(self) -> int:
        """Samples per training trajectory."""
        return self.windows.window

    @property
    def stride(self) -> int:
        """Samples between the starts of a recording's windows."""
        return self.windows.stride

    @property
    def obs_shape(self) -> tuple[int, ...]:
        layout = self.sensor_layout
        if layout:  # the streams packed
            return (sum(int(np.prod(s["shape"])) for s in layout),)
        return self._sample_shapes[self.streams[0]]

    @property
    def input_dim(self) -> int:
        return int(self._arrays["u"].shape[-1]) if "u" in self._arrays else 0

    @property
    def sensor_layout(self) -> list[dict[str, Any]] | None:
        """Several sensors: the streams of ``y`` in order, their sample shapes and ``noise_std``."""
        if len(self.streams) == 1:
            return None
        return [
            {"name": n, "shape": list(self._sample_shapes[n]), "noise_std": self.noise_std.get(n, 1.0)}
            for n in self.streams
        ]

    @property
    def sample_period(self) -> float | None:
        """Seconds per sample (``dt``; ``None``: not given)."""
        return self.dt

    def generator_params(self) -> dict[str, Any]:
        """What identifies the data: their shapes, the cut, and a sha1 digest of the arrays."""
        return {
            "recordings": len(self.windows.lengths),
            "samples": int(sum(self.windows.lengths)),
            "sample_shapes": {n: list(s) for n, s in self._sample_shapes.items()},
            "input_dim": self.input_dim,
            "clean": "y_clean" in self._arrays,
            "window": self.window,
            "stride": self.stride,
            "sha1": self._digest,
        }

    # ------------------------------------------------------------------ served from memory
    def prepare_split(self, split: str) -> None:
        """Nothing to generate or cache: the arrays are in memory."""

    def load_split(self, split: str) -> TrajectoryDataset:
        if split != "train":
            raise ValueError(
                f"no {split} split: Recordings serve the recordings given as training data; forecast other sequences "
                "with the trained model, or test from files (FileDataModule's test_path)"
            )
        return TrajectoryDataset(self._arrays, streams=self.stream_names)
