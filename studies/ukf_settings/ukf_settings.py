"""The UKF's two departures from the paper's filter, measured on Lorenz; writes studies/ukf_settings/ukf_settings.md.

Run from the repository root::

    python studies/ukf_settings/ukf_settings.py --ssm-checkpoint runs/.../checkpoints/last.ckpt \\
        [--config configs/cpu/lorenz_T1000_ukf.yaml]

The authors' filter uses the 2d-point cubature rule and starts the components no measurement sets at zero; ours
defaults to the unscented rule with beta = 2 (2d + 1 points, one at the centre) and starts them at the mean shooting
node. Each of the four combinations runs the test protocol of the UKF stage ``--config`` (``cli.py test``, nothing
trained; the analysis left out) on the SSM ``--ssm-checkpoint``, with the stage's noise settings; the table gives
the protocol's forecast MSE against the noiseless x in original units (mean and std over the test sequences) and
the ratio to the default. ``--process-vars`` adds rows: the default filter with other process variances (the
stage's own is the paper's 1e-6 in normalised units), so the filter's tuning is weighed against its sigma points.
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from benchmarks.report import provenance  # noqa: E402
from experiments.configs import load_config  # noqa: E402
from ssm_ms.runtime.machine import CpuWatch, quiet_note  # noqa: E402

DEFAULT = {"unscented": {"beta": 2.0}, "init_mean": "nodes"}
VARIANTS = [  # (label, method name, overrides of the stage's init_args)
    ("beta = 2 (2d + 1 points), mean node start: ours, the default", "ukf", DEFAULT),
    ("cubature (2d points), mean node start", "ukf_cubature", {"unscented": {"beta": 0.0}, "init_mean": "nodes"}),
    ("beta = 2, zero start", "ukf_zero", {"unscented": {"beta": 2.0}, "init_mean": "zero"}),
    ("cubature, zero start: the paper's filter", "ukf_paper", {"unscented": {"beta": 0.0}, "init_mean": "zero"}),
]


def _arg(value: object) -> str:
    return value if isinstance(value, str) else json.dumps(value)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ssm-checkpoint", required=True, help="the trained Lorenz SSM (last.ckpt)")
    parser.add_argument("--config", default="configs/cpu/lorenz_T1000_ukf.yaml", help="the UKF stage's config")
    parser.add_argument("--out", default="studies/ukf_settings/ukf_settings.md")
    parser.add_argument(
        "--process-vars",
        type=float,
        nargs="*",
        default=[],
        help="more rows: the default filter with these process variances",
    )
    args = parser.parse_args(argv)
    if any(q < 0 for q in args.process_vars):
        parser.error(f"--process-vars: a variance cannot be negative, got {args.process_vars}")
    ckpt = Path(args.ssm_checkpoint).resolve()
    if not ckpt.is_file():
        sys.exit(
            f"no SSM checkpoint at {ckpt}: train one first (python cli.py fit --config configs/cpu/lorenz_T1000.yaml)"
        )
    stage = load_config(ROOT / args.config)["model"]["init_args"]
    variants = VARIANTS + [
        (f"the default, process variance {q:g}", f"ukf_q{i}", {**DEFAULT, "process_var": q})
        for i, q in enumerate(args.process_vars)
    ]
    watch, rows = CpuWatch(), []
    with tempfile.TemporaryDirectory() as tmp:
        for label, name, overrides in variants:
            cmd = [
                sys.executable,
                "cli.py",
                "test",
                "--config",
                args.config,
                f"--model.init_args.ssm_checkpoint={ckpt}",
                *(f"--model.init_args.{key}={_arg(value)}" for key, value in overrides.items()),
                f"--model.init_args.method_name={name}",
                "--model.init_args.analysis=null",
                f"--model.init_args.results_dir={tmp}",
                f"--model.init_args.figures_dir={tmp}/figures",
                f"--trainer.logger.init_args.save_dir={tmp}/runs",
                "--trainer.enable_progress_bar=false",
            ]
            print(f"{label}: {shlex.join(cmd)}", flush=True)
            start = time.perf_counter()
            subprocess.run(cmd, cwd=ROOT, check=True, stdout=subprocess.DEVNULL)
            seconds = time.perf_counter() - start
            runs = json.loads((Path(tmp) / f"{stage['experiment']}.json").read_text())["runs"]
            score = runs[name]["summary"][f"{name}/clean/mse"]
            rows.append((label, score["mean"], score["std"], score["n"], seconds))
            print(f"  MSE {score['mean']:.4f} ({seconds:.0f} s)", flush=True)
    ref = rows[0][1]
    lines = [
        "# The UKF's sigma points, prior mean and process variance against the paper's filter, on Lorenz (one run)",
        "",
        *provenance("studies/ukf_settings/ukf_settings.py", argv),
        f"- Others' CPU use: {quiet_note(watch.others())}",
        f"- SSM: `{ckpt.relative_to(ROOT) if ckpt.is_relative_to(ROOT) else ckpt}`; protocol and noise settings: "
        f"`{args.config}` (process_var {stage['process_var']}, measurement_var {stage['measurement_var']}, "
        f"init_var {stage['init_var']}, filter {stage['n_filter']} steps, then forecast).",
        "- Score: the protocol's forecast MSE against the noiseless x, original units, mean (std) over the test "
        "sequences; wall time of the whole `cli.py test` command.",
        "",
        "| UKF | forecast MSE | std | sequences | / default | wall (s) |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    lines += [f"| {label} | {m:.4f} | {s:.4f} | {n} | {m / ref:.3f} | {t:.0f} |" for label, m, s, n, t in rows]
    out = ROOT / args.out
    out.write_text("\n".join(lines) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
