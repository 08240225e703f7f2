"""The identification benchmarks of nonlinearbenchmark.org (Silverbox, Wiener-Hammerstein, EMPS, Cascaded Tanks, ...),
read by their official loader (PyPI ``nonlinear-benchmarks``; ``pip install -e '.[benchmarks]'``).

Each benchmark is a training recording and one or more test recordings of a physical system driven by a known input
``u``, measured through its output ``y``. The benchmarks' rules, kept here: the test recordings decide nothing (they are
served only to ``test``); the end of the training recording (``val_fraction``) is held out as the validation recording,
which chooses the epoch kept and the model order; the rest is cut into training windows (:mod:`datamodules.windows`),
normalised with their statistics (saved in checkpoints). Splits: ``train`` (windows), ``val`` (the held-out end, one
whole sequence), ``test`` (each test recording whole, one data loader each, in the loader's order). ``val_at`` holds out
another segment of the same length instead (the windows cut from the samples before and after it): one fit per
segment is a cross-validation over time, for choices one held-out end is too short to make.

The benchmark's protocol (:mod:`ssm_ms.inference.simulation`): the state from a test recording's first ``n_init``
samples, then a free-run simulation of the rest from its inputs alone, scored by the loader's own
``error_metrics.RMSE`` in the benchmark's unit (``unit``, ``unit_scale``: the factor from the files' units to it).
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any

import numpy as np
from torch.utils.data import DataLoader

from datamodules.dataset import TrajectoryDataset
from datamodules.recordings import Recordings
from datamodules.windows import default_window

EXTRA = "pip install -e '.[benchmarks]' (or: pip install nonlinear-benchmarks==1.0.1 rarfile progressbar)"


def loader_module() -> Any:
    """The official loader, or one message naming the fix where it is not installed."""
    try:
        return importlib.import_module("nonlinear_benchmarks")
    except ImportError:
        raise ValueError(f"the benchmarks need their official loader, nonlinear-benchmarks: {EXTRA}") from None


def loader_names(nb: Any) -> list[str]:
    """The benchmarks the loader knows with a train / test split."""
    names = getattr(nb, "all_splitted_benchmarks", None)
    return sorted(f.__name__ for f in names) if names else sorted(n for n in dir(nb) if n[:1].isupper())


def load_benchmark(name: str, dir_placement: str | None = None) -> tuple[Any, list[Any]]:
    """``(train, [test, ...])`` of the loader's ``name`` (``Input_output_data`` each), its files under
    ``dir_placement`` (``None``: the loader's cache, ``~/.nonlinear_benchmarks``, downloaded once)."""
    nb = loader_module()
    known = loader_names(nb)
    if name not in known:
        raise ValueError(f"unknown benchmark {name!r}: the loader knows {', '.join(known)}")
    if dir_placement is not None and not Path(dir_placement).is_dir():
        raise ValueError(
            f"dir_placement {dir_placement}: no such folder; give the folder holding the benchmark's files (the "
            "loader's layout, e.g. ../shared/data/nonlinear_benchmarks), or leave it unset to download them"
        )
    try:
        train, test = getattr(nb, name)(dir_placement=dir_placement)
    except Exception as err:  # no file and no internet: the loader's download fails (a plain Exception of its own)
        where = dir_placement or "~/.nonlinear_benchmarks"
        raise ValueError(
            f"benchmark {name}: its files are not in {where} and could not be downloaded ({err}); give dir_placement "
            "a folder holding them (the loader's layout), or run once where the internet is reachable"
        ) from None
    return train, list(test) if isinstance(test, (list, tuple)) else [test]


def _sequence(y: np.ndarray, u: np.ndarray) -> dict[str, np.ndarray]:
    """One recording ``y [T]`` / ``[T, p]``, ``u`` likewise as a batch of one: ``{"y": [1, T, p], "u": [1, T, m]}``."""
    y = np.asarray(y, dtype=np.float32).reshape(len(y), -1)
    u = np.asarray(u, dtype=np.float32).reshape(len(u), -1)
    return {"y": y[None], "u": u[None]}


class BenchmarkDataModule(Recordings):
    """A nonlinearbenchmark.org benchmark through its official loader (the module's docstring: splits, rules).

    Args:
        benchmark: the loader's name of it (``Silverbox``, ``WienerHammerBenchMark``, ``EMPS``, ``Cascaded_Tanks``,
            ...); an unknown name is refused with the loader's list.
        dir_placement: the folder of the benchmark files in the loader's layout (``None``: the loader's own cache,
            downloading them where the internet is reachable; the tests use ``../shared/data/nonlinear_benchmarks``).
        val_fraction: the end of the training recording held out for validation (default 0.2: a fifth).
        val_at: where the held-out segment (``val_fraction`` of the recording) starts, as a fraction of the training
            recording (default ``None``: ``1 - val_fraction``, its end). With ``val_fraction`` 0.2, the fits at
            ``val_at`` 0, 0.2, 0.4, 0.6 and 0.8 hold out each fifth once (a cross-validation over time); the training
            windows are cut from the samples before the segment and after it, at the window the end's fit uses.
        val_run_in: samples of the training recording before its held-out segment that each validation simulation runs
            through first, the state estimated from their first ``n_init``, scored on the held-out segment only (0,
            the default: the segment alone, its first ``n_init`` samples given; ``"all"``: every sample before it,
            so that the validation of the end simulates as many steps as a test recording of the training
            recording's length).
        window, stride: the training windows cut from the rest (:class:`~datamodules.recordings.Recordings`).
        n_init: samples of each recording given to estimate its initial state (default: the loader's
            ``state_initialization_window_length`` of the test recordings).
        unit, unit_scale: the unit the benchmark reports in and the factor from the files' units to it (Silverbox:
            ``mV`` and 1000, the files hold volts).
        test_names: names of the test recordings (default: the loader's, numbered where they repeat).
        **kwargs: :class:`~datamodules.recordings.Recordings`' ``batch_size``, ``seed``, ``normalize``, ...
    """

    def __init__(
        self,
        benchmark: str,
        dir_placement: str | None = None,
        val_fraction: float = 0.2,
        val_at: float | None = None,
        val_run_in: int | str = 0,
        window: int | None = None,
        stride: int | None = None,
        n_init: int | None = None,
        unit: str = "",
        unit_scale: float = 1.0,
        test_names: list[str] | None = None,
        **kwargs: Any,
    ):
        if not 0.0 < val_fraction < 1.0:
            raise ValueError(
                f"val_fraction must be in (0, 1): the end of the training recording held out, got {val_fraction}"
            )
        if not unit_scale > 0:
            raise ValueError(f"unit_scale must be > 0 (the files' units to the reported one), got {unit_scale}")
        last = 1.0 - val_fraction
        if val_at is not None and not 0.0 <= val_at <= last + 1e-9:
            raise ValueError(
                f"val_at must be in [0, {last:g}] (1 - val_fraction: the held-out segment inside the training "
                f"recording), got {val_at}"
            )
        train, tests = load_benchmark(benchmark, dir_placement)
        y_all, u_all = np.asarray(train.y), np.asarray(train.u)
        length = len(y_all) - int(round(len(y_all) * last))  # the held-out segment's samples
        cut = len(y_all) - length if val_at is None else min(int(round(len(y_all) * val_at)), len(y_all) - length)
        end = cut + length
        if val_run_in == "all":
            val_run_in = cut
        if not isinstance(val_run_in, int) or not 0 <= val_run_in <= cut:
            raise ValueError(
                f"val_run_in must be 'all' or a number of samples in [0, {cut}] (the training part before the "
                f"held-out segment), got {val_run_in!r}"
            )
        pieces = [(a, b) for a, b in ((0, cut), (end, len(y_all))) if b > a]  # the training part, around the segment
        dt = getattr(train, "sampling_time", None)
        super().__init__(
            y=[y_all[a:b] for a, b in pieces],
            u=[u_all[a:b] for a, b in pieces],
            dt=float(dt) if dt else None,
            window=window if window is not None else default_window([len(y_all) - length]),
            stride=stride,
            **kwargs,
        )
        self.benchmark, self.dir_placement, self.val_fraction = benchmark, dir_placement, float(val_fraction)
        self.val_at, self.val_run_in = val_at, val_run_in
        self.name = benchmark.lower()
        self.unit, self.unit_scale = unit, float(unit_scale)
        given = {int(t.state_initialization_window_length) for t in tests if t.state_initialization_window_length}
        self.n_init = int(n_init) if n_init is not None else (max(given) if given else 0)
        if self.n_init < 1:
            raise ValueError(
                f"benchmark {benchmark}: the loader gives no n_init: "
                "give n_init, the samples to estimate the state from"
            )
        self._sequences = {
            "train": [_sequence(y_all[a:b], u_all[a:b]) for a, b in pieces],
            "val": [_sequence(y_all[cut - val_run_in : end], u_all[cut - val_run_in : end])],
            "test": [_sequence(t.y, t.u) for t in tests],
        }
        if val_run_in + self.val_length <= self.val_scored_from:
            raise ValueError(
                f"val_fraction={val_fraction} leaves no held-out sample to score after the n_init={self.n_init} "
                "given: raise it (or val_run_in)"
            )
        names = list(test_names) if test_names is not None else _unique([str(t.name) for t in tests])
        if len(names) != len(tests):
            raise ValueError(f"test_names names {len(names)} test recordings, the benchmark has {len(tests)}")
        self.test_names = names
        self.splits = ("train", "val", "test")

    def stage_splits(self, stage: str | None) -> tuple[str, ...]:
        """``fit`` and ``validate`` load the training windows; the held-out recordings are served whole
        (:meth:`sequences`), never as a split of windows."""
        return ("train",) if stage in (None, "fit", "validate") else ()

    def generator_params(self) -> dict[str, Any]:
        return {
            "benchmark": self.benchmark,
            "val_fraction": self.val_fraction,
            "val_at": self.val_at,
            "val_run_in": self.val_run_in,
            **super().generator_params(),
        }

    # ------------------------------------------------------------------ the held-out recordings
    def load_split(self, split: str) -> TrajectoryDataset:
        if split == "train":
            return super().load_split(split)
        if split == "val":
            return TrajectoryDataset(self._sequences["val"][0])
        raise ValueError(f"the benchmark's test recordings are served one loader each: test_dataloader(), not {split}")

    def sequences(self, split: str) -> list[TrajectoryDataset]:
        """The whole recordings of ``split`` (``"val"``: the held-out segment after its ``val_run_in``; ``"test"``: the
        test recordings; ``"train"``: the parts the windows are cut from, before and after the segment), each a data
        set of one sequence, normalised with the training statistics."""
        out = [TrajectoryDataset(arrays) for arrays in self._sequences[split]]
        for ds in out:
            self._set_normalizer(ds)
        return out

    def raw_recordings(self, split: str) -> list[tuple[np.ndarray, np.ndarray]]:
        """``[(y [T, p], u [T, m]), ...]`` of ``split`` in the files' units, whole (``"train"``: the training
        recording less its held-out segment, the parts the windows are cut from; ``"val"``: the held-out segment,
        without ``val_run_in``): for a peer trained on the same data."""
        start = self.val_run_in if split == "val" else 0
        return [(arrays["y"][0, start:], arrays["u"][0, start:]) for arrays in self._sequences[split]]

    def test_dataloader(self) -> list[DataLoader]:
        return [self._loader(ds, 1) for ds in self.sequences("test")]

    def split_dataloader(self, split: str) -> DataLoader | list[DataLoader]:
        """The whole recordings of ``"val"`` (one loader) or ``"test"`` (one each)."""
        loaders = [self._loader(ds, 1) for ds in self.sequences(split)]
        return loaders[0] if split == "val" else loaders

    @property
    def val_length(self) -> int:
        """Samples held out of the training recording (``val_run_in`` not counted)."""
        return int(self._sequences["val"][0]["y"].shape[1]) - self.val_run_in

    @property
    def val_scored_from(self) -> int:
        """The first sample of the validation simulation that is scored: the held-out segment's first after the run-in,
        and never one of the ``n_init`` given to estimate the state."""
        return max(self.n_init, self.val_run_in)


def _unique(names: list[str]) -> list[str]:
    """Names made unique by numbering the repeated ones (``a``, ``a (2)``)."""
    out = []
    for name in names:
        k = sum(1 for n in names[: len(out)] if n == name)
        out.append(name if k == 0 else f"{name} ({k + 1})")
    return out
