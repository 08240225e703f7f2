"""Shared fixtures: a tiny rotation system as a DataModule, trainer settings for fast CPU runs, and
``decoder_path``, which runs a decoder test twice: with the backend ``"native"`` and with ``"torch"``.

The ConvDecoder has two float32 CPU paths with the same values: the native kernels (ssm_ms/nets/native/), which
backend ``"auto"`` takes where they build (AVX-512 or AVX2 with FMA, a C compiler) and are faster, and the torch
path. A test run on one machine would otherwise exercise only one of them, so the other could rot unseen: a test
that asks for ``decoder_path`` runs once per backend in the same pytest process (``[native]`` is skipped, with the
reason, where the kernels cannot be built, and fails instead with ``SSM_MS_REQUIRE_NATIVE=1``)."""

from __future__ import annotations

import math
import os
import warnings
from pathlib import Path

import lightning.pytorch as pl
import numpy as np
import pytest
import torch

from datamodules.base import TrajectoryDataModule
from ssm_ms.module import MultipleShootingModule
from ssm_ms.nets import LocallyLinearTransition, Projection, native
from ssm_ms.schedule import ShootingSchedule

ROOT = Path(__file__).resolve().parents[1]


def pytest_collection_modifyitems(config, items):
    """The tests marked ``longest`` first (in their order), the rest as collected: under ``make test``'s two workers a
    test of minutes then runs beside the others from the start, not alone after them (as the README's test did, ~2.5
    minutes of the suite's ~8 on the slowest CPUs, when it came in file order)."""
    items.sort(key=lambda item: item.get_closest_marker("longest") is None)


# what the project commits as results: a test writes its own into tmp_path, never here
COMMITTED_OUTPUTS = ("results", "benchmarks/results", "pretrained")
STUDY_RESULTS = ("*.md", "*.png", "*.json")  # studies/<question>/: its results files (its script may be edited)


def committed_outputs() -> dict[str, tuple[int, int]]:
    """``{path: (size, mtime_ns)}`` of every file under :data:`COMMITTED_OUTPUTS`, and of the studies' results."""
    files = [p for folder in COMMITTED_OUTPUTS for p in (ROOT / folder).rglob("*")]
    files += [p for pattern in STUDY_RESULTS for p in (ROOT / "studies").glob(f"*/{pattern}")]
    return {str(p.relative_to(ROOT)): (p.stat().st_size, p.stat().st_mtime_ns) for p in files if p.is_file()}


@pytest.fixture(scope="session", autouse=True)
def committed_outputs_untouched():
    """Fail the session if a test wrote into the committed results, benchmarks' figures or pretrained files (a
    forecaster left at its default ``results_dir`` writes ``results/<data set>.json`` of the working tree)."""
    before = committed_outputs()
    yield
    after = committed_outputs()
    changed = sorted(k for k in before.keys() | after.keys() if before.get(k) != after.get(k))
    assert not changed, f"tests wrote into committed outputs (give them tmp_path): {changed}"


if "OMP_NUM_THREADS" not in os.environ:  # the CI machine's 2 cores; OMP_NUM_THREADS=1 on a shared machine
    torch.set_num_threads(2)


@pytest.fixture(autouse=True)
def torch_threads_restored():
    """Each test leaves torch's thread count as it found it: a benchmark script run in a test sets its own (2), and
    under ``make test``'s two workers of one thread each that would put four threads on two cores for every later
    test of that worker (OpenMP's spinning then made a 2-s test take two minutes)."""
    threads = torch.get_num_threads()
    yield
    if torch.get_num_threads() != threads:
        torch.set_num_threads(threads)


warnings.filterwarnings("ignore", ".*does not have many workers.*")
warnings.filterwarnings("ignore", ".*GPU available but not used.*")
warnings.filterwarnings("ignore", ".*LeafSpec.*")


class RotationDataModule(TrajectoryDataModule):
    """A 2-D rotation ``x[t+1] = R(omega) x[t]`` measured through its first component plus noise."""

    name = "rotation"
    split_params = {"train": ("n_train",), "test": ("n_test",)}

    def __init__(
        self,
        n_train: int = 8,
        n_test: int = 4,
        seq_len: int = 12,
        omega: float = 0.3,
        noise_std: float = 0.05,
        nan_at: tuple[int, int] | None = None,
        **kwargs,
    ):
        super().__init__(**kwargs)
        self.n_train, self.n_test, self.length = n_train, n_test, seq_len
        self.omega, self.noise_std, self.nan_at = omega, noise_std, nan_at

    @property
    def num_train_trajectories(self) -> int:
        return self.n_train

    def generator_params(self) -> dict:
        return {
            "n_train": self.n_train,
            "n_test": self.n_test,
            "seq_len": self.length,
            "omega": self.omega,
            "noise_std": self.noise_std,
            "nan_at": self.nan_at,
            "seed": self.seed,
        }

    def generate(self, split: str) -> dict[str, np.ndarray]:
        rng = np.random.default_rng([self.seed, 0 if split == "train" else 1])
        n = self.n_train if split == "train" else self.n_test
        phase = rng.uniform(0, 2 * math.pi, size=(n, 1)) + self.omega * np.arange(self.length)
        state = np.stack([np.cos(phase), np.sin(phase)], axis=-1).astype(np.float32)
        y_clean = state[..., :1].copy()
        y = y_clean + self.noise_std * rng.standard_normal(y_clean.shape).astype(np.float32)
        if self.nan_at is not None and split == "train":
            y[self.nan_at] = np.nan
        return {"y": y, "y_clean": y_clean, "state": state}


def rotation_model(**kwargs) -> MultipleShootingModule:
    torch.manual_seed(0)
    args = dict(state_dim=2, n_nodes=3, lr=1e-2)
    args.update(kwargs)
    d = args["state_dim"]
    return MultipleShootingModule(LocallyLinearTransition(d, n_matrices=4, hidden=16), Projection([0]), **args)


class ConstantSchedule(ShootingSchedule):
    """:meth:`ShootingSchedule.constant` for any module (a forecaster has no alpha: nothing to hold)."""

    def __init__(self):
        super().__init__(alpha_epoch=None, lr_milestones=())

    def on_fit_start(self, trainer, pl_module):
        if hasattr(pl_module, "alpha"):
            super().on_fit_start(trainer, pl_module)

    def on_train_epoch_start(self, trainer, pl_module):
        if hasattr(pl_module, "alpha"):
            super().on_train_epoch_start(trainer, pl_module)


def fast_trainer(tmp_path, max_epochs: int, callbacks=(), **kwargs) -> pl.Trainer:
    """A quick CPU trainer. Its fits keep alpha and lr constant unless ``callbacks`` hold a schedule (the model adds
    the paper's to a fit that names none: tests/test_api.py tests that)."""
    if not any(isinstance(c, ShootingSchedule) for c in callbacks):
        callbacks = [*callbacks, ConstantSchedule()]
    args = dict(
        max_epochs=max_epochs,
        accelerator="cpu",
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        default_root_dir=str(tmp_path),
        callbacks=list(callbacks),
        num_sanity_val_steps=0,
        deterministic=True,
    )
    args.update(kwargs)
    return pl.Trainer(**args)


REQUIRE_NATIVE_ENV = "SSM_MS_REQUIRE_NATIVE"


def native_or_skip() -> None:
    """Skip the test, saying why, where the native kernels cannot be built; with ``SSM_MS_REQUIRE_NATIVE=1`` (on a
    machine where they should build) fail it instead, so that a broken build cannot hide behind a skip."""
    if native.library() is None:
        message = f"native kernels unavailable: {native.unavailable_reason()}"
        if os.environ.get(REQUIRE_NATIVE_ENV, "") == "1":
            pytest.fail(f"{message} ({REQUIRE_NATIVE_ENV}=1 is set)")
        pytest.skip(message)


@pytest.fixture
def needs_native() -> None:
    native_or_skip()


@pytest.fixture(params=["native", "torch"])
def decoder_path(request) -> str:
    """The ConvDecoder backend under test, ``"native"`` or ``"torch"`` (see the module docstring)."""
    if request.param == "native":
        native_or_skip()
    return request.param


@pytest.fixture
def rotation_dm(tmp_path):
    return RotationDataModule(data_dir=str(tmp_path / "data"), batch_size=4, val_trajectories=2)


class ExactRotation(torch.nn.Module):
    """The true transition of RotationDataModule: rotation by ``omega`` (a learnable angle)."""

    def __init__(self, omega: float = 0.3, learnable: bool = True):
        super().__init__()
        self.state_dim = 2
        if learnable:
            self.omega = torch.nn.Parameter(torch.tensor(float(omega)))
        else:
            self.register_buffer("omega", torch.tensor(float(omega)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        c, s = torch.cos(self.omega), torch.sin(self.omega)
        return torch.stack([c * x[:, 0] - s * x[:, 1], s * x[:, 0] + c * x[:, 1]], dim=1)
