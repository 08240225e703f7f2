"""Penalty against augmented Lagrangian at the paper's alpha and at 10x / 0.1x, dense against sparse nodes,
on the CPU-sized simple pendulum and Lorenz T=1000 (configs/cpu/).

    python benchmarks/bench_constraints.py                       # every variant, each config's own epochs (~12 h)
    python benchmarks/bench_constraints.py --fraction 0.1        # 1/10 of each config's epochs, milestones scaled
    python benchmarks/bench_constraints.py --tiny                # a few trajectories, 2 epochs (the test)

Each variant trains from the same config and seed; only the constraint (and the augmented Lagrangian's
multiplier cadence: every epoch, every 10 or every 50), the node optimizer and alpha differ (the model's
initial alpha and the value the ShootingSchedule raises it to, both times 1, 10 or 0.1). With
``--fraction F`` each config trains ``F * max_epochs`` epochs and the schedule's milestones are scaled by ``F``. Reported per variant, after training, over the whole training set: the fit and the
gap (the paper's mean squared continuity gap, whatever the constraint), the mean squared error of the
rollout from each training trajectory's first node over ``horizon`` steps against the noiseless data (a
forecast from the learned initial state; pendulum: all 100 frames, Lorenz: 200 steps, about a Lyapunov
time), and seconds per epoch. Written to ``benchmarks/results/constraints.md`` (``--out``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.report import provenance  # noqa: E402

EXPERIMENTS = {
    "pendulum": {
        "config": "configs/cpu/pendulum.yaml",
        "horizon": 100,
        "tiny": [
            "--data.init_args.n_train",
            "8",
            "--data.init_args.n_test",
            "4",
            "--data.init_args.workers",
            "1",
            "--data.init_args.batch_size",
            "4",
        ],
    },
    "lorenz_T1000": {
        "config": "configs/cpu/lorenz_T1000.yaml",
        "horizon": 200,
        "tiny": [
            "--data.init_args.n_train",
            "2",
            "--data.init_args.n_test",
            "2",
            "--data.init_args.train_steps",
            "4000",
            "--data.init_args.batch_size",
            "4",
        ],
    },
}
# name: (constraint, node_optimizer, alpha multiplier, constraint_options)
VARIANTS = {
    "penalty": ("penalty", "dense", 1.0, None),
    "penalty, alpha x10": ("penalty", "dense", 10.0, None),
    "penalty, alpha x0.1": ("penalty", "dense", 0.1, None),
    "augmented Lagrangian": ("augmented_lagrangian", "dense", 1.0, None),
    "augmented Lagrangian, alpha x10": ("augmented_lagrangian", "dense", 10.0, None),
    "augmented Lagrangian, alpha x0.1": ("augmented_lagrangian", "dense", 0.1, None),
    "penalty, sparse nodes": ("penalty", "sparse", 1.0, None),
}
for _every in (10, 50):  # multipliers updated less often: the nodes' Adam steps have time to follow them
    for _x, _tag in ((1.0, ""), (10.0, ", alpha x10"), (0.1, ", alpha x0.1")):
        VARIANTS[f"augmented Lagrangian every {_every} epochs{_tag}"] = (
            "augmented_lagrangian",
            "dense",
            _x,
            {"every_n_epochs": _every},
        )


def _scale_schedule(schedule, factor: float, alpha_x: float) -> None:
    schedule.alpha *= alpha_x
    if factor != 1.0:
        schedule.alpha_epoch = round(schedule.alpha_epoch * factor)
        schedule.lr_milestones = [round(e * factor) for e in schedule.lr_milestones]
        schedule.reset_optimizer_at = [round(e * factor) for e in schedule.reset_optimizer_at]


@torch.no_grad()
def scores(model, dm, horizon: int) -> dict[str, float]:
    """Fit, gap and first-node rollout error over the whole training set (batch-size weighted means)."""
    from ssm_ms.training.shooting import multiple_shooting_loss

    model.eval()
    totals = {"fit": 0.0, "gap": 0.0, "rollout_mse": 0.0}
    count = 0
    from datamodules.dataset import collate

    for batch in torch.utils.data.DataLoader(dm._train(), batch_size=64, collate_fn=collate, shuffle=False):
        nodes = model.node_states(batch["index"])
        fit, gap = multiple_shooting_loss(model.f, model.g, nodes, batch["y"], model.hparams.loss)
        truth = batch.get("y_clean", batch["y"])[:, :horizon]
        _, y_hat = model(nodes[:, 0], truth.shape[1])
        b = len(batch["index"])
        totals["fit"] += float(fit) * b
        totals["gap"] += float(gap) * b
        totals["rollout_mse"] += float((y_hat - truth).pow(2).mean()) * b
        count += b
    return {k: v / count for k, v in totals.items()}


def run_variant(experiment: str, name: str, args: argparse.Namespace, workdir: Path) -> dict:
    from ssm_ms.cli import main as cli_main

    spec = EXPERIMENTS[experiment]
    constraint, node_optimizer, alpha_x, options = VARIANTS[name]
    cli_args = [
        "--config",
        str(ROOT / spec["config"]),
        "--trainer.logger",
        "false",
        "--trainer.enable_progress_bar",
        "false",
        "--trainer.enable_model_summary",
        "false",
        "--trainer.check_val_every_n_epoch",
        "100000",
        "--trainer.default_root_dir",
        str(workdir),
        "--model.init_args.constraint",
        constraint,
        "--model.init_args.node_optimizer",
        node_optimizer,
        *(["--model.init_args.constraint_options", json.dumps(options)] if options else []),
        "--data.init_args.data_dir",
        args.data_dir,
    ]
    if args.tiny:
        cli_args += spec["tiny"]
    cli = cli_main(cli_args, run=False)
    max_epochs = cli.trainer.max_epochs
    epochs = args.epochs or max(1, round(args.fraction * max_epochs))
    cli.trainer.fit_loop.max_epochs = epochs
    cli.trainer.callbacks = []  # the model's schedule only (configure_callbacks)
    if cli.model.schedule is None:
        raise SystemExit(f"{spec['config']} names no schedule (model.init_args.schedule): nothing to scale")
    _scale_schedule(cli.model.schedule, epochs / max_epochs, alpha_x)
    with torch.no_grad():
        cli.model.alpha.mul_(alpha_x)  # the initial alpha too: the whole schedule is scaled
    initial_alpha = float(cli.model.alpha)
    start = time.perf_counter()
    cli.trainer.fit(cli.model, cli.datamodule)
    seconds = time.perf_counter() - start
    out = scores(cli.model, cli.datamodule, spec["horizon"])
    out.update(
        experiment=experiment,
        variant=name,
        epochs=epochs,
        seconds_per_epoch=seconds / epochs,
        initial_alpha=initial_alpha,
        final_alpha=float(cli.model.alpha * getattr(cli.model, "alpha_factor", 1.0)),
    )
    return out


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--experiments", nargs="+", default=list(EXPERIMENTS), choices=list(EXPERIMENTS))
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--fraction", type=float, default=1.0, help="train this fraction of each config's epochs")
    parser.add_argument("--epochs", type=int, default=None, help="train this many epochs (overrides --fraction)")
    parser.add_argument("--tiny", action="store_true", help="a few short trajectories, 2 epochs: a smoke test")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--data-dir", default="data")
    parser.add_argument("--workdir", default="runs/bench_constraints")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "constraints.md"))
    args = parser.parse_args(argv)
    if args.tiny and args.epochs is None:
        args.epochs = 2
    if args.threads:
        torch.set_num_threads(args.threads)
    rows = []
    for experiment in args.experiments:
        for name in args.variants:
            rows.append(run_variant(experiment, name, args, Path(args.workdir) / experiment / name.replace(" ", "_")))
            print(json.dumps(rows[-1]), flush=True)  # progress, and what a cut-off run leaves
    lines = [
        "# Penalty against augmented Lagrangian, dense against sparse nodes (CPU-sized configs)",
        "",
        *provenance("benchmarks/bench_constraints.py", argv),
    ]
    if args.tiny:
        lines += ["", "**TINY sizes** (a smoke test of the script: the figures say nothing about the methods)."]
    lines += [
        "",
        "fit, gap: over the whole training set after training (gap: the paper's mean squared continuity gap); "
        "rollout MSE: from each training trajectory's first node over the horizon, against the noiseless data; "
        "alpha: the model's initial alpha and the schedule's final one (times the augmented Lagrangian's growth factor).",
        "",
    ]
    for experiment in args.experiments:
        lines += [
            f"## {experiment} ({EXPERIMENTS[experiment]['config']}, horizon {EXPERIMENTS[experiment]['horizon']})",
            "",
            "| variant | epochs | alpha: initial, final | fit | gap | rollout MSE | s / epoch |",
            "|---|---|---|---|---|---|---|",
        ]
        for r in rows:
            if r["experiment"] == experiment:
                lines.append(
                    f"| {r['variant']} | {r['epochs']} | {r['initial_alpha']:.3g}, {r['final_alpha']:.3g} | {r['fit']:.4g} | {r['gap']:.3g} | "
                    f"{r['rollout_mse']:.4g} | {r['seconds_per_epoch']:.3g} |"
                )
        lines.append("")
    lines += ["```json", json.dumps(rows, indent=1), "```", ""]
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text("\n".join(lines))
    print("\n".join(lines))
    return rows


if __name__ == "__main__":
    main()
