"""A user's own recorded trajectories, from ``.npy`` / ``.npz`` files.

Accepted layouts of a file (``N`` trajectories of ``T`` samples each):

- ``[T]`` or ``[T, D]``: one recording, served with ``obs_shape = (1,)`` / ``(D,)``;
- ``[N, T, D]`` vectors, served with ``obs_shape = (D,)``;
- ``[N, T, H, W]`` grey images, served as ``(1, H, W)``;
- ``[N, T, C, H, W]`` images, served as ``(C, H, W)``.

``uint8`` arrays are images stored as 0..255 and are served in [0, 1]; other numeric arrays are
served as float32. The array headers are read at construction (nothing else), so the number of
training trajectories is known before any data are loaded; the data are read in :meth:`setup`.

Every trajectory of every file of a split is a recording. Several recordings of one length are served as
they are: several files of one split are concatenated along ``N`` (in memory, as float32 when their
dtypes differ, uint8 parts mapped to [0, 1]); a single file stays memory-mapped where the file allows it
(``.npy`` and uncompressed ``.npz``, i.e. ``numpy.save`` / ``numpy.savez``; ``numpy.savez_compressed``
files are read into memory). One recording, recordings of different lengths, or any recordings given a
``window`` are cut into windows of one length (:mod:`datamodules.windows`; the windows are copied into
memory): each window is a training trajectory, with its own shooting nodes.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import numpy as np
from torch.utils.data import DataLoader

from datamodules.arrays import (
    ArrayHeader,
    check_header,
    load_files,
    open_files,
    read_beside,
    read_header,
    served_shape,
    stored_dtype,
    stream_headers,
)
from datamodules.base import TrajectoryDataModule
from datamodules.dataset import TrajectoryDataset
from datamodules.windows import Windows, cut_windows


def _as_list(paths: str | list[str] | None) -> list[str]:
    if paths is None:
        return []
    return [paths] if isinstance(paths, (str, Path)) else [str(p) for p in paths]


def _obs(heads: list[ArrayHeader], what: str) -> tuple[int, ...]:
    """The served sample shape of the recordings of ``heads``, checked to be the same in every file."""
    first = served_shape(heads[0].shape)[2:]
    for h in heads[1:]:
        other = served_shape(h.shape)[2:]
        if other != first:
            raise ValueError(
                f"{what}: {h.label} holds samples of shape {other} but {heads[0].label} holds {first} (served layout "
                "[N, T, *obs]); the recordings of one split must hold the same kind of measurement"
            )
    return first


def _lengths(heads: list[ArrayHeader]) -> list[int]:
    """The length of every recording of ``heads``, file after file (each trajectory of a file is one)."""
    return [served_shape(h.shape)[1] for h in heads for _ in range(served_shape(h.shape)[0])]


def _shape_of(heads: list[ArrayHeader]) -> tuple[int, ...] | list[tuple[int, ...]]:
    """The served shape of files concatenated, ``[N, T, *obs]``; where their lengths differ, each file's."""
    shapes = [served_shape(h.shape) for h in heads]
    if len({s[1:] for s in shapes}) == 1:
        return (sum(s[0] for s in shapes), *shapes[0][1:])
    return shapes


class FileDataModule(TrajectoryDataModule):
    """Trajectories recorded by the user, from ``.npy`` / ``.npz`` files.

    Args:
        train_path: a file or a list of files of training recordings (see the module's docstring: recordings of one
            length are concatenated along N, others cut into windows).
        val_path: optional validation files (checked and normalised with the training statistics).
            Lightning's validation loop runs on them for every model that forecasts from measurements
            (the baselines). A model whose validation needs the training trajectories' own states
            (class attribute ``validates_on_training_trajectories``: the SSM, which rolls out from
            its shooting nodes and has none for an unseen trajectory, and the encoder stage, whose
            targets are those rollouts) keeps the evenly spaced subset of training trajectories.
            :meth:`split_dataloader` serves the val files to any code.
        test_path: optional test files (trajectories may have another length T than training).
        key: array name inside ``.npz`` files; a list of names for several sensors, one stream each (``.npz`` files
            holding them all, same N and T): a batch's ``y`` packs them (:mod:`ssm_ms.nets.sensors`), the first
            stream finite, the others with NaN where they did not sample (a lower rate: masked in the fit).
        noise_std: several sensors: each stream's noise standard deviation, ``{name: std}``, which weighs the fit
            (the maximum-likelihood weighting, each stream by ``1 / std^2``); a stream not named weighs 1.
        clean_key: optional name of the noiseless targets (``y_clean``) inside the same ``.npz`` files.
        input_key: optional name of the inputs ``u`` inside the same ``.npz`` files (``[N, T, m]`` beside ``[N, T,
            ...]`` measurements, ``[T, m]`` beside one recording), for a system driven by them (torques,
            voltages): ``u[:, t]`` acts between samples ``t`` and ``t + 1``, the model learns ``x[t+1] = f(x[t],
            u[t])`` (give ``f`` ``input_dim: m``). Every file of every split must hold it, with the measurements' N
            and T, finite, in a float or signed integer dtype; normalised like the measurements (per component,
            training statistics, kept in checkpoints) when ``normalize`` is on.
        train_clean_path, val_clean_path, test_clean_path: noiseless targets in separate files (the measurements'
            recordings, of the same shapes, once concatenated; ``.npz`` read at ``clean_key`` or else ``key``).
        window: samples per training trajectory where the recordings are cut into windows (every split's files are
            cut alike; :mod:`datamodules.windows`). Default: several recordings of one length are served whole; one
            recording, or recordings of different lengths, are cut into windows of the shortest recording's length,
            at most 200 and rounded down to a multiple of 10. A recording shorter than the window gives none (a
            warning says which).
        stride: samples between the starts of a recording's windows (default: the window, windows side by side; a
            last window ends at the recording's end). A stride below the window gives overlapping windows, more
            training trajectories from the same samples.
        test_fraction: hold out the last ``round(test_fraction * N)`` training trajectories (windows) as the test
            split (only without ``test_path``); training windows that share samples with a held-out one are dropped.
        seed: seed of the shuffling.
        **kwargs: the :class:`~datamodules.base.TrajectoryDataModule` arguments (``batch_size``,
            ``eval_batch_size``, ``num_workers``, ``val_trajectories``, ``normalize``, ``shuffle``;
            ``data_dir`` is unused: nothing is cached).
    """

    name = "files"

    def __init__(
        self,
        train_path: str | list[str],
        val_path: str | list[str] | None = None,
        test_path: str | list[str] | None = None,
        key: str | list[str] = "y",
        clean_key: str | None = None,
        input_key: str | None = None,
        noise_std: dict[str, float] | None = None,
        train_clean_path: str | list[str] | None = None,
        val_clean_path: str | list[str] | None = None,
        test_clean_path: str | list[str] | None = None,
        window: int | None = None,
        stride: int | None = None,
        test_fraction: float = 0.0,
        seed: int = 0,
        **kwargs: Any,
    ):
        super().__init__(seed=seed, **kwargs)
        self.paths = {"train": _as_list(train_path), "val": _as_list(val_path), "test": _as_list(test_path)}
        self.clean_paths = {
            "train": _as_list(train_clean_path),
            "val": _as_list(val_clean_path),
            "test": _as_list(test_clean_path),
        }
        self.keys = [key] if isinstance(key, str) else [str(k) for k in key]
        if not self.keys or len(set(self.keys)) != len(self.keys):
            raise ValueError(f"key must name one array or several different ones, got {key!r}")
        self.key, self.clean_key, self.input_key = self.keys[0], clean_key, input_key
        self.noise_std = {str(k): float(v) for k, v in (noise_std or {}).items()}
        unknown = sorted(set(self.noise_std) - set(self.keys))
        if unknown or any(not v > 0 for v in self.noise_std.values()):
            raise ValueError(f"noise_std names streams of key ({self.keys}) with stds > 0, got {noise_std}")
        if len(self.keys) > 1 and self.normalize:
            raise ValueError("several sensors (a list of keys) are served unnormalised: set normalize: false")
        if not self.paths["train"]:
            raise ValueError("train_path is required: a .npy / .npz file or a list of them")
        if not 0.0 <= test_fraction < 1.0:
            raise ValueError(f"test_fraction must be in [0, 1), got {test_fraction}")
        if test_fraction > 0 and self.paths["test"]:
            raise ValueError("give either test_path or test_fraction > 0, not both")
        for split in ("val", "test"):
            if self.clean_paths[split] and not self.paths[split]:
                raise ValueError(f"{split}_clean_path is given but {split}_path is not")
        self.test_fraction = float(test_fraction)
        self.window, self.stride = window, stride

        # Headers only: shapes, dtypes, clean targets, windows; every check that needs no data happens here.
        self.headers: dict[str, list[ArrayHeader]] = {}
        self.clean_headers: dict[str, list[ArrayHeader]] = {}
        self.input_headers: dict[str, list[ArrayHeader]] = {}
        self.stream_headers: dict[str, dict[str, list[ArrayHeader]]] = {}  # several sensors: the other streams
        self.stream_obs: dict[str, tuple[int, ...]] = {}  # several sensors: each stream's served sample shape
        self.windows: dict[str, Windows] = {}  # each split's windows (``whole``: its recordings served as they are)
        self.shapes: dict[str, tuple[int, ...]] = {}  # served shape of each split, [N, T, *obs_shape]
        for split, files in self.paths.items():
            if files:
                self._read_split_headers(split)
        self.splits = tuple(
            s for s in ("train", "val", "test") if s in self.shapes or (s == "test" and test_fraction > 0)
        )
        n = self.shapes["train"][0]
        self.n_holdout = max(1, int(round(n * test_fraction))) if test_fraction > 0 else 0
        # the training and held-out test windows of the training files
        self.holdout = self.windows["train"].split_last(self.n_holdout) if self.n_holdout else None
        if self.holdout is not None and len(self.holdout[0]) == 0:
            raise ValueError(
                f"test_fraction={test_fraction} holds out {self.n_holdout} of the {n} training trajectories and "
                "leaves none to train on; lower it"
            )
        self._arrays: dict[str, dict[str, np.ndarray]] = {}

    # ------------------------------------------------------------------ headers
    def _read_split_headers(self, split: str) -> None:
        what = f"{split}_path"
        heads = [read_header(p, self.key, what) for p in self.paths[split]]
        for h in heads:
            check_header(h, what, one_recording=True)
        obs = _obs(heads, what)
        if split != "train" and obs != self.shapes["train"][2:]:
            raise ValueError(
                f"{what}: observations of shape {obs} do not match the training observations "
                f"{self.shapes['train'][2:]} (served layout [N, T, *obs]); every split must hold the same kind of "
                "measurement"
            )
        if self.clean_paths[split]:
            what_clean = f"{split}_clean_path"
            clean = [read_header(p, self.clean_key or self.key, what_clean) for p in self.clean_paths[split]]
        elif self.clean_key is not None:
            what_clean = f"clean_key '{self.clean_key}' of {what}"
            refusal = (
                "clean_key applies to .npz files, but {path} is a .npy file: pass the noiseless targets as "
                f"{split}_clean_path instead"
            )
            clean = [read_beside(h, self.clean_key, f"clean_key of {what}", refusal) for h in heads]
        else:
            clean = []
        if clean:
            for h in clean:
                check_header(h, what_clean, one_recording=True)
            if _lengths(clean) != _lengths(heads) or _obs(clean, what_clean) != obs:
                raise ValueError(
                    f"{what_clean}: the clean targets have shape {_shape_of(clean)} but the measurements have shape "
                    f"{_shape_of(heads)}: clean targets must have exactly the measurements' shape"
                )
        windows = cut_windows(_lengths(heads), self.window, self.stride, what)
        if windows.note(what):
            warnings.warn(windows.note(what), stacklevel=3)
        self.input_headers[split] = self._input_headers(split, heads) if self.input_key else []
        self.stream_headers[split] = {key: self._stream_headers(split, key, heads) for key in self.keys[1:]}
        self.headers[split], self.clean_headers[split], self.windows[split] = heads, clean, windows
        self.shapes[split] = (len(windows), windows.window, *obs)

    def _stream_headers(self, split: str, key: str, heads: list[ArrayHeader]) -> list[ArrayHeader]:
        """A further sensor's headers in a split's files, checked beside the first stream's (same N and T)."""
        what = f"stream '{key}' of {split}_path"
        streams = stream_headers(heads, key, self.key, what, one_recording=True)
        obs = _obs(streams, what)
        if split == "train":
            self.stream_obs[key] = obs
        elif obs != self.stream_obs[key]:
            raise ValueError(f"{what}: its samples' shape differs from the training files'")
        return streams

    @property
    def sensor_layout(self) -> list[dict[str, Any]] | None:
        """Several sensors: the streams of ``key`` in order, their shapes as served and ``noise_std``."""
        if len(self.keys) == 1:
            return None
        shapes = {self.keys[0]: tuple(self.shapes["train"][2:]), **self.stream_obs}
        return [{"name": k, "shape": list(shapes[k]), "noise_std": self.noise_std.get(k, 1.0)} for k in self.keys]

    def _input_headers(self, split: str, heads: list[ArrayHeader]) -> list[ArrayHeader]:
        """The inputs' headers of a split's files, checked: one array per file beside ``y``, ``[N, T, m]`` (``[T,
        m]`` beside one recording)."""
        what = f"input_key '{self.input_key}' of {split}_path"
        inputs = []
        refusal = (
            f"{what}: inputs are read from .npz files (y and u side by side), but {{path}} is a .npy file: save both "
            "with numpy.savez(path, y=..., u=...)"
        )
        for h in heads:
            u = read_beside(h, self.input_key, what, refusal)
            check_header(u, what, one_recording=True)
            layout = "[T, m]" if len(h.shape) <= 2 else "[N, T, m]"
            if len(u.shape) != (2 if len(h.shape) <= 2 else 3) or u.dtype == np.uint8 or u.dtype.kind not in "fi":
                raise ValueError(
                    f"{what}: {u.label} must be a float (or signed integer) array {layout}, got "
                    f"shape {u.shape} and dtype {u.dtype}"
                )
            (n_u, t_u), (n, t) = served_shape(u.shape)[:2], served_shape(h.shape)[:2]
            if (n_u, t_u) != (n, t):
                raise ValueError(
                    f"{what}: {u.label} holds {n_u} trajectories of {t_u} inputs but its "
                    f"measurements hold {n} of {t} samples: one input per sample"
                )
            inputs.append(u)
        widths = {u.shape[-1] for u in inputs}
        if len(widths) > 1 or (
            self.input_headers.get("train") and self.input_headers["train"][0].shape[-1] not in widths
        ):
            raise ValueError(f"{what}: every file must have the same number of inputs m, got {sorted(widths)}")
        return inputs

    # ------------------------------------------------------------------ sizes known before loading
    @property
    def num_train_trajectories(self) -> int:
        return len(self.holdout[0]) if self.holdout is not None else self.shapes["train"][0]

    @property
    def obs_shape(self) -> tuple[int, ...]:
        layout = self.sensor_layout
        if layout:  # the streams packed
            return (sum(int(np.prod(s["shape"])) for s in layout),)
        return tuple(self.shapes["train"][2:])

    @property
    def seq_len(self) -> int:
        return int(self.shapes["train"][1])

    @property
    def input_dim(self) -> int:
        """Inputs per step (0 without ``input_key``), known from the headers before any data are read."""
        return int(self.input_headers["train"][0].shape[-1]) if self.input_headers.get("train") else 0

    def generator_params(self) -> dict[str, Any]:
        """Where the data came from (stored in checkpoints with the DataModule's state); ``window`` and ``stride``:
        the training recordings' cut (``None``: served whole)."""
        cut = self.windows["train"]
        return {
            "paths": self.paths,
            "clean_paths": self.clean_paths,
            "key": self.key if len(self.keys) == 1 else self.keys,
            **({"noise_std": self.noise_std} if self.noise_std else {}),
            "clean_key": self.clean_key,
            "input_key": self.input_key,
            "test_fraction": self.test_fraction,
            "window": None if cut.whole else cut.window,
            "stride": None if cut.whole else cut.stride,
        }

    # ------------------------------------------------------------------ loading
    def prepare_split(self, split: str) -> None:
        """Nothing to generate or cache: the files are read in :meth:`setup`."""

    def _read(self, split: str, indices: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """The arrays of a split's files, ``[N, T, *obs]``, their trajectories (windows) ``indices`` (all: None):
        recordings served whole stay as :func:`~datamodules.arrays.load_files` reads them (memory-mapped where they
        can be; a selection is a view), windows are cut (a copy)."""
        sources = {"y": (self.headers[split], False)}
        if self.clean_headers[split]:
            sources["y_clean"] = (self.clean_headers[split], False)
        if self.input_headers[split]:
            sources["u"] = (self.input_headers[split], False)
        for key, heads in self.stream_headers[split].items():  # further sensors: NaN where they did not sample
            sources[f"y_{key}"] = (heads, True)
        windows = self.windows[split]
        if indices is not None:
            windows = windows.subset(indices)
        arrays = {}
        for name, (heads, missing) in sources.items():
            if self.windows[split].whole:
                a = load_files(heads, missing)  # one window per recording: a held-out selection is contiguous
                arrays[name] = a if indices is None else a[indices[0] : indices[-1] + 1]
            else:
                recordings = [a[n] for a in open_files(heads, missing) for n in range(len(a))]
                arrays[name] = windows.gather(recordings, stored_dtype(recordings[0].dtype))
        return arrays

    def _split_arrays(self, split: str) -> dict[str, np.ndarray]:
        if split not in self._arrays:
            if split in ("train", "test") and self.holdout is not None:
                self._arrays[split] = self._read("train", self.holdout[0 if split == "train" else 1])
            else:
                self._arrays[split] = self._read(split)
        return self._arrays[split]

    def load_split(self, split: str) -> TrajectoryDataset:
        if split not in self.splits:
            raise ValueError(f"no {split} split: this FileDataModule has {list(self.splits)} (pass {split}_path)")
        return TrajectoryDataset(self._split_arrays(split), streams=self.stream_names)

    def stage_splits(self, stage: str | None) -> tuple[str, ...]:
        """The base's, and the val files for ``fit`` and ``validate``."""
        extra = ("val",) if stage in ("fit", "validate") and "val" in self.splits else ()
        return super().stage_splits(stage) + extra

    # ------------------------------------------------------------------ loaders
    def split_dataloader(self, split: str) -> DataLoader:
        """A non-shuffled loader over any split (e.g. the val files), with the evaluation batch size."""
        if split not in self.splits:
            raise ValueError(f"no {split} split: this FileDataModule has {list(self.splits)} (pass {split}_path)")
        return self._loader(self.load(split), self.eval_batch_size)

    def val_dataloader(self) -> DataLoader | list:
        """The val files, unless the model validates on training trajectories (see ``val_path``)."""
        model = self.trainer.lightning_module if self.trainer is not None else None
        if "val" not in self.splits or getattr(model, "validates_on_training_trajectories", False):
            return super().val_dataloader()
        return self._loader(self.load("val"), self.eval_batch_size)

    def test_dataloader(self) -> DataLoader:
        if "test" not in self.splits:
            raise ValueError("this FileDataModule has no test split: pass test_path, or test_fraction > 0")
        return super().test_dataloader()
