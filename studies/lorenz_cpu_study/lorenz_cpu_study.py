"""One row of the CPU-sized Lorenz study (studies/lorenz_cpu_study/lorenz_cpu_study.md) for a trained SSM checkpoint.

    python cli.py test --config configs/cpu/lorenz_T1000_ukf.yaml --model.init_args.ssm_checkpoint <ckpt> \
        --model.init_args.results_dir <dir>                     # the protocol and its analysis section
    python studies/lorenz_cpu_study/lorenz_cpu_study.py <ckpt> --results <dir>/lorenz_T1000_cpu.json --ukf ukf \
        [--encoder encoder] [--label "what differed"] [--threads 1] [--out rows.jsonl]

The analysis is the test's own (``ssm_ms.analysis.dynamics_report`` on the SSM's f, recorded in the results
file): this script puts beside it what a study compares runs by, and nothing it computes again:

- training: epochs and optimizer steps (from the checkpoint) and wall-clock (first to last event of each of
  the run's TensorBoard event files beside the checkpoint, summed over files, so a resumed run counts once);
- the data and f's size (from the checkpoint);
- from the results file: W1 of the free runs' x against the training set's noiseless x, their std against
  that reference's, the share of runs that visit both wings, the largest Lyapunov exponent (and its spread
  over runs) beside the true system's, the 10-step forecast MSE (original units, noiseless x) of the UKF
  and encoder runs named, and the UKF's valid prediction time where the test computed it.

It is meant for snapshots along a run (``snap-epoch=*.ckpt``), each tested with its own ``--model.init_args.method_name``.
"""

from __future__ import annotations

import argparse
import glob
import json
from pathlib import Path

import torch


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


def study_row(checkpoint: dict, runs: dict, ukf: str, encoder: str = "") -> dict:
    """The study's columns from an SSM checkpoint and the results-file runs of its test(s)."""
    if ukf not in runs:
        raise SystemExit(f"no run {ukf!r} in the results file: give the --model.init_args.method_name of its test")
    analysis = runs[ukf].get("analysis") or {}
    if "dynamics" not in analysis:
        raise SystemExit(f"run {ukf!r} has no dynamics analysis: test it with a config that has analysis.dynamics")
    free, ly = analysis["dynamics"]["free_run"], analysis["dynamics"]["lyapunov"]
    data = next(
        (v["generator_params"] for v in checkpoint.values() if isinstance(v, dict) and "generator_params" in v), {}
    )
    hp = checkpoint["hyper_parameters"]
    row = {
        "epochs": checkpoint["epoch"] + 1,
        "steps": checkpoint["global_step"],
        "data": {k: data.get(k) for k in ("n_train", "train_steps", "noise_std")},
        "f": {k: v for k, v in hp["f"]["init_args"].items() if k != "state_dim"},
        "n_nodes": hp["n_nodes"],
        "w1": free["wasserstein"][0],
        "both_wings": free.get("both_wings_share"),
        "finite_share": free["finite_share"],
        "model_std": free["model_std"][0],
        "reference_std": free["reference_std"][0],
        "largest": ly["largest"],
        "largest_std": ly["std_over_runs"][0],
        "exponents": ly["exponents"],
        "largest_true": (analysis.get("true_system") or {}).get("largest"),
        "valid_time": analysis.get("valid_time"),
    }
    for kind, name in (("ukf", ukf), ("encoder", encoder)):
        if name:
            row[f"{kind}_mse"] = runs[name]["summary"][f"{name}/clean/mse"]["mean"]
    return row


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("ckpt", type=Path, help="checkpoint of a MultipleShootingModule trained on Lorenz")
    parser.add_argument("--results", type=Path, required=True, help="results JSON written by its test(s)")
    parser.add_argument("--ukf", required=True, help="method name of the UKF test run, with the analysis")
    parser.add_argument("--encoder", default="", help="method name of the encoder test run")
    parser.add_argument("--label", default="", help="what this run differs in (goes into the row)")
    parser.add_argument("--threads", type=int, default=None, help="thread count the run was trained with (recorded)")
    parser.add_argument("--out", type=Path, help="append the row as one JSON line to this file")
    opts = parser.parse_args(argv)

    checkpoint = torch.load(opts.ckpt, map_location="cpu", weights_only=False)
    row = {
        "label": opts.label,
        "ckpt": str(opts.ckpt),
        "threads": opts.threads,
        **study_row(checkpoint, json.loads(opts.results.read_text())["runs"], opts.ukf, opts.encoder),
    }
    row["train_seconds"] = training_time(opts.ckpt, row["steps"])
    print(json.dumps(row, indent=1))

    def fmt(v, spec=".2f"):
        return "" if v is None else format(v, spec)

    minutes = None if row["train_seconds"] is None else row["train_seconds"] / 60
    print(
        f"| {row['label']} | {row['epochs']} | {row['steps']} | {fmt(minutes, '.0f')} min, {row['threads']} thr "
        f"| {fmt(row['w1'])} | {fmt(row['both_wings'])} | {fmt(row['model_std'])} / {fmt(row['reference_std'])} "
        f"| {fmt(row['largest'])} +- {fmt(row['largest_std'])} | {fmt(row.get('ukf_mse'), '.3f')} "
        f"| {fmt(row.get('encoder_mse'), '.3f')} |"
    )
    if opts.out:
        with opts.out.open("a") as fh:
            fh.write(json.dumps(row) + "\n")
    return row


if __name__ == "__main__":
    main()
