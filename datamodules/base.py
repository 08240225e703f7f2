"""What every trajectory data set shares: on-disk cache, splits, normalisation, loaders.

A DataModule of this project serves dictionaries::

    {"index": LongTensor[B], "y": FloatTensor[B, T, *obs_shape], ...optional "y_clean", "state"}

``index`` is the trajectory's position in its split. For the training split it selects the
trajectory's shooting nodes in the model's ``nn.Embedding``. ``y`` is the noisy measurement,
``y_clean`` the noiseless one where the generator knows it, ``state`` the true state (for plots).
Images are channel-first, ``obs_shape = (C, H, W)``; vectors have ``obs_shape = (D,)``.

Subclasses that generate arrays implement :meth:`generator_params` (everything the data depend
on: the cache key), :attr:`split_params` (which of those parameters only one split depends on, e.g.
its size), :meth:`generate` (one split as numpy arrays) and :attr:`num_train_trajectories` (known
before any data exist, so that the model can size its node table at construction). Data sets that
are not arrays (Moving MNIST is generated on the fly) override :meth:`prepare_data` and
:meth:`load_split` instead.

A stage reads, and generates, only its own splits: ``fit`` and ``validate`` the training split
(validation runs on training trajectories), ``test`` the test split, ``predict`` only its files.
Whatever a test needs from the training data (the normalisation, the mean training measurement) is
saved in every checkpoint with the DataModule's state; the training split is read, and generated if
missing, only when that state lacks it (:meth:`TrajectoryDataModule.train_split`).

The arrays are served by :class:`~datamodules.dataset.TrajectoryDataset` and normalised by
:class:`~datamodules.normalizer.Normalizer`; this module holds the DataModule that builds and feeds them.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, Sampler, default_collate

from datamodules.arrays import (
    check_finite,
)
from datamodules.dataset import TrajectoryDataset, collate
from datamodules.normalizer import Normalizer, to_float
from datamodules.predict import read_predict
from datamodules.samplers import EpochSeededSampler, GlobalBatchShardSampler


def params_digest(params: Mapping[str, Any]) -> str:
    """A short stable hash of generator parameters (the cache key)."""
    text = json.dumps(params, sort_keys=True, default=str)
    return hashlib.sha1(text.encode()).hexdigest()[:10]


class TrajectoryDataModule(pl.LightningDataModule):
    """Base class: generation into a cache, splits, validation subset, normalisation, loaders.

    Args:
        data_dir: where generated data sets are cached (one sub-folder per parameter set).
        batch_size: trajectories per training batch.
        eval_batch_size: trajectories per validation / test batch (default: ``batch_size``).
        num_workers: DataLoader worker processes.
        val_trajectories: size of the fixed, evenly spaced subset of *training* trajectories on
            which validation measures the full-length rollout error (0 disables validation). A model whose
            attribute ``validate_held_out`` is true (an encoder's or a baseline's option) is not trained on them.
        normalize: normalise measurements to zero mean and unit std per channel, with statistics
            of the training set (they are saved in checkpoints with the DataModule's state).
        shuffle: shuffle the training set every epoch (order fixed by ``seed`` and the epoch).
        seed: seed of the generator and of the shuffling.
        predict_path: a ``.npy`` / ``.npz`` file (or a list, concatenated) of new sequences for
            ``python cli.py predict``, in the layouts of :mod:`datamodules.files` (``[N, T, D]``,
            ``[N, T, H, W]``, ``[N, T, C, H, W]``) and in the measurements' original units: they are
            normalised with the statistics the model was trained with.
        predict_key: the array's name inside ``.npz`` files (several sensors: each stream's array is read by
            the stream's name instead).
        predict_given: how many of each sequence's first samples the forecaster sees (``k``; default
            all of them: forecast what comes after the recording).
        predict_steps: how many steps to forecast after them (``p``; default the forecaster's
            ``n_predict``).
    """

    name = "trajectories"
    splits: tuple[str, ...] = ("train", "test")
    # generator parameters that one split alone depends on (its size, its length): testing on fewer test
    # sequences neither regenerates nor changes the training split, nor counts as other training data
    split_params: Mapping[str, tuple[str, ...]] = {}
    MEAN_TRAJECTORIES = 1000  # training trajectories (the first ones) averaged for the mean measurement

    def __init__(
        self,
        data_dir: str = "data",
        batch_size: int = 40,
        eval_batch_size: int | None = None,
        num_workers: int = 0,
        val_trajectories: int = 16,
        normalize: bool = False,
        shuffle: bool = True,
        seed: int = 0,
        predict_path: str | list[str] | None = None,
        predict_key: str = "y",
        predict_given: int | None = None,
        predict_steps: int | None = None,
    ):
        super().__init__()
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        for name, value in (("predict_given", predict_given), ("predict_steps", predict_steps)):
            if value is not None and value < 1:
                raise ValueError(f"{name} must be >= 1 (or unset), got {value}")
        self.predict_path = [predict_path] if isinstance(predict_path, (str, Path)) else predict_path
        self.predict_key, self.predict_given, self.predict_steps = predict_key, predict_given, predict_steps
        self.data_dir = Path(data_dir)
        self.batch_size = batch_size
        self.eval_batch_size = eval_batch_size or batch_size
        self.num_workers = num_workers
        self.val_trajectories = val_trajectories
        self.normalize = normalize
        self.shuffle = shuffle
        self.seed = seed
        self.datasets: dict[str, Dataset] = {}
        self._normalizer: Normalizer | None = None
        self._loaded_normalizer: Normalizer | None = None
        self._input_normalizer: Normalizer | None = None  # of the inputs "u", where the data have them
        self._loaded_input_normalizer: Normalizer | None = None
        self._saved_input_dim: int | None = None
        self._mean: torch.Tensor | None = None  # mean training measurement [*obs_shape], original units
        self._saved_obs_shape: tuple[int, ...] | None = None  # a checkpoint's, for predict before any data

    # ------------------------------------------------------------------ to implement
    @property
    def num_train_trajectories(self) -> int:
        """Number of training trajectories; must be known before the data exist."""
        raise NotImplementedError

    def generator_params(self) -> dict[str, Any]:
        """Everything the generated arrays depend on (the cache key). Not batch size etc."""
        raise NotImplementedError

    def generate(self, split: str) -> dict[str, np.ndarray]:
        """Generate one split: ``{"y": [N, T, *obs], optional "y_clean", "state"}``."""
        raise NotImplementedError

    # ------------------------------------------------------------------ cache
    def params_of(self, split: str | None, params: Mapping[str, Any] | None = None) -> dict[str, Any]:
        """The generator parameters ``split`` depends on: all but the other splits' own (``None``: none of the
        splits' own, what every split shares). ``params``: another set, e.g. a checkpoint's."""
        params = self.generator_params() if params is None else params
        others = {k for s, keys in self.split_params.items() if s != split for k in keys}
        return {k: v for k, v in params.items() if k not in others}

    @property
    def cache_dir(self) -> Path:
        """The folder of this data set's cached splits, keyed by the parameters every split shares."""
        return self.data_dir / f"{self.name}-{params_digest(self.params_of(None))}"

    def _split_prefix(self, split: str) -> str:
        """The name of a split's files in :attr:`cache_dir`, keyed by the parameters of that split alone."""
        own = {k: v for k, v in self.generator_params().items() if k in self.split_params.get(split, ())}
        return f"{split}-{params_digest(own)}" if own else split

    def split_file(self, split: str, key: str) -> Path:
        """The cached ``.npy`` file of array ``key`` (``"y"``, ``"state"``, ...) of ``split``."""
        return self.cache_dir / f"{self._split_prefix(split)}_{key}.npy"

    def _split_files(self, split: str) -> list[Path]:
        return sorted(self.cache_dir.glob(f"{self._split_prefix(split)}_*.npy"))

    def is_cached(self, split: str) -> bool:
        return (self.cache_dir / f"{self._split_prefix(split)}.done").exists()

    def stage_splits(self, stage: str | None) -> tuple[str, ...]:
        """The splits a stage reads: ``fit`` / ``validate`` the training split, ``test`` the test split,
        ``predict`` none (its files), no stage every split."""
        if stage is None:
            return tuple(self.splits)
        wanted = {"fit": ("train",), "validate": ("train",), "test": ("test",)}.get(stage, ())  # TrainerFn is a str
        return tuple(s for s in self.splits if s in wanted)

    def _trainer_stage(self) -> str | None:
        trainer = getattr(self, "trainer", None)
        return getattr(getattr(trainer, "state", None), "fn", None)

    def prepare_data(self) -> None:
        """Generate the splits the trainer's stage reads (every split outside a trainer) that are not cached yet
        (a second run reuses the cache)."""
        for split in self.stage_splits(self._trainer_stage()):
            self.prepare_split(split)

    def prepare_split(self, split: str) -> None:
        """Generate one split unless it is cached."""
        if not self.is_cached(split):
            self.save_split(split, self.generate(split))

    def save_split(self, split: str, arrays: Mapping[str, np.ndarray]) -> None:
        """Write a split atomically: a crash mid-write never leaves a half cache behind."""
        self.cache_dir.mkdir(parents=True, exist_ok=True)
        prefix = self._split_prefix(split)
        tmp = Path(tempfile.mkdtemp(prefix=f".{split}-", dir=self.cache_dir))
        try:
            for key, a in arrays.items():
                np.save(tmp / f"{prefix}_{key}.npy", a)
            for f in tmp.iterdir():
                os.replace(f, self.cache_dir / f.name)
            with open(self.cache_dir / f"{prefix}.json", "w") as fh:
                json.dump(self.params_of(split), fh, indent=2, sort_keys=True, default=str)
            (self.cache_dir / f"{prefix}.done").touch()
        finally:
            shutil.rmtree(tmp, ignore_errors=True)

    def load_arrays(self, split: str) -> dict[str, np.ndarray]:
        if not self.is_cached(split):
            raise FileNotFoundError(
                f"the {split} split of {self.name} is not in {self.cache_dir}: call prepare_data() first "
                "(the Trainer does) or check data_dir"
            )
        prefix = self._split_prefix(split)
        return {f.stem[len(prefix) + 1 :]: np.load(f, mmap_mode="r") for f in self._split_files(split)}

    def load_split(self, split: str) -> Dataset:
        """Build the data set of a split (arrays from the cache, checked for NaN / inf)."""
        arrays = self.load_arrays(split)
        for key in ("y", "y_clean"):  # further sensors' streams hold NaN where they did not sample
            if key in arrays:
                check_finite(f"{self.name} {split} '{key}'", arrays[key])
        return TrajectoryDataset(arrays, streams=self.stream_names)

    # ------------------------------------------------------------------ setup
    def setup(self, stage: str | None = None) -> None:
        """Load the splits ``stage`` reads (:meth:`stage_splits`; ``predict`` reads its files when its loader is
        asked for, once the checkpoint has given the measurement shape)."""
        for split in self.stage_splits(stage):
            self.load(split)

    def load(self, split: str) -> Dataset:
        """The data set of ``split``, loaded once (generated first if it is not cached)."""
        if split not in self.datasets:
            self.prepare_split(split)
            ds = self.load_split(split)
            if split == "train" and len(ds) != self.num_train_trajectories:
                raise RuntimeError(
                    f"{self.name}: the training split holds {len(ds)} trajectories but num_train_trajectories "
                    f"says {self.num_train_trajectories}"
                )
            self.datasets[split] = ds
            if split == "train" and self._mean is None:
                self._mean = self.compute_mean(ds)
            if self._normalizer is not None or split == "train" or not self.normalize:
                self._set_normalizer(ds)
        return self.datasets[split]

    def train_split(self) -> Dataset:
        """The training split, loaded (and generated) on first use: a test reads it only for what its checkpoint
        does not hold (:meth:`state_dict`)."""
        return self.load("train")

    def load_predict(self) -> TrajectoryDataset:
        """The sequences of ``predict_path``, whole (:func:`datamodules.predict.read_predict`): the forecaster reads
        the first ``predict_given`` samples and the rest, if any, is what followed them."""
        if not self.predict_path:
            raise ValueError(
                "nothing to predict: give the sequences to forecast with --data.init_args.predict_path FILE "
                "(.npy or .npz, the layouts of training data)"
            )
        return read_predict(
            self.predict_path,
            predict_key=self.predict_key,
            obs_shape=tuple(self.obs_shape),
            predict_given=self.predict_given,
            input_dim=self.input_dim,
            input_key=self.predict_input_key,
            sensor_layout=self.sensor_layout,
        )

    @property
    def predict_input_key(self) -> str:
        """The inputs' name in predict files: ``"u"`` (the files DataModule: its ``input_key``)."""
        return getattr(self, "input_key", None) or "u"

    def predict_dataloader(self) -> DataLoader:
        if "predict" not in self.datasets:
            self.datasets["predict"] = self.load_predict()
        return self._loader(self.datasets["predict"], self.eval_batch_size)

    def _set_normalizer(self, ds: Dataset) -> None:
        if isinstance(ds, TrajectoryDataset):
            norm = self.normalizer
            ds.normalizer = None if norm is None or norm.is_identity else norm
            if "u" in ds.arrays:
                norm = self.input_normalizer
                ds.input_normalizer = None if norm is None or norm.is_identity else norm

    @property
    def input_dim(self) -> int:
        """Inputs per step ``m`` of the data's ``"u" [N, T, m]`` (0: no inputs, an autonomous system)."""
        for ds in self.datasets.values():
            if isinstance(ds, TrajectoryDataset):
                return int(ds.arrays["u"].shape[-1]) if "u" in ds.arrays else 0
        return self._saved_input_dim or 0

    @property
    def input_normalizer(self) -> Normalizer | None:
        """The inputs' normalisation, as the measurements': a checkpoint's, the identity (``normalize: false``),
        else the training split's per-component statistics. ``None`` without inputs."""
        if self._input_normalizer is None:
            if self._loaded_input_normalizer is not None:
                self._input_normalizer = self._loaded_input_normalizer
            elif self.input_dim == 0:
                return None
            elif not self.normalize:
                self._input_normalizer = Normalizer.identity(self.input_dim, 1)
            else:
                self._input_normalizer = Normalizer(*self.compute_statistics(self.train_split(), "u"), 1)
        return self._input_normalizer

    @property
    def normalizer(self) -> Normalizer | None:
        """The measurements' normalisation: a checkpoint's (the statistics the model was trained with), the
        identity (``normalize: false``), else the training split's statistics. ``None`` before any data."""
        if self._normalizer is None:
            if self._loaded_normalizer is not None:
                self._normalizer = self._loaded_normalizer
            elif not self.datasets and self._saved_obs_shape is None:
                return None
            elif not self.normalize:
                obs_shape = self.obs_shape
                self._normalizer = Normalizer.identity(obs_shape[0], len(obs_shape))
            else:
                self._normalizer = Normalizer(*self.compute_statistics(self.train_split()), len(self.obs_shape))
        return self._normalizer

    def compute_mean(self, train: Dataset) -> torch.Tensor:
        """Mean measurement ``[*obs_shape]`` (original units) over the first :attr:`MEAN_TRAJECTORIES` training
        trajectories: the test protocol's ``mean`` reference, saved with the DataModule's state."""
        n = min(len(train), self.MEAN_TRAJECTORIES)
        total, count = None, 0
        for start in range(0, n, 64):
            items = list(range(start, min(start + 64, n)))
            batch = (
                train.__getitems__(items)
                if hasattr(train, "__getitems__")
                else default_collate([train[i] for i in items])
            )
            y = batch["y"].double()
            if isinstance(train, TrajectoryDataset) and train.normalizer is not None:
                y = train.normalizer.denormalize(y)
            observed = torch.isfinite(y)  # a sensor's missing samples (NaN) are not averaged
            s = torch.where(observed, y, 0.0).sum(dim=(0, 1))
            total = s if total is None else total + s
            count = count + observed.sum(dim=(0, 1))
        return (total / count).float()

    def mean_measurement(self) -> torch.Tensor:
        """The mean training measurement ``[*obs_shape]`` in original units (a checkpoint's, else computed)."""
        if self._mean is None:
            self._mean = self.compute_mean(self.train_split())
        return self._mean

    def compute_statistics(self, train: Dataset, key: str = "y") -> tuple[torch.Tensor, torch.Tensor]:
        """Per-channel mean and std of the training measurements (or of another array ``[N, T, C, ...]``: the
        inputs ``"u"``), float64 accumulation."""
        y = train.arrays[key] if isinstance(train, TrajectoryDataset) else None
        if y is None:
            raise NotImplementedError(f"{type(self).__name__} must implement compute_statistics")
        c = y.shape[2]
        axes = tuple(i for i in range(y.ndim) if i != 2)
        s = np.zeros(c)
        s2 = np.zeros(c)
        count = 0
        for start in range(0, len(y), 256):
            block = to_float(np.asarray(y[start : start + 256])).double().numpy()
            s += block.sum(axis=axes)
            s2 += (block**2).sum(axis=axes)
            count += block.size // c
        mean = s / count
        std = np.sqrt(np.maximum(s2 / count - mean**2, 0.0))
        return torch.tensor(mean, dtype=torch.float32), torch.tensor(std, dtype=torch.float32)

    # ------------------------------------------------------------------ sensors
    @property
    def sensor_layout(self) -> list[dict[str, Any]] | None:
        """Several sensors: ``[{"name", "shape", "noise_std"}, ...]`` in the order batches pack them
        (:mod:`ssm_ms.nets.sensors`); ``None``: one sensor, ``y`` as it is."""
        return None

    @property
    def stream_names(self) -> list[str] | None:
        layout = self.sensor_layout
        return [s["name"] for s in layout] if layout else None

    # ------------------------------------------------------------------ properties
    def _train(self) -> Dataset:
        if "train" not in self.datasets:
            raise RuntimeError(f"{type(self).__name__}.setup() has not run yet")
        return self.datasets["train"]

    def _loaded(self) -> Dataset:
        """A loaded split (the training one first) for what every split shares."""
        for split in ("train", *self.splits):
            if split in self.datasets:
                return self.datasets[split]
        raise RuntimeError(f"{type(self).__name__}.setup() has not run yet")

    @property
    def seq_len(self) -> int:
        """Length of the training sequences (of the loaded split's where the training split is not loaded)."""
        return self._loaded().seq_len

    @property
    def obs_shape(self) -> tuple[int, ...]:
        if self.datasets:
            return self._loaded().obs_shape
        if self._saved_obs_shape is not None:  # predict: from the checkpoint, before any data are read
            return self._saved_obs_shape
        return self.train_split().obs_shape

    def val_indices(self) -> np.ndarray:
        n = len(self._train())
        k = min(self.val_trajectories, n)
        return np.unique(np.linspace(0, n - 1, k).round().astype(np.int64)) if k > 0 else np.zeros(0, np.int64)

    def check_range(self, low: float, high: float, why: str) -> None:
        """Refuse training measurements outside ``[low, high]`` (after normalisation), before training.

        ``why`` says what needs the range (e.g. ``"loss: bce"``). Checked in chunks on the served values;
        data sets that are not arrays are not checked.
        """
        train = self._train()
        if not isinstance(train, TrajectoryDataset):
            return
        if train.normalizer is not None:
            raise ValueError(
                f"{why} needs measurements in [{low}, {high}], but data.normalize is on (zero mean, unit std): "
                "set data.init_args.normalize to false, or use loss: mse"
            )
        y = train.arrays["y"]
        if y.dtype == np.uint8:  # served as y / 255
            return
        lo, hi = np.inf, -np.inf
        for start in range(0, len(y), 256):
            block = np.asarray(y[start : start + 256])
            lo, hi = min(lo, float(block.min())), max(hi, float(block.max()))
        if lo < low or hi > high:
            raise ValueError(
                f"{why} needs measurements in [{low}, {high}], but the training data range from {lo:.4g} to "
                f"{hi:.4g}: rescale the data to [{low}, {high}] (images: divide by their maximum), or use loss: mse"
            )

    def node_measurements(self, n_nodes: int) -> torch.Tensor:
        """Training measurements at the shooting nodes' times: ``[N, n_nodes, *obs_shape]`` (normalised).

        Used to start nodes at measured values (``MultipleShootingModule(node_init_map=...)``).
        """
        train = self._train()
        if not isinstance(train, TrajectoryDataset):
            raise NotImplementedError(f"{type(self).__name__} does not support starting nodes at measurements")
        y = train.arrays["y"]
        n = y.shape[1] // n_nodes
        out = to_float(np.asarray(y[:, ::n][:, :n_nodes]))
        return out if train.normalizer is None else train.normalizer.normalize(out)

    # ------------------------------------------------------------------ loaders
    def _loader(self, ds: Dataset, batch_size: int, sampler: Sampler | None = None) -> DataLoader:
        self._set_normalizer(ds)  # resolved now: a checkpoint's statistics have been restored by then
        return DataLoader(
            ds,
            batch_size=batch_size,
            sampler=sampler,
            collate_fn=collate,
            num_workers=self.num_workers,
            persistent_workers=self.num_workers > 0,
        )

    def train_dataloader(self) -> DataLoader:
        ds = self._train()
        trainer = self.trainer
        if getattr(trainer.lightning_module if trainer is not None else None, "validate_held_out", False):
            held_out = self.val_indices()
            if len(held_out) == 0:
                raise ValueError(
                    "validate_held_out holds the validation trajectories out of training, but there are none: set "
                    "data.init_args.val_trajectories > 0"
                )
            if len(held_out) >= len(ds):
                raise ValueError(
                    f"validate_held_out holds out all {len(ds)} training trajectories (val_trajectories="
                    f"{self.val_trajectories}): set data.init_args.val_trajectories below {len(ds)}"
                )
            ds = self.subset(ds, np.setdiff1d(np.arange(len(ds)), held_out))
        world = trainer.world_size if trainer is not None else 1
        if world > 1:  # batch_size stays the global batch: the same training on any number of devices
            sampler = GlobalBatchShardSampler(
                len(ds), self.batch_size, world, trainer.global_rank, self.seed, self.shuffle
            )
            return self._loader(ds, self.batch_size // world, sampler)
        return self._loader(ds, self.batch_size, EpochSeededSampler(len(ds), self.seed, self.shuffle))

    def val_dataloader(self) -> DataLoader | list:
        idx = self.val_indices()
        if len(idx) == 0:
            return []
        return self._loader(self.subset(self._train(), idx), self.eval_batch_size)

    def subset(self, ds: Dataset, indices: np.ndarray) -> Dataset:
        """The trajectories ``indices`` of ``ds``, keeping their index (override for non-array data)."""
        assert isinstance(ds, TrajectoryDataset)
        return TrajectoryDataset(ds.arrays, ds.normalizer, ds.indices[indices], ds.input_normalizer, ds.streams)

    def test_dataloader(self) -> DataLoader:
        return self._loader(self.load("test"), self.eval_batch_size)

    # ------------------------------------------------------------------ checkpoint
    def state_dict(self) -> dict[str, Any]:
        """Saved in every checkpoint: what the data were, and what a test needs from the training data (the
        normalisation statistics, the mean measurement, the measurements' shape)."""
        state: dict[str, Any] = {"name": self.name, "generator_params": self._safe_generator_params()}
        if self.normalizer is not None:
            state["normalizer"] = self.normalizer.state_dict()
        if self.input_normalizer is not None:
            state["input_normalizer"] = self.input_normalizer.state_dict()
            state["input_dim"] = self.input_dim
        if self._mean is not None:
            state["mean_measurement"] = self._mean.clone()
        if self.datasets or self._saved_obs_shape is not None:
            state["obs_shape"] = list(self.obs_shape)
        return state

    def _safe_generator_params(self) -> dict[str, Any] | None:
        try:
            return json.loads(json.dumps(self.generator_params(), default=str))
        except NotImplementedError:
            return None

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        if "input_normalizer" in state_dict:
            self._loaded_input_normalizer = self._input_normalizer = Normalizer.from_state_dict(
                state_dict["input_normalizer"]
            )
            self._saved_input_dim = int(state_dict.get("input_dim", self._loaded_input_normalizer.mean.numel()))
        if "normalizer" in state_dict:
            self._loaded_normalizer = self._normalizer = Normalizer.from_state_dict(state_dict["normalizer"])
            for ds in self.datasets.values():
                self._set_normalizer(ds)
        if state_dict.get("mean_measurement") is not None:
            self._mean = torch.as_tensor(state_dict["mean_measurement"], dtype=torch.float32)
        if state_dict.get("obs_shape") is not None:
            self._saved_obs_shape = tuple(int(d) for d in state_dict["obs_shape"])
