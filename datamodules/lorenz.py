"""The Lorenz system observed through its first coordinate only, with heavy Gaussian noise.

The paper's set-up: ``sigma, beta, rho = 10, 8/3, 28``, RK4 with ``dt = 0.005`` (one sample per
step), initial states uniform in ``[-10, 10]^3``; the measurement is ``x_1 + N(0, 2.5^2)``.
Training: 1000 trajectories of 50 s (10,000 samples); test: 1000 trajectories of 10 s (2000
samples). For the trajectory-length study the training trajectories are cut into consecutive pieces
of ``piece_length`` samples (10, 100, 1000 or 10,000), which keeps the number of samples: the cache
holds the uncut set once and the pieces are a reshaped view of it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import partial
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from datamodules.base import TrajectoryDataModule
from datamodules.dataset import TrajectoryDataset

SPLIT_STREAMS = {"train": 0, "test": 1}  # spawn keys: independent random streams per split from one seed


def lorenz_wing_level(beta: float = 8.0 / 3.0, rho: float = 28.0) -> float:
    """``0.5 * sqrt(beta (rho - 1))``: half the distance from 0 of the Lorenz fixed points' ``x`` (~4.24)."""
    if not beta * (rho - 1) > 0:
        raise ValueError(f"the Lorenz wings need beta * (rho - 1) > 0, got beta={beta!r}, rho={rho!r}")
    return 0.5 * math.sqrt(beta * (rho - 1))


def lorenz_rk4(
    x0: np.ndarray,
    steps: int,
    dt: float = 0.005,
    sigma: float = 10.0,
    beta: float = 8.0 / 3.0,
    rho: float = 28.0,
    out_dtype: Any = np.float64,
    progress: str | None = None,
) -> np.ndarray:
    """Integrate the Lorenz system with classical RK4, vectorised over trajectories.

    Args:
        x0: initial states ``[N, 3]``.
        steps: samples per trajectory; sample ``k`` is the state after ``k`` steps (sample 0 is ``x0``).
        out_dtype: dtype of the returned array (the integration itself runs in float64).
        progress: description of a tqdm progress bar (``None``: no bar).

    Returns:
        States ``[N, steps, 3]``.
    """
    x0 = np.asarray(x0, dtype=np.float64)
    if x0.ndim != 2 or x0.shape[1] != 3:
        raise ValueError(f"x0 must have shape [N, 3], got {x0.shape}")
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    n = len(x0)
    # Component-major working arrays [3, N]: each component is one contiguous row.
    x = np.ascontiguousarray(x0.T)
    k1, k2, k3, k4, tmp = (np.empty_like(x) for _ in range(5))
    out = np.empty((steps, 3, n), dtype=out_dtype)  # time-major while integrating: contiguous writes
    out[0] = x

    def rhs(s: np.ndarray, k: np.ndarray) -> np.ndarray:
        np.subtract(s[1], s[0], out=k[0])
        k[0] *= sigma
        np.subtract(rho, s[2], out=k[1])
        k[1] *= s[0]
        k[1] -= s[1]
        np.multiply(s[0], s[1], out=k[2])
        k[2] -= beta * s[2]
        return k

    half = 0.5 * dt
    for t in tqdm(range(1, steps), desc=progress, unit="step", disable=progress is None, mininterval=0.5):
        rhs(x, k1)
        np.multiply(k1, half, out=tmp)
        tmp += x
        rhs(tmp, k2)
        np.multiply(k2, half, out=tmp)
        tmp += x
        rhs(tmp, k3)
        np.multiply(k3, dt, out=tmp)
        tmp += x
        rhs(tmp, k4)
        k2 += k3
        k2 *= 2.0
        k1 += k4
        k1 += k2
        k1 *= dt / 6.0
        x += k1
        out[t] = x
    return np.ascontiguousarray(out.transpose(2, 0, 1))


def lorenz_rk4_step(
    x: torch.Tensor, dt: float = 0.005, sigma: float = 10.0, beta: float = 8.0 / 3.0, rho: float = 28.0
) -> torch.Tensor:
    """One classical RK4 step of the Lorenz system in torch: ``[N, 3] -> [N, 3]``.

    The same scheme, with the same order of operations, as :func:`lorenz_rk4`, so iterating it
    reproduces that integrator to float64 rounding; it runs in ``x``'s dtype and device and is
    differentiable (the true system's Jacobians, e.g. for :func:`ssm_ms.analysis.lyapunov_spectrum`).
    Any leading batch shape ``[..., 3]`` works.
    """
    if x.dim() < 1 or x.shape[-1] != 3:
        raise ValueError(f"x must have shape [N, 3] (Lorenz states), got {tuple(x.shape)}")

    def rhs(s: torch.Tensor) -> torch.Tensor:
        a, b, c = s.unbind(-1)
        return torch.stack([sigma * (b - a), (rho - c) * a - b, a * b - beta * c], dim=-1)

    half = 0.5 * dt
    k1 = rhs(x)
    k2 = rhs(x + k1 * half)
    k3 = rhs(x + k2 * half)
    k4 = rhs(x + k3 * dt)
    return x + ((k1 + k4) + (k2 + k3) * 2.0) * (dt / 6.0)


class LorenzDataModule(TrajectoryDataModule):
    """Noisy first-coordinate measurements of the Lorenz system (the paper's Lorenz experiment).

    Batches hold ``y`` (``[B, T, 1]``, noisy, normalised by default), ``y_clean`` (noiseless ``x_1``,
    same normalisation) and ``state`` (the true 3-D state, original units).

    Args:
        piece_length: samples per training trajectory after cutting the generated trajectories into
            consecutive pieces; must divide ``train_steps`` (paper: 10, 100, 1000 or 10,000).
            ``None`` (default): ``train_steps``, i.e. uncut.
        n_train: generated training trajectories.
        train_steps: samples per generated training trajectory (50 s at ``dt = 0.005``).
        n_test: test trajectories.
        test_steps: samples per test trajectory (10 s); the test set is never cut.
        dt: RK4 step and sampling period.
        sigma, beta, rho: Lorenz parameters.
        init_range: initial states are uniform in ``[-init_range, init_range]^3``.
        noise_std: standard deviation of the Gaussian measurement noise.
        seed: seed of the generator (train and test use separate streams) and of the shuffling.
        normalize: normalise with training statistics (default here: on).
        **kwargs: the other :class:`~datamodules.base.TrajectoryDataModule` arguments (``data_dir``,
            ``batch_size``, ``eval_batch_size``, ``num_workers``, ``val_trajectories``, ``shuffle``).
    """

    name = "lorenz"
    splits = ("train", "test")
    split_params = {"train": ("n_train", "train_steps"), "test": ("n_test", "test_steps")}

    def __init__(
        self,
        piece_length: int | None = None,
        n_train: int = 1000,
        train_steps: int = 10_000,
        n_test: int = 1000,
        test_steps: int = 2000,
        dt: float = 0.005,
        sigma: float = 10.0,
        beta: float = 8.0 / 3.0,
        rho: float = 28.0,
        init_range: float = 10.0,
        noise_std: float = 2.5,
        seed: int = 0,
        normalize: bool = True,
        **kwargs: Any,
    ):
        super().__init__(normalize=normalize, seed=seed, **kwargs)
        if piece_length is None:
            piece_length = train_steps
        for arg, value in (
            ("n_train", n_train),
            ("train_steps", train_steps),
            ("n_test", n_test),
            ("test_steps", test_steps),
            ("piece_length", piece_length),
        ):
            if int(value) != value or value < 1:
                raise ValueError(f"{arg} must be a positive integer, got {value!r}")
        for arg, value in (("dt", dt), ("init_range", init_range)):
            if not value > 0:
                raise ValueError(f"{arg} must be > 0, got {value!r}")
        if not noise_std >= 0:
            raise ValueError(f"noise_std must be >= 0, got {noise_std!r}")
        if train_steps % piece_length != 0:
            divisors = [d for d in range(1, train_steps + 1) if train_steps % d == 0]
            raise ValueError(
                f"piece_length={piece_length} does not divide train_steps={train_steps}: the training "
                f"trajectories are cut into equal consecutive pieces. Valid choices: {divisors} "
                "(the paper uses 10, 100, 1000 and 10000 with train_steps=10000)"
            )
        self.piece_length = int(piece_length)
        self.n_train, self.train_steps = int(n_train), int(train_steps)
        self.n_test, self.test_steps = int(n_test), int(test_steps)
        self.dt, self.sigma, self.beta, self.rho = float(dt), float(sigma), float(beta), float(rho)
        self.init_range, self.noise_std = float(init_range), float(noise_std)

    @property
    def num_train_trajectories(self) -> int:
        """Number of training pieces: ``n_train * train_steps / piece_length``."""
        return self.n_train * (self.train_steps // self.piece_length)

    def generator_params(self) -> dict[str, Any]:
        # piece_length is deliberately absent: every piece length shares one cached data set.
        return {
            "n_train": self.n_train,
            "train_steps": self.train_steps,
            "n_test": self.n_test,
            "test_steps": self.test_steps,
            "dt": self.dt,
            "sigma": self.sigma,
            "beta": self.beta,
            "rho": self.rho,
            "init_range": self.init_range,
            "noise_std": self.noise_std,
            "seed": self.seed,
        }

    def generate(self, split: str) -> dict[str, np.ndarray]:
        """``{"y", "y_clean": [N, T, 1] float32, "state": [N, T, 3] float32}`` of one split (uncut)."""
        if split not in SPLIT_STREAMS:
            raise ValueError(f"unknown split {split!r}; Lorenz has {sorted(SPLIT_STREAMS)}")
        n, steps = (self.n_train, self.train_steps) if split == "train" else (self.n_test, self.test_steps)
        rng = np.random.default_rng(np.random.SeedSequence(self.seed, spawn_key=(SPLIT_STREAMS[split],)))
        x0 = rng.uniform(-self.init_range, self.init_range, size=(n, 3))
        state = lorenz_rk4(
            x0,
            steps,
            self.dt,
            self.sigma,
            self.beta,
            self.rho,
            out_dtype=np.float32,
            progress=f"lorenz {split} ({n} x {steps})",
        )
        y_clean = np.ascontiguousarray(state[..., :1])
        noise = rng.standard_normal(y_clean.shape, dtype=np.float32)
        noise *= np.float32(self.noise_std)
        return {"y": y_clean + noise, "y_clean": y_clean, "state": state}

    @property
    def sample_period(self) -> float:
        """Seconds (time units) between samples."""
        return self.dt

    def wing_level(self) -> float:
        """Level of ``x`` beyond which a run is on a wing of the butterfly: half the fixed points' ``|x|``."""
        return lorenz_wing_level(self.beta, self.rho)

    def true_transition(self) -> Callable[[torch.Tensor], torch.Tensor]:
        """The data's own transition ``x[t+1] = RK4(x[t])``, ``[N, 3] -> [N, 3]`` in original units.

        :func:`lorenz_rk4_step` with this data set's ``dt``, ``sigma``, ``beta``, ``rho``: the reference
        against which a learned ``f`` is compared (e.g. the true Lyapunov exponents from the equations).
        """
        return partial(lorenz_rk4_step, dt=self.dt, sigma=self.sigma, beta=self.beta, rho=self.rho)

    def load_split(self, split: str) -> TrajectoryDataset:
        """The cached split; training trajectories are cut into pieces by a reshape (a view, no copy).

        Piece ``k`` of generated trajectory ``j`` is training trajectory ``j * (train_steps //
        piece_length) + k`` and holds samples ``k * piece_length ... (k + 1) * piece_length - 1``.
        """
        ds = super().load_split(split)
        if split != "train" or self.piece_length == self.train_steps:
            return ds
        arrays = {key: a.reshape(-1, self.piece_length, *a.shape[2:]) for key, a in ds.arrays.items()}
        return TrajectoryDataset(arrays)
