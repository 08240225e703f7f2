"""Table 4's score split by predicted step: how much is already in the filter's state, how much the forecast adds.

Run from the repository root::

    python studies/lorenz_error_by_step/lorenz_error_by_step.py --ssm pretrained/lorenz_T1000.ckpt runs/.../last.ckpt \\
        [--config configs/lorenz_T1000_ukf.yaml] [--n-test N] [--out studies/lorenz_error_by_step/lorenz_error_by_step.md]

Each SSM ``--ssm`` runs the protocol of the UKF stage ``--config`` (its filter settings, ``n_filter`` given steps,
``n_predict`` predicted, the data of its ``data`` section, the test split generated in memory: the sequences
``cli.py test`` scores) with the normalisation its checkpoint was trained with; beside them the true model's UKF
(``studies/lorenz_oracle/lorenz_oracle.py``'s floor, process variance ``--oracle-process-var`` in original units). For each, the
squared error of x against the noiseless x in original units at step 0 (the filter's estimate of the last given
sample) and at each predicted step, averaged over the test sequences (± the standard error of that mean). The mean of
the predicted steps is the protocol's ``clean/mse``; each column after the first also gets that score less the
first column's, paired over the same sequences (± its standard error: whether two SSMs differ). Step 0 is what the
filter leaves; the growth over the predicted steps is what iterating ``f`` from that state adds (for the oracle, only
the doubt about the unmeasured y and z, grown by the true dynamics). A second table follows the filter along the given samples (the same squared error of its
estimate of x at sample t, the measurements up to t filtered, and its mean over the samples after the first 250,
paired as above): how fast each filter settles, and where.
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
from experiments.configs import build_datamodule, load_config  # noqa: E402
from ssm_ms.checkpointing import datamodule_state  # noqa: E402
from ssm_ms.inference.filter_module import FilterForecaster  # noqa: E402
from ssm_ms.loading import load_ssm  # noqa: E402
from studies.lorenz_oracle.lorenz_oracle import oracle_filter, oracle_rollout  # noqa: E402

FILTER_KEYS = ("method", "process_var", "measurement_var", "init_var", "init_mean", "unscented", "autocast")
BATCH = 200


# the given samples (1-based) at which the second table reads the filter, those up to n_filter, and n_filter itself
FILTER_SAMPLES = (1, 10, 100, 250, 500, 750, 1000, 1250, 1500, 1750)
SETTLED = 250  # samples after which the second table also averages each sequence's errors (the filters have settled)


@torch.inference_mode()
def ssm_errors(ckpt: Path, settings: dict, dm: LorenzDataModule, y: torch.Tensor, clean: torch.Tensor, k: int, p: int):
    """Squared errors ``[N, k + p]`` (original units) of the SSM's UKF against the noiseless x: its filtered
    estimates of the ``k`` given samples, then the ``p`` predicted samples."""
    forecaster = FilterForecaster(str(ckpt), n_filter=k, n_predict=p, **settings).eval()
    _, checkpoint = load_ssm(ckpt)
    dm.load_state_dict(datamodule_state(checkpoint)[1])  # the normalisation this SSM was trained with
    out = []
    for start in range(0, len(y), BATCH):
        yb = dm.normalizer.normalize(y[start : start + BATCH, :k].float())
        fc = forecaster.forecast(yb, p)
        x = dm.normalizer.denormalize(torch.cat([fc.filtered, fc.predicted], dim=1)).double()
        out.append((x - clean[start : start + BATCH, : k + p]).square().flatten(1))
    return torch.cat(out)


def oracle_errors(dm: LorenzDataModule, y: torch.Tensor, clean: torch.Tensor, k: int, p: int, q: float):
    """The same squared errors ``[N, k + p]`` of the true model's UKF (process variance ``q``)."""
    x = oracle_filter(dm, y, k, q)
    xs = torch.cat([x[..., :1], oracle_rollout(dm, x[:, -1], p)], dim=1)
    return (xs - clean[:, : k + p]).square().flatten(1)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ssm", nargs="+", required=True, help="trained Lorenz SSMs (checkpoints)")
    parser.add_argument("--config", default="configs/lorenz_T1000_ukf.yaml", help="the UKF stage's config")
    parser.add_argument("--n-test", type=int, default=None, help="test sequences (default: the config's)")
    parser.add_argument("--oracle-process-var", type=float, default=1e-5, help="the true model's UKF, original units")
    parser.add_argument("--out", default="studies/lorenz_error_by_step/lorenz_error_by_step.md")
    args = parser.parse_args(argv)
    ckpts = [Path(c).resolve() for c in args.ssm]
    for ckpt in ckpts:
        if not ckpt.is_file():
            sys.exit(f"no SSM checkpoint at {ckpt}: give trained Lorenz SSMs (e.g. pretrained/lorenz_T1000.ckpt)")
    try:
        config = load_config(ROOT / args.config)
        dm = build_datamodule(config, **({} if args.n_test is None else {"n_test": args.n_test}))
    except (OSError, ValueError) as e:
        sys.exit(f"error: {args.config}: {e}")
    stage = (config.get("model") or {}).get("init_args") or {}
    if not isinstance(dm, LorenzDataModule) or "n_filter" not in stage:
        sys.exit(f"error: {args.config} is not a Lorenz UKF stage (configs/lorenz_*_ukf.yaml)")
    k, p = int(stage["n_filter"]), int(stage.get("n_predict") or 10)
    if k + p > dm.test_steps:
        sys.exit(f"error: n_filter + n_predict ({k} + {p}) exceeds the {dm.test_steps} steps of the test sequences")
    settings = {key: stage[key] for key in FILTER_KEYS if key in stage}
    test = dm.generate("test")
    y, clean = torch.from_numpy(test["y"]).double(), torch.from_numpy(test["y_clean"]).double()
    columns = []
    for ckpt in ckpts:
        start = time.perf_counter()
        name = ckpt.relative_to(ROOT) if ckpt.is_relative_to(ROOT) else ckpt
        try:
            errors = ssm_errors(ckpt, settings, dm, y, clean, k, p)
        except ValueError as e:  # not an SSM of this data (its g draws other measurements)
            sys.exit(f"error: {name}: {e}")
        columns.append((f"`{name}`", errors, time.perf_counter() - start))
        print(f"{name}: MSE {errors[:, k:].mean():.4f} ({columns[-1][2]:.0f} s)", flush=True)
    start = time.perf_counter()
    columns.append(
        ("true model", oracle_errors(dm, y, clean, k, p, args.oracle_process_var), time.perf_counter() - start)
    )
    n = len(y)

    def cell(v: torch.Tensor) -> str:
        return f"{v.mean():.4f} ± {v.std() / n**0.5:.4f}"

    def mean_rows(label: str, per_sequence: list[torch.Tensor]) -> list[str]:
        """The columns' per-sequence values averaged, then each later column's less the first's (paired)."""
        return [
            f"| {label} | " + " | ".join(cell(v) for v in per_sequence) + " |",
            f"| {label} less the first column's, paired | | "
            + " | ".join(cell(v - per_sequence[0]) for v in per_sequence[1:])
            + " |",
        ]

    lines = [
        "# Lorenz, Table 4's score split by step: the filter's state (step 0) and the forecast's growth (one run)",
        "",
        *provenance("studies/lorenz_error_by_step/lorenz_error_by_step.py", argv),
        f"- Protocol: `{args.config}` ({n} test sequences of {dm.test_steps} steps; UKF over the first {k} noisy "
        f"samples of x with {', '.join(f'{key} {settings[key]}' for key in settings)}, then {p} steps of f and g); "
        f"true model: its own UKF (process variance {args.oracle_process_var:g} in original units, "
        "`studies/lorenz_oracle/lorenz_oracle.py`).",
        "- Cell: squared error of x against the noiseless x in original units, mean over the test sequences ± its "
        "standard error. Step 0: the filter's estimate of the last given sample; steps 1.. : the forecast. "
        "`mean of 1-..`: the mean of the predicted steps, the protocol's `clean/mse`; below it, each column's "
        "per-sequence score less the first column's on the same sequence (a paired difference: negative is better "
        "than the first).",
        "",
        "| step | " + " | ".join(label for label, _, _ in columns) + " |",
        "|---:|" + "---:|" * len(columns),
    ]
    for step in range(p + 1):
        lines.append(f"| {step} | " + " | ".join(cell(e[:, k - 1 + step]) for _, e, _ in columns) + " |")
    lines += mean_rows(f"mean of 1-{p}", [e[:, k:].mean(1) for _, e, _ in columns])
    lines.append("| seconds | " + " | ".join(f"{t:.0f}" for _, _, t in columns) + " |")
    samples = sorted({t for t in FILTER_SAMPLES if t < k} | {k})
    lines += [
        "",
        f"The filter along the given samples: the squared error of its estimate of x at sample t (1-based; t = {k} is "
        f"step 0 above), the measurements up to t filtered, the same sequences; below, each sequence's mean over the "
        f"samples after the first {SETTLED} (the filters settled), and that less the first column's (paired).",
        "",
        "| sample t | " + " | ".join(label for label, _, _ in columns) + " |",
        "|---:|" + "---:|" * len(columns),
        *(f"| {t} | " + " | ".join(cell(e[:, t - 1]) for _, e, _ in columns) + " |" for t in samples),
    ]
    if k > SETTLED:  # each sequence's mean over the samples after the filters have settled
        lines += mean_rows(f"mean of {SETTLED + 1}-{k}", [e[:, SETTLED:k].mean(1) for _, e, _ in columns])
    write(ROOT / args.out, lines)


if __name__ == "__main__":
    main()
