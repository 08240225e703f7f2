"""Write an example data set a user can train on: noisy recordings of a damped oscillator.

    python examples/make_oscillator_data.py                 # -> data/oscillator.npz
    python examples/make_oscillator_data.py --out my.npz --n 512 --noise 0.1

The system is a damped harmonic oscillator ``x'' + 2 zeta omega x' + omega^2 x = 0`` (solved in
closed form, so the recordings are exact), started from positions and velocities uniform in
``[-1, 1]``. Each trajectory holds ``steps`` samples every ``dt`` seconds of the measurement
``y = [x, x'] + noise``. The .npz holds, with N trajectories and T samples:

- ``y``       float32 [N, T, 2]  noisy measurements (what a user records)
- ``y_clean`` float32 [N, T, 2]  the same without noise (optional in real data; used for metrics)
- ``t``       float32 [T]        sample times in seconds (not used by the DataModule)

Train on it with ``datamodules.files.FileDataModule(train_path="data/oscillator.npz",
clean_key="y_clean", test_fraction=0.2)``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def damped_oscillator(x0: np.ndarray, v0: np.ndarray, t: np.ndarray, omega: float, zeta: float) -> np.ndarray:
    """Closed-form underdamped solution: states ``[N, T, 2]`` (position, velocity) at times ``t``."""
    if not 0 <= zeta < 1:
        raise ValueError(f"zeta must be in [0, 1) (underdamped), got {zeta}")
    wd = omega * np.sqrt(1.0 - zeta**2)  # damped angular frequency
    a, b = x0[:, None], (v0[:, None] + zeta * omega * x0[:, None]) / wd
    decay = np.exp(-zeta * omega * t)[None, :]
    c, s = np.cos(wd * t)[None, :], np.sin(wd * t)[None, :]
    x = decay * (a * c + b * s)
    v = decay * ((b * wd - zeta * omega * a) * c - (a * wd + zeta * omega * b) * s)
    return np.stack([x, v], axis=-1)


def make(
    n: int = 256,
    steps: int = 200,
    dt: float = 0.05,
    omega: float = np.pi,
    zeta: float = 0.05,
    noise: float = 0.05,
    seed: int = 0,
) -> dict[str, np.ndarray]:
    """The arrays of the example data set (see the module docstring)."""
    rng = np.random.default_rng(seed)
    x0, v0 = rng.uniform(-1.0, 1.0, size=(2, n))
    t = np.arange(steps) * dt
    clean = damped_oscillator(x0, v0, t, omega, zeta)
    y = clean + noise * rng.standard_normal(clean.shape)
    return {"y": y.astype(np.float32), "y_clean": clean.astype(np.float32), "t": t.astype(np.float32)}


def main(argv: list[str] | None = None) -> Path:
    p = argparse.ArgumentParser(description="Write noisy damped-oscillator trajectories [N, T, 2] to an .npz file.")
    p.add_argument("--out", default="data/oscillator.npz", help="output file (default: data/oscillator.npz)")
    p.add_argument("--n", type=int, default=256, help="number of trajectories N")
    p.add_argument("--steps", type=int, default=200, help="samples per trajectory T")
    p.add_argument("--dt", type=float, default=0.05, help="sampling period (s)")
    p.add_argument("--omega", type=float, default=float(np.pi), help="natural angular frequency (rad/s)")
    p.add_argument("--zeta", type=float, default=0.05, help="damping ratio, in [0, 1)")
    p.add_argument("--noise", type=float, default=0.05, help="std of the Gaussian measurement noise")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    arrays = make(args.n, args.steps, args.dt, args.omega, args.zeta, args.noise, args.seed)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez(out, **arrays)  # uncompressed: FileDataModule memory-maps it
    n, T, d = arrays["y"].shape
    print(f"wrote {out}: y and y_clean of shape [N={n}, T={T}, D={d}], noise std {args.noise}")
    return out


if __name__ == "__main__":
    main()
