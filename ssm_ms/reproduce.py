"""One command per experiment: SSM fit -> encoder fit -> test (-> UKF test where a config exists).

    python -m ssm_ms.reproduce pendulum            # configs/pendulum*.yaml, the paper's sizes
    python -m ssm_ms.reproduce pendulum --size cpu # configs/cpu/pendulum*.yaml, CPU-sized twins

(``make reproduce EXP=pendulum [SIZE=cpu]``.) Each stage is ``python cli.py ...`` in its own process,
logged under ``runs/<name>/reproduce-<stamp>/``, so the checkpoints each stage hands to the next are
known. The results table ``results/<experiment>.md`` ends with the commands and their durations.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

from omegaconf import OmegaConf

from ssm_ms.machine import describe
from ssm_ms.results import write_pipeline

ROOT = Path(__file__).resolve().parents[1]


def logger_dir(config: Path) -> Path:
    """``save_dir/name`` of the TensorBoard logger a config declares."""
    cfg = OmegaConf.load(config)
    args = OmegaConf.select(cfg, "trainer.logger.init_args", default=None)
    if args is None or "save_dir" not in args or "name" not in args:
        raise ValueError(f"{config} declares no TensorBoardLogger with save_dir and name: reproduce needs them")
    return Path(args.save_dir) / args.name


def experiment_name(config: Path) -> str:
    cfg = OmegaConf.load(config)
    return str(OmegaConf.select(cfg, "model.init_args.experiment", default=config.stem))


def run_stage(args: list[str], stages: list[dict]) -> None:
    cmd = [sys.executable, "cli.py", *args]
    print("\n>>> " + " ".join(cmd), flush=True)
    start = time.time()
    subprocess.run(cmd, cwd=ROOT, check=True)
    stages.append({"command": "python " + " ".join(cmd[1:]), "seconds": round(time.time() - start, 1)})


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("experiment", help="e.g. pendulum, pendulum_fc, quad, quad_fc, mnist, lorenz_T1000")
    parser.add_argument("--size", choices=["paper", "cpu"], default="paper")
    opts = parser.parse_args(argv)
    folder = ROOT / "configs" / ("cpu" if opts.size == "cpu" else "")
    ssm_cfg = folder / f"{opts.experiment}.yaml"
    enc_cfg = folder / f"{opts.experiment}_encoder.yaml"
    ukf_cfg = folder / f"{opts.experiment}_ukf.yaml"
    if not ssm_cfg.exists() or not enc_cfg.exists():
        known = sorted(p.stem for p in folder.glob("*_encoder.yaml"))
        raise SystemExit(
            f"no {ssm_cfg.relative_to(ROOT)} / {enc_cfg.relative_to(ROOT)}: experiments with both configs "
            f"here are {[k[: -len('_encoder')] for k in known]}"
        )
    version = "reproduce-" + datetime.now().strftime("%Y%m%d-%H%M%S")
    ssm_ckpt = logger_dir(ssm_cfg) / version / "checkpoints" / "last.ckpt"
    enc_ckpt = logger_dir(enc_cfg) / version / "checkpoints" / "last.ckpt"
    stages: list[dict] = []
    v = ["--trainer.logger.init_args.version", version]
    run_stage(["fit", "--config", str(ssm_cfg.relative_to(ROOT)), *v], stages)
    with_ssm = ["--model.init_args.ssm_checkpoint", str(ssm_ckpt)]
    run_stage(["fit", "--config", str(enc_cfg.relative_to(ROOT)), *with_ssm, *v], stages)
    run_stage(["test", "--config", str(enc_cfg.relative_to(ROOT)), *with_ssm, "--ckpt_path", str(enc_ckpt), *v], stages)
    if ukf_cfg.exists():
        run_stage(["test", "--config", str(ukf_cfg.relative_to(ROOT)), *with_ssm, *v], stages)
    experiment = experiment_name(enc_cfg)
    results_dir = ROOT / str(OmegaConf.select(OmegaConf.load(enc_cfg), "model.init_args.results_dir", default="results"))
    md = write_pipeline(results_dir, experiment, {
        "stages": stages,
        "total_seconds": round(sum(s["seconds"] for s in stages), 1),
        "machine": describe(),
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "command": f"make reproduce EXP={opts.experiment}" + (" SIZE=cpu" if opts.size == "cpu" else ""),
    })
    print(f"\nresults: {md.relative_to(ROOT)}\n")
    print(md.read_text())


if __name__ == "__main__":
    main()
