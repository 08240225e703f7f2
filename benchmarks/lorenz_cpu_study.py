"""One row of the CPU-sized Lorenz study (benchmarks/results/lorenz_cpu_study.md) from a trained SSM checkpoint.

    python benchmarks/lorenz_cpu_study.py runs/lorenz_T1000_cpu/<version>/checkpoints/last.ckpt \
        [--label "what differed"] [--threads 1] [--results results/lorenz_T1000_cpu.json --ukf ukf --encoder encoder] \
        [--out rows.jsonl]

What it measures, all with the project's own functions:

- training: epochs and optimizer steps (from the checkpoint) and wall-clock (first to last event of each of
  the run's TensorBoard event files beside the checkpoint, summed over files, so a resumed run counts once);
- ``ssm_ms.analysis.dynamics_report`` from 16 shooting nodes drawn with a fixed seed: the model's Lyapunov
  spectrum and the true system's (from the first states of 16 test trajectories), and 16 free runs of
  20,000 steps after a 2000-step transient, decoded to original units: the 1-Wasserstein distance of their
  x to the noiseless x of the *training* split (long trajectories: the true system's own free runs are
  ~0.4 from it), their std against that reference's, and the share of runs that visit both wings;
- with ``--results``: the 10-step forecast MSE (original units, against the noiseless x) of the UKF and
  encoder test runs (``python cli.py test ...``) recorded under the given method names.

It is for snapshots along a run (``snap-epoch=*.ckpt``); the valid prediction time and the rest of the
analysis of a finished run come from its test (``python cli.py test`` with an ``analysis`` section).
"""

from __future__ import annotations

import argparse
import glob
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from datamodules.base import Normalizer  # noqa: E402
from datamodules.lorenz import LorenzDataModule  # noqa: E402
from ssm_ms.analysis import dynamics_report, lorenz_wing_level  # noqa: E402
from ssm_ms.inference.ssm_forecaster import datamodule_state, load_ssm  # noqa: E402

DT = 0.005
N_STARTS = 16


def training_time(ckpt: Path, last_step: int) -> float | None:
    """Seconds of training up to ``last_step`` in the run's TensorBoard event files (``<run>/checkpoints/x.ckpt``
    -> ``<run>``): first to last ``train/loss`` event of each file, summed over files (a resumed run counts once)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    total = None
    for path in sorted(glob.glob(str(ckpt.parent.parent / "events.out.tfevents.*"))):
        acc = EventAccumulator(path, size_guidance={"scalars": 0})
        acc.Reload()
        if "train/loss" in acc.Tags()["scalars"]:
            events = [e for e in acc.Scalars("train/loss") if e.step < last_step]
            if events:
                total = (total or 0.0) + events[-1].wall_time - events[0].wall_time
    return total


def data_of(checkpoint: dict, data_dir: str) -> tuple[LorenzDataModule, Normalizer]:
    """The data module the SSM was trained on (from the generator parameters saved in its checkpoint)."""
    state = datamodule_state(checkpoint)[1]
    params = {k: v for k, v in state["generator_params"].items()}
    dm = LorenzDataModule(data_dir=data_dir, **params)
    dm.prepare_data()
    return dm, Normalizer.from_state_dict(state["normalizer"])


def forecast_scores(results: Path, methods: dict[str, str]) -> dict[str, float]:
    runs = json.loads(results.read_text())["runs"]
    return {f"{kind}_mse": runs[name]["summary"][f"{name}/clean/mse"]["mean"] for kind, name in methods.items() if name}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("ckpt", type=Path, help="checkpoint of a MultipleShootingModule trained on Lorenz")
    parser.add_argument("--label", default="", help="what this run differs in (goes into the row)")
    parser.add_argument("--threads", type=int, default=None, help="thread count the run was trained with (recorded)")
    parser.add_argument("--data-dir", default=str(ROOT / "data"))
    parser.add_argument("--results", type=Path, help="results JSON of the test runs (python cli.py test ...)")
    parser.add_argument("--ukf", default="", help="method name of the UKF run in --results")
    parser.add_argument("--encoder", default="", help="method name of the encoder run in --results")
    parser.add_argument("--out", type=Path, help="append the row as one JSON line to this file")
    parser.add_argument("--lyapunov-steps", type=int, default=4000, help="Jacobian products per run")
    parser.add_argument("--free-steps", type=int, default=20_000, help="length of the free runs, after the transient")
    parser.add_argument("--transient", type=int, default=2000, help="steps discarded before measuring")
    opts = parser.parse_args(argv)
    torch.set_num_threads(1)

    ssm, checkpoint = load_ssm(opts.ckpt)
    dm, norm = data_of(checkpoint, opts.data_dir)
    reference = torch.from_numpy(np.array(dm.load_arrays("train")["y_clean"])).reshape(-1, 1)
    generator = torch.Generator().manual_seed(0)
    nodes = ssm.nodes.weight.detach().view(-1, ssm.state_dim)
    starts = nodes[torch.randperm(len(nodes), generator=generator)[:N_STARTS]]
    true_starts = torch.from_numpy(np.array(dm.load_arrays("test")["state"][:N_STARTS, 0])).double()
    start = time.time()
    report = dynamics_report(ssm.f, ssm.g, starts, DT, to_units=norm.denormalize, reference=reference,
                             lyapunov_steps=opts.lyapunov_steps, free_steps=opts.free_steps,
                             transient=opts.transient, align=min(600, opts.transient),
                             wing_level=lorenz_wing_level(), true_f=dm.true_transition(), true_starts=true_starts)
    free = report["free_run"]
    row = {
        "label": opts.label, "ckpt": str(opts.ckpt), "epochs": checkpoint["epoch"] + 1,
        "steps": checkpoint["global_step"], "train_seconds": training_time(opts.ckpt, checkpoint["global_step"]),
        "threads": opts.threads,
        "data": {"n_train": dm.n_train, "train_steps": dm.train_steps, "noise_std": dm.noise_std,
                 "piece_length": dm.n_train * dm.train_steps // ssm.nodes.num_embeddings},
        "f": {k: v for k, v in checkpoint["hyper_parameters"]["f"]["init_args"].items() if k != "state_dim"},
        "n_nodes": ssm.n_nodes,
        "w1": free.get("wasserstein", [None])[0], "both_wings": free["both_wings_share"],
        "finite_share": free["finite_share"],
        "model_std": free.get("model_std", [None])[0], "reference_std": free.get("reference_std", [None])[0],
        "largest": report["lyapunov"]["largest"], "largest_std": report["lyapunov"]["std_over_runs"][0],
        "exponents": report["lyapunov"]["exponents"], "largest_true": report["lyapunov_true"]["largest"],
        "report_seconds": round(time.time() - start, 1),
    }
    if opts.results:
        row.update(forecast_scores(opts.results, {"ukf": opts.ukf, "encoder": opts.encoder}))
    print(json.dumps(row, indent=1))

    def fmt(v, spec=".2f"):
        return "" if v is None else format(v, spec)

    minutes = None if row["train_seconds"] is None else row["train_seconds"] / 60
    print(f"| {row['label']} | {row['epochs']} | {row['steps']} | {fmt(minutes, '.0f')} min, {row['threads']} thr "
          f"| {fmt(row['w1'])} | {fmt(row['both_wings'])} | {fmt(row['model_std'])} / {fmt(row['reference_std'])} "
          f"| {fmt(row['largest'])} +- {fmt(row['largest_std'])} | {fmt(row.get('ukf_mse'), '.3f')} "
          f"| {fmt(row.get('encoder_mse'), '.3f')} |")
    if opts.out:
        with opts.out.open("a") as fh:
            fh.write(json.dumps(row) + "\n")
    return row


if __name__ == "__main__":
    main()
