"""The closed loop's camera row toward 95%: planner settings tried on a tuning set of starts, then the chosen one on the
table's.

Every row runs ``python cli.py test`` of a control config from the shipped files (``pretrained/pendulum_torque.ckpt``
and its encoder, as ``make control-pretrained``) with the row's overrides, 100 episodes (five batches of 20), and reads
the success count from the results file it writes under ``--out``. ``--set tuning`` draws the starts and camera noise
from seed 1 (data and loop), which no row of results/pendulum_control*.md used; ``--set table`` the rows' own (seed 0).

    python studies/control_robust/control_robust.py --set tuning --out runs/control_robust/tuning \
        --markdown studies/control_robust/tuning.md
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from ssm_ms.runtime.machine import describe  # noqa: E402

FILES = [
    "--model.init_args.ssm_checkpoint",
    "pretrained/pendulum_torque.ckpt",
    "--model.init_args.encoder_checkpoint",
    "pretrained/pendulum_torque_encoder.ckpt",
]
SETS = {"tuning": ["--data.init_args.seed", "1", "--model.init_args.seed", "1"], "table": []}
P = "--model.init_args.planner."
# (label, overrides): one change at a time from configs/pendulum_torque_control.yaml's settings
ROWS = [
    ("as configured", []),
    ("iterations 4", [P + "iterations", "4"]),
    ("samples 512", [P + "samples", "512"]),
    ("horizon 10", [P + "horizon", "10"]),
    ("horizon 5", [P + "horizon", "5"]),
    ("temperature 0.05", [P + "temperature", "0.05"]),
    ("noise 1.5 N m", [P + "noise_std", "1.5"]),
    ("smoothing 0.2", [P + "smoothing", "0.2"]),
]
SETTINGS = {
    "control": "configs/pendulum_torque_control.yaml",
    "control_2nm": "configs/pendulum_torque_control_2nm.yaml",
}


def run(setting: str, label: str, overrides: list[str], which: str, out: Path) -> dict:
    folder = out / setting / label.replace(" ", "_").replace(".", "")
    command = [
        sys.executable, "cli.py", "test", "--config", SETTINGS[setting], *FILES, *SETS[which], *overrides,
        "--model.init_args.results_dir", str(folder), "--model.init_args.figures_dir", "null",
        "--trainer.logger.init_args.name", "control_robust", "--trainer.enable_progress_bar", "false",
    ]  # fmt: skip
    start = time.time()
    subprocess.run(command, cwd=ROOT, check=True, stdout=subprocess.DEVNULL)
    (found,) = folder.glob("*.json")
    (entry,) = json.loads(found.read_text())["runs"].values()
    summary = {k.split("/", 1)[1]: v for k, v in entry["summary"].items()}
    return {
        "setting": setting,
        "label": label,
        "success": round(summary["episodes/success"]["mean"] * summary["episodes/success"]["n"]),
        "n": summary["episodes/success"]["n"],
        "ci95": summary["episodes/success"]["ci95"],
        "never_up": summary["episodes/first_upright_s"]["non_finite"],
        "first_up_s": summary["episodes/first_upright_s"]["mean"],
        "seconds": round(time.time() - start),
        "command": "python " + shlex.join(command[1:]),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--set", choices=sorted(SETS), default="tuning")
    parser.add_argument("--settings", nargs="+", default=["control", "control_2nm"], choices=sorted(SETTINGS))
    parser.add_argument("--rows", nargs="+", help="labels of ROWS to run (default: all)")
    parser.add_argument("--out", type=Path, default=Path("runs/control_robust"))
    parser.add_argument("--markdown", type=Path, help="append the table to this file")
    args = parser.parse_args(argv)
    rows = [r for r in ROWS if not args.rows or r[0] in args.rows]
    results = []
    for setting in args.settings:
        for label, overrides in rows:
            results.append(run(setting, label, overrides, args.set, args.out))
            r = results[-1]
            print(
                f"{setting:12s} {label:18s} {r['success']}/{r['n']} never up {r['never_up']} ({r['seconds']} s)",
                flush=True,
            )
    if args.markdown:
        lines = [
            f"\n## {args.set} set ({'seed 1: starts and camera noise no table row used' if args.set == 'tuning' else 'the table rows own starts, seed 0'})\n",
            f"- machine: {describe()}; date {datetime.now(timezone.utc).isoformat(timespec='seconds')}",
            f"- command: `python studies/control_robust/control_robust.py {shlex.join(argv or sys.argv[1:])}`",
            "- each row: the encoder row of the named config from the shipped files, 100 episodes, one override\n",
            "| torque bound | planner change | success | 95% CI | never upright | first upright (s) | seconds |",
            "|---|---|---:|---|---:|---:|---:|",
        ]
        for r in results:
            bound = "3 N m" if r["setting"] == "control" else "2 N m"
            lines.append(
                f"| {bound} | {r['label']} | {r['success']}/{r['n']} | {r['ci95'][0]:.2f}-{r['ci95'][1]:.2f} | "
                f"{r['never_up']} | {r['first_up_s']:.2f} | {r['seconds']} |"
            )
        with open(args.markdown, "a") as fh:
            fh.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
