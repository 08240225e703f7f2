"""The allocator setting on a training step whose activations exceed 2 GiB: the quadruple pendulum's encoder.

    python benchmarks/bench_allocator.py [--rounds 3] [--steps 8] [--warm 2]
    python benchmarks/bench_allocator.py --config configs/quad_encoder.yaml --ssm pretrained/quad.ckpt
    python benchmarks/bench_allocator.py --config C --ssm S --data.init_args.data_dir /tmp/d   # other options: to cli.py

Runs ``python cli.py fit --config CONFIG --model.init_args.ssm_checkpoint SSM`` for ``--warm + --steps`` training
steps (one epoch, no validation, no logger, no checkpoint) once per setting per round, the settings' order
alternating from round to round, each in its own process (the setting is process-wide):

* ``trim off``: ``ssm_ms.runtime.perf.configure_allocator()`` as ``cli.py`` calls it (heap trimming switched off);
* ``trim 2 GiB``: ``configure_allocator(trim_threshold=2**31 - 1)``, the largest threshold ``mallopt`` takes (what
  ssm-ms set before);
* ``glibc defaults``: ``SSM_MS_MALLOC_TUNING=0``.

A callback reads the process's ``getrusage`` after every training step; the figures are per step over the
``--steps`` steps after the ``--warm`` first ones: wall seconds, user and system CPU seconds, minor page faults.
The ratio is ``setting / trim off`` of the wall seconds per step, per round, median over rounds.
The data set must be the SSM's (the config's data section; generated on first use, ~13 min for the quad's
4000 trajectories). Writes benchmarks/results/allocator_quad_encoder.md with the machine, command and date.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

SETTINGS = {  # label: (trim_threshold given to configure_allocator or None, extra environment)
    "trim off": (None, {}),
    "trim 2 GiB": ((1 << 31) - 1, {}),
    "glibc defaults": (None, {"SSM_MS_MALLOC_TUNING": "0"}),
}
BASE = "trim off"

# The child: set the allocator first (the first configure_allocator call in a process decides), then run cli.py.
DRIVER = r"""
import json, runpy, sys
trim = json.loads(sys.argv.pop(1))
from ssm_ms.runtime import perf
if trim is not None:
    perf.configure_allocator(trim_threshold=trim)
sys.argv = ["cli.py"] + sys.argv[1:]
runpy.run_path("cli.py", run_name="__main__")
"""

CALLBACK = r"""
import json, resource, time
from lightning.pytorch.callbacks import Callback

class StepUsage(Callback):
    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        r = resource.getrusage(resource.RUSAGE_SELF)
        print("STEP " + json.dumps([time.perf_counter(), r.ru_utime, r.ru_stime, r.ru_minflt]), flush=True)
"""


def run_once(label: str, args: argparse.Namespace, overrides: list[str], callback_dir: Path) -> dict[str, float]:
    """One process of one setting: per-step figures over the steps after the warm ones."""
    trim, extra_env = SETTINGS[label]
    env = {**os.environ, **extra_env, "PYTHONPATH": os.pathsep.join([str(ROOT), str(callback_dir)])}
    if "SSM_MS_MALLOC_TUNING" not in extra_env:
        env.pop("SSM_MS_MALLOC_TUNING", None)
    cmd = [
        sys.executable,
        "-c",
        DRIVER,
        json.dumps(trim),
        "fit",
        "--config",
        args.config,
        "--model.init_args.ssm_checkpoint",
        args.ssm,
        "--trainer.max_epochs",
        "1",
        "--trainer.limit_train_batches",
        str(args.warm + args.steps),
        "--trainer.limit_val_batches",
        "0",
        "--trainer.logger",
        "false",
        "--trainer.enable_checkpointing",
        "false",
        "--trainer.enable_progress_bar",
        "false",
        "--trainer.callbacks",
        "[{class_path: step_usage.StepUsage}]",
        "--trainer.default_root_dir",
        str(callback_dir),
        *overrides,
    ]  # its config.yaml: not in the repository
    out = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
    rows = [json.loads(line[5:]) for line in out.stdout.splitlines() if line.startswith("STEP ")]
    if out.returncode != 0 or len(rows) < args.warm + args.steps:
        raise SystemExit(f"the {label!r} run failed (exit {out.returncode}):\n{out.stderr[-2000:]}")
    a, b, k = rows[args.warm - 1], rows[-1], args.steps
    return {"wall": (b[0] - a[0]) / k, "user": (b[1] - a[1]) / k, "sys": (b[2] - a[2]) / k, "faults": (b[3] - a[3]) / k}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="configs/quad_encoder.yaml")
    parser.add_argument("--ssm", default="pretrained/quad.ckpt", help="the SSM checkpoint the encoder learns from")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--steps", type=int, default=8, help="timed steps per run")
    parser.add_argument("--warm", type=int, default=2, help="steps per run before the timed ones (at least 1)")
    parser.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "allocator_quad_encoder.md"))
    args, overrides = parser.parse_known_args(argv)  # the rest goes to cli.py
    if args.warm < 1 or args.steps < 1 or args.rounds < 1:
        parser.error("--warm, --steps and --rounds must be at least 1")
    if BASE not in args.settings:
        args.settings = [BASE] + args.settings
    from benchmarks.report import provenance, write
    from ssm_ms.runtime.machine import CpuWatch, quiet_note

    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "step_usage.py").write_text(CALLBACK)
        results: dict[str, list[dict[str, float]]] = {label: [] for label in args.settings}
        watch = CpuWatch()
        for r in range(args.rounds):
            order = args.settings if r % 2 == 0 else args.settings[::-1]
            for label in order:
                results[label].append(run_once(label, args, overrides, Path(tmp)))
                print(f"round {r + 1}/{args.rounds} {label}: {results[label][-1]}", flush=True)
        others = watch.others()

    lines = [
        f"# Allocator settings on the quadruple pendulum encoder's training step (`{args.config}`)",
        "",
        *provenance("benchmarks/bench_allocator.py", argv, f"Python {sys.version.split()[0]}; {quiet_note(others)}"),
        f"- {args.rounds} rounds; in each, every setting runs in its own process (order alternating between rounds): "
        f"{args.warm} untimed then {args.steps} timed training steps (batch of the config, forward, backward, Adam, "
        "the batch's loading included)",
        f"- ratio = setting / `{BASE}` (seconds per step), per round, median over rounds",
        "",
        "| setting | s / step (median) | user s / step | system s / step | minor page faults / step | "
        f"ratio to `{BASE}` | per-round ratios |",
        "|---|---:|---:|---:|---:|---:|---|",
    ]
    for label in args.settings:
        runs = results[label]
        ratios = [x["wall"] / base["wall"] for x, base in zip(runs, results[BASE])]
        med = {key: statistics.median(x[key] for x in runs) for key in ("wall", "user", "sys", "faults")}
        lines.append(
            f"| {label} | {med['wall']:.2f} | {med['user']:.2f} | {med['sys']:.2f} | {med['faults']:,.0f} | "
            f"{statistics.median(ratios):.2f} | {', '.join(f'{q:.2f}' for q in ratios)} |"
        )
    write(args.out, lines)


if __name__ == "__main__":
    main()
