"""Shared fixtures: a tiny rotation system as a DataModule, trainer settings for fast CPU runs, and
``decoder_path``, which runs a decoder test twice: through the native kernels and through the torch-only path.

The ConvDecoder has two float32 CPU paths with the same values (ssm_ms/nets/native/): the native kernels, taken
wherever they can be built (AVX-512 or AVX2 with FMA, a C compiler), and the torch-only path, taken everywhere else.
A test run on one machine would otherwise exercise only one of them, so the other could rot unseen: a test that
asks for ``decoder_path`` runs once per path in the same pytest process (``[native]`` is skipped, with the reason,
where the kernels cannot be built; ``[torch-only]`` sets ``SSM_MS_NATIVE=0`` and forgets any loaded library for
the test's duration, so subprocesses it starts take that path too)."""

from __future__ import annotations

import math
import os
import warnings

import lightning.pytorch as pl
import numpy as np
import pytest
import torch

from datamodules.base import TrajectoryDataModule
from ssm_ms.module import MultipleShootingModule
from ssm_ms.nets import LocallyLinearTransition, Projection, native

if "OMP_NUM_THREADS" not in os.environ:  # the CI machine's 2 cores; OMP_NUM_THREADS=1 on a shared machine
    torch.set_num_threads(2)
warnings.filterwarnings("ignore", ".*does not have many workers.*")
warnings.filterwarnings("ignore", ".*GPU available but not used.*")
warnings.filterwarnings("ignore", ".*LeafSpec.*")


class RotationDataModule(TrajectoryDataModule):
    """A 2-D rotation ``x[t+1] = R(omega) x[t]`` measured through its first component plus noise."""

    name = "rotation"

    def __init__(self, n_train: int = 8, n_test: int = 4, seq_len: int = 12, omega: float = 0.3,
                 noise_std: float = 0.05, nan_at: tuple[int, int] | None = None, **kwargs):
        super().__init__(**kwargs)
        self.n_train, self.n_test, self.length = n_train, n_test, seq_len
        self.omega, self.noise_std, self.nan_at = omega, noise_std, nan_at

    @property
    def num_train_trajectories(self) -> int:
        return self.n_train

    def generator_params(self) -> dict:
        return {"n_train": self.n_train, "n_test": self.n_test, "seq_len": self.length, "omega": self.omega,
                "noise_std": self.noise_std, "nan_at": self.nan_at, "seed": self.seed}

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


def fast_trainer(tmp_path, max_epochs: int, callbacks=(), **kwargs) -> pl.Trainer:
    args = dict(max_epochs=max_epochs, accelerator="cpu", logger=False, enable_progress_bar=False,
                enable_model_summary=False, default_root_dir=str(tmp_path), callbacks=list(callbacks),
                num_sanity_val_steps=0, deterministic=True)
    args.update(kwargs)
    return pl.Trainer(**args)


@pytest.fixture(params=["native", "torch-only"])
def decoder_path(request, monkeypatch) -> str:
    """The ConvDecoder's float32 CPU path for this test: ``"native"`` or ``"torch-only"`` (see the module docstring)."""
    if request.param == "native":
        if native.library() is None:
            pytest.skip(f"native kernels unavailable: {native.unavailable_reason()}")
    else:
        monkeypatch.setenv("SSM_MS_NATIVE", "0")
        monkeypatch.setattr(native.build, "_state", {})
        assert native.library() is None
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
