"""The UKF's floor of Table 4's score: the UKF on the Lorenz system's own equations, under the test protocol.

Run from the repository root::

    python benchmarks/lorenz_oracle.py [--data-config configs/cpu/data/lorenz_T1000.yaml ...] \\
        [--out benchmarks/results/lorenz_oracle.md]

For each data config, its test split (generated in memory by its data module: the same sequences the test protocol
reads) is filtered over the protocol's first ``--n-filter`` noisy measurements of x by ssm-ms's UKF with the data's
own transition (``true_transition``: the generator's RK4 step) and observation (x itself, with the noise's true
variance), started from the generator's own prior (mean 0, the variance of its uniform initial states); the last
filtered mean is then run forward ``--n-predict`` steps by the same transition and scored like the protocol's
``clean/mse`` (the squared error against the noiseless x in original units, averaged over the predicted steps, then
mean and std over the sequences). With a perfect model, what it leaves is the error the measurements leave to a UKF:
the noise hides where on the attractor a sequence is, and chaos grows that doubt over the predicted steps. A learned
SSM + UKF well above it is losing to its model (or its filter settings), not to the data. It is a floor for the
UKF, not for every filter: the UKF approximates the optimal filter of a nonlinear system (a particle filter on the
same equations could score lower).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.report import provenance, write  # noqa: E402
from datamodules.lorenz import LorenzDataModule  # noqa: E402
from ssm_ms.forecasting.metrics import mse_per_sequence  # noqa: E402
from ssm_ms.inference.ukf import UnscentedKalmanFilter  # noqa: E402

DATA_CONFIGS = ["configs/cpu/data/lorenz_T1000.yaml", "configs/data/lorenz_T1000.yaml"]
PROCESS_VARS = [0.0, 1e-5, 1e-4, 1e-3]  # original units squared per step: a deterministic f, then some slack


def data_module(config: str, n_test: int | None) -> LorenzDataModule:
    """The config's Lorenz data module (its generator settings only; ``n_test`` overrides the number of sequences)."""
    spec = yaml.safe_load((ROOT / config).read_text())
    args = dict(spec.get("init_args", {}))
    if n_test is not None:
        args["n_test"] = n_test
    return LorenzDataModule(**{k: v for k, v in args.items() if k not in ("data_dir",)}, data_dir="unused")


def oracle_forecast(
    dm: LorenzDataModule, y: torch.Tensor, n_filter: int, n_predict: int, process_var: float
) -> torch.Tensor:
    """The true model's UKF over ``y[:, :n_filter]`` (``[B, T, 1]``, original units, float64), then ``n_predict``
    steps of the true transition from the last filtered mean: the forecast of x, ``[B, n_predict, 1]``."""
    f = dm.true_transition()
    ukf = UnscentedKalmanFilter(
        f,
        lambda x: x[:, :1],
        process_var=process_var,
        measurement_var=dm.noise_std**2,
        init_var=dm.init_range**2 / 3.0,  # the variance of the uniform initial states
        state_dim=3,
    )
    x = ukf.filter(y[:, :n_filter]).means[:, -1]
    out = []
    for _ in range(n_predict):
        x = f(x)
        out.append(x[:, :1])
    return torch.stack(out, dim=1)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data-config", nargs="+", default=DATA_CONFIGS, help="Lorenz data configs (test splits)")
    parser.add_argument("--n-filter", type=int, default=1990, help="measurements filtered (Table 4: 1990)")
    parser.add_argument("--n-predict", type=int, default=10, help="steps forecast (Table 4: 10)")
    parser.add_argument("--n-test", type=int, default=None, help="test sequences (default: each config's)")
    parser.add_argument("--out", default="benchmarks/results/lorenz_oracle.md")
    args = parser.parse_args(argv)
    rows = []
    for config in args.data_config:
        dm = data_module(config, args.n_test)
        if args.n_filter + args.n_predict > dm.test_steps:
            sys.exit(f"--n-filter + --n-predict exceeds the {dm.test_steps} steps of {config}'s test sequences")
        test = dm.generate("test")
        y = torch.from_numpy(test["y"]).double()
        truth = torch.from_numpy(test["y_clean"]).double()[:, args.n_filter : args.n_filter + args.n_predict]
        for q in PROCESS_VARS:
            start = time.perf_counter()
            score = mse_per_sequence(oracle_forecast(dm, y, args.n_filter, args.n_predict, q), truth)
            rows.append((config, dm.n_test, q, score.mean().item(), score.std().item(), time.perf_counter() - start))
            print(f"{config} process_var {q:g}: MSE {rows[-1][3]:.4f} ± {rows[-1][4]:.3f}", flush=True)
    lines = [
        "# Lorenz, Table 4's protocol with the UKF on the true equations: the UKF's floor of its forecast score",
        "",
        *provenance("benchmarks/lorenz_oracle.py", argv),
        f"- Protocol: filter {args.n_filter} noisy measurements of x, forecast {args.n_predict} steps; the score is "
        "the mean squared error of x against the noiseless x in original units (the protocol's `clean/mse`), mean "
        "± std over the test sequences.",
        "- Filter: ssm-ms's UKF (float64, unscented beta = 2) on the data's own RK4 step and on x itself, measurement "
        "variance the noise's (2.5^2), prior mean 0 and variance init_range^2 / 3 (the generator's uniform initial "
        "states); process variance as in the table (original units squared per step).",
        "",
        "| test set (data config) | sequences | process variance | forecast MSE | std | seconds |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    lines += [f"| `{c}` | {n} | {q:g} | {m:.4f} | {s:.4f} | {t:.0f} |" for c, n, q, m, s, t in rows]
    write(ROOT / args.out, lines)


if __name__ == "__main__":
    main()
