"""Where a training epoch's time goes: steps, validation, data, checkpoints, logging (Lightning's SimpleProfiler).

    python benchmarks/profile_epoch.py                                   # configs/pendulum.yaml, 20 epochs
    python benchmarks/profile_epoch.py --config configs/quad.yaml --epochs 10    # -> benchmarks/results/epoch_profile_quad.md
    python benchmarks/profile_epoch.py --config configs/cpu/pendulum.yaml --epochs 1 --out /tmp/x.md   # seconds

Runs ``python cli.py fit --config CONFIG --trainer.max_epochs N`` with ``SimpleProfiler`` in its own process
(under a temporary log folder: nothing of ``runs/`` is touched), reads the profiler's table and writes the
shares of the whole fit: the data set's generation (only where it is not cached yet), the training steps (forward, backward, optimizer), the wait for the next batch, the
validation loop, the end-of-epoch callbacks (``last.ckpt`` every epoch, figures), the rest (logging, set-up,
the progress bar). ``--epochs`` should cover a validation epoch (``check_val_every_n_epoch``: 10 for the paper
configs) for its share to be right. Writes benchmarks/results/epoch_profile_<config>.md, a row per machine (this
run's replace this machine's earlier ones), with the machine, command and date of each machine's run.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def parse_profile(text: str) -> dict[str, tuple[int, float]]:
    """``{action: (calls, total seconds)}`` from SimpleProfiler's table."""
    rows = {}
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) != 5 or not re.fullmatch(r"[0-9.eE+-]+", cells[1] or "x"):
            continue
        try:
            rows[cells[0]] = (int(cells[2]), float(cells[3]))
        except ValueError:
            continue
    return rows


def shares(rows: dict[str, tuple[int, float]]) -> tuple[float, list[tuple[str, float]]]:
    """The fit's total seconds and the seconds of each group (groups do not overlap)."""
    total = rows.get("Total", (1, 0.0))[1]
    steps = rows.get("run_training_batch", (0, 0.0))[1]
    data = rows.get("[_TrainingEpochLoop].train_dataloader_next", (0, 0.0))[1]
    val = sum(
        t
        for a, (_, t) in rows.items()
        if a.startswith("[_EvaluationLoop].val_next") or ".validation_step" in a or "on_validation" in a
    )
    epoch_end = sum(t for a, (_, t) in rows.items() if a.startswith("[Callback]") and "on_train_epoch_end" in a)
    prepare = sum(t for a, (_, t) in rows.items() if a.endswith(".prepare_data") or a.endswith("Module.setup"))
    out = [
        ("data set generation and set-up (first run of a config only)", prepare),
        ("training steps (forward, backward, optimizer)", steps),
        ("waiting for the next training batch (data)", data),
        ("validation (steps, batches, its hooks)", val),
        ("end-of-epoch callbacks (last.ckpt, figures)", epoch_end),
    ]
    out.append(("the rest (logging, progress bar, set-up)", max(total - sum(t for _, t in out), 0.0)))
    return total, out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="configs/pendulum.yaml")
    parser.add_argument("--epochs", type=int, default=20)
    parser.add_argument(
        "--out", help="default: benchmarks/results/epoch_profile_<the config's path under configs/, / as _>.md"
    )
    args = parser.parse_args(argv)
    from benchmarks.report import provenance, write_by_machine
    from ssm_ms.runtime.machine import CpuWatch, quiet_note

    with tempfile.TemporaryDirectory() as tmp:
        cmd = [
            sys.executable,
            "cli.py",
            "fit",
            "--config",
            args.config,
            "--trainer.max_epochs",
            str(args.epochs),
            "--trainer.logger.init_args.save_dir",
            tmp,
            "--trainer.logger.init_args.version",
            "profile",
            "--trainer.enable_progress_bar",
            "false",
            "--trainer.profiler.class_path",
            "lightning.pytorch.profilers.SimpleProfiler",
            "--trainer.profiler.init_args.dirpath",
            tmp,
            "--trainer.profiler.init_args.filename",
            "profile",
        ]
        watch = CpuWatch()
        start = time.time()
        subprocess.run(cmd, cwd=ROOT, check=True, stdout=subprocess.DEVNULL)
        seconds = time.time() - start
        others = watch.others()
        text = next(Path(tmp).glob("*profile*.txt")).read_text()
    rows = parse_profile(text)
    total, groups = shares(rows)
    lines = [
        f"# Where a training epoch goes: `{args.config}`",
        "",
        *provenance("benchmarks/profile_epoch.py", argv, quiet_note(others)),
        f"- {args.epochs} epochs: the fit took {seconds:.1f} s wall-clock ({seconds / args.epochs:.2f} s per epoch, start-up included); "
        f"the profiler's total: {total:.1f} s",
        "",
        "| share | seconds | % of the fit | per epoch (s) |",
        "|---|---|---|---|",
    ]
    for name, t in groups:
        lines.append(f"| {name} | {t:.2f} | {100 * t / max(total, 1e-9):.1f} | {t / args.epochs:.3f} |")
    steps = rows.get("run_training_batch")
    if steps:
        lines.insert(6, f"- training steps: {steps[0]} calls, {1000 * steps[1] / max(steps[0], 1):.1f} ms each")
    top = sorted(((a, c, t) for a, (c, t) in rows.items() if a != "Total"), key=lambda r: -r[2])[:15]
    lines += [
        "",
        "The profiler's 15 largest actions (nested: a step's parts are inside `run_training_batch`):",
        "",
        "| action | calls | seconds |",
        "|---|---|---|",
    ]
    lines += [f"| `{a.split('{')[0]}` | {c} | {t:.2f} |" for a, c, t in top]
    name = Path(args.config).with_suffix("").as_posix().removeprefix("configs/").replace("/", "_")
    write_by_machine(args.out or ROOT / "benchmarks" / "results" / f"epoch_profile_{name}.md", lines)


if __name__ == "__main__":
    main()
