"""The floor of Table 4's score: filters on the Lorenz system's own equations, under the test protocol.

Run from the repository root::

    python studies/lorenz_oracle/lorenz_oracle.py [--data-config configs/cpu/data/lorenz_T1000.yaml ...] \\
        [--particles 4000] [--out studies/lorenz_oracle/lorenz_oracle.md]

For each data config, its test split (generated in memory by its data module: the same sequences the test protocol
reads) is filtered over the protocol's first ``--n-filter`` noisy measurements of x with the data's own transition
(``true_transition``: the generator's RK4 step) and observation (x itself, with the noise's true variance), started
from the generator's own prior (mean 0, the variance of its uniform initial states), by ssm-ms's UKF and (on test sets
of at most ``--pf-max-sequences``) its bootstrap particle filter, each at a few process noises; the last filtered
mean is then run forward ``--n-predict`` steps by the same transition and scored like the protocol's ``clean/mse``
(the squared error against the noiseless x in original units, averaged over the predicted steps, then mean and std
over the sequences). With a perfect model, what is left is the error the measurements leave to these filters: the
noise hides where on the attractor a sequence is, and chaos grows that doubt over the predicted steps. A learned
SSM + UKF well above it is losing to its model (or its filter settings), not to the data. It is a floor for these
filters, not a bound for every one: both approximate the optimal filter of a nonlinear system.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from benchmarks.report import provenance, write  # noqa: E402
from datamodules.lorenz import LorenzDataModule  # noqa: E402
from experiments.configs import build_datamodule  # noqa: E402
from ssm_ms.forecasting.metrics import mse_per_sequence  # noqa: E402
from ssm_ms.inference.particle import ParticleFilter  # noqa: E402
from ssm_ms.inference.ukf import UnscentedKalmanFilter  # noqa: E402

DATA_CONFIGS = ["configs/cpu/data/lorenz_T1000.yaml", "configs/data/lorenz_T1000.yaml"]
PROCESS_VARS = [0.0, 1e-5, 1e-4, 1e-3]  # UKF, original units squared per step: a deterministic f, then some slack
PF_PROCESS_STDS = [0.02, 0.05]  # particle filter, original units per step (with too little the cloud collapses)


def data_module(config: str, n_test: int | None) -> LorenzDataModule:
    """The config's Lorenz data module (its generator settings only; ``n_test`` overrides the number of sequences)."""
    changes = {"data_dir": "unused"} if n_test is None else {"data_dir": "unused", "n_test": n_test}
    try:
        dm = build_datamodule(ROOT / config, **changes)
    except OSError:  # no such file
        dm = None
    except ValueError as e:  # no data module, or arguments it refuses
        sys.exit(f"error: {e}")
    if not isinstance(dm, LorenzDataModule):
        sys.exit(f"error: {config} is not a Lorenz data config (configs/data/lorenz_*.yaml, configs/cpu/data/lorenz_*)")
    return dm


def oracle_filter(
    dm: LorenzDataModule, y: torch.Tensor, n_filter: int, noise: float, particles: int = 0
) -> torch.Tensor:
    """The true model's filter over ``y[:, :n_filter]`` (``[B, T, 1]``, original units, float64): its filtered means
    of the state at each of those samples, ``[B, n_filter, 3]``. ``particles`` 0: the UKF, ``noise`` its process
    variance; else a bootstrap particle filter of that many particles per sequence, ``noise`` its process std
    (seeded)."""
    f, g = dm.true_transition(), lambda x: x[:, :1]
    init_var = dm.init_range**2 / 3.0  # the variance of the uniform initial states
    if particles:
        pf = ParticleFilter(
            f, g, n_particles=particles, process_std=noise, measurement_std=dm.noise_std,
            init_std=init_var**0.5, state_dim=3, seed=0,
        )  # fmt: skip
        return pf.filter(y[:, :n_filter])
    ukf = UnscentedKalmanFilter(
        f, g, process_var=noise, measurement_var=dm.noise_std**2, init_var=init_var, state_dim=3
    )
    return ukf.filter(y[:, :n_filter]).means


def oracle_rollout(dm: LorenzDataModule, x: torch.Tensor, n_predict: int) -> torch.Tensor:
    """``n_predict`` steps of the true transition from the states ``x [B, 3]``: x of each, ``[B, n_predict, 1]``."""
    f, out = dm.true_transition(), []
    for _ in range(n_predict):
        x = f(x)
        out.append(x[:, :1])
    return torch.stack(out, dim=1)


def oracle_forecast(
    dm: LorenzDataModule, y: torch.Tensor, n_filter: int, n_predict: int, noise: float, particles: int = 0
) -> torch.Tensor:
    """:func:`oracle_filter`, then :func:`oracle_rollout` from its last filtered mean: the forecast of x,
    ``[B, n_predict, 1]``."""
    return oracle_rollout(dm, oracle_filter(dm, y, n_filter, noise, particles)[:, -1], n_predict)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data-config", nargs="+", default=DATA_CONFIGS, help="Lorenz data configs (test splits)")
    parser.add_argument("--n-filter", type=int, default=1990, help="measurements filtered (Table 4: 1990)")
    parser.add_argument("--n-predict", type=int, default=10, help="steps forecast (Table 4: 10)")
    parser.add_argument("--n-test", type=int, default=None, help="test sequences (default: each config's)")
    parser.add_argument("--particles", type=int, default=4000, help="particle filter's particles per sequence")
    parser.add_argument(
        "--pf-max-sequences", type=int, default=64, help="particle filter only on test sets of at most this many"
    )
    parser.add_argument("--out", default="studies/lorenz_oracle/lorenz_oracle.md")
    args = parser.parse_args(argv)
    rows, skipped = [], []
    for config in args.data_config:
        dm = data_module(config, args.n_test)
        if args.n_filter + args.n_predict > dm.test_steps:
            sys.exit(f"--n-filter + --n-predict exceeds the {dm.test_steps} steps of {config}'s test sequences")
        test = dm.generate("test")
        y = torch.from_numpy(test["y"]).double()
        truth = torch.from_numpy(test["y_clean"]).double()[:, args.n_filter : args.n_filter + args.n_predict]
        variants = [("UKF", f"process variance {q:g}", q, 0) for q in PROCESS_VARS]
        if dm.n_test <= args.pf_max_sequences:
            variants += [
                (f"particle filter, {args.particles}", f"process std {q:g}", q, args.particles) for q in PF_PROCESS_STDS
            ]
        else:
            skipped.append(f"`{config}` ({dm.n_test} sequences)")
        for name, setting, noise, particles in variants:
            start = time.perf_counter()
            pred = oracle_forecast(dm, y, args.n_filter, args.n_predict, noise, particles)
            score = mse_per_sequence(pred, truth)
            rows.append(
                (config, dm.n_test, name, setting, score.mean().item(), score.std().item(), time.perf_counter() - start)
            )
            print(f"{config} {name}, {setting}: MSE {rows[-1][4]:.4f} ± {rows[-1][5]:.3f}", flush=True)
    lines = [
        "# Lorenz, Table 4's protocol with filters on the true equations: the floor of its forecast score",
        "",
        *provenance("studies/lorenz_oracle/lorenz_oracle.py", argv),
        f"- Protocol: filter {args.n_filter} noisy measurements of x, forecast {args.n_predict} steps from the last "
        "filtered mean; the score is the mean squared error of x against the noiseless x in original units (the "
        "protocol's `clean/mse`), mean ± std over the test sequences.",
        "- Filters (float64) on the data's own RK4 step and on x itself with the noise's variance (2.5^2), started "
        "from the generator's prior (mean 0, variance init_range^2 / 3 per component): ssm-ms's UKF (unscented, beta "
        "= 2) and its bootstrap particle filter (seed 0), each with the process noise of the table (original units).",
    ]
    if skipped:
        lines.append(f"- Particle filter not run on {', '.join(skipped)}: over --pf-max-sequences, for its cost.")
    lines += [
        "",
        "| test set (data config) | sequences | filter | process noise | forecast MSE | std | seconds |",
        "|---|---:|---|---|---:|---:|---:|",
    ]
    lines += [f"| `{c}` | {n} | {f} | {q} | {m:.4f} | {s:.4f} | {t:.0f} |" for c, n, f, q, m, s, t in rows]
    write(ROOT / args.out, lines)


if __name__ == "__main__":
    main()
