"""Tests of lorenz_cpu_study.py, frozen with the study: `make test` does not collect studies/ (testpaths: tests/).
Run: `.venv/bin/python -m pytest studies/lorenz_cpu_study`."""

import json
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))  # the repository's packages and studies/, from wherever pytest runs

from studies.lorenz_cpu_study import lorenz_cpu_study as study  # noqa: E402
from tests.test_cli import CHEAP_ANALYSIS, CPU, TINY, fit_tiny, outputs, run  # noqa: E402


def test_lorenz_cpu_study_reads_a_row_from_a_checkpoint_and_its_test(tmp_path):
    """The study's row of a tiny CPU Lorenz SSM after its UKF stage's test (as tests/test_cli.py runs it): the
    checkpoint's epochs and steps, the data it saw, the UKF's score and the exponents from the results file."""
    ssm = CPU / "lorenz_T1000.yaml"
    fit_tiny(tmp_path, ssm)
    ssm_ckpt = outputs(tmp_path, ssm) / "checkpoints" / "last.ckpt"
    run(
        tmp_path,
        "test",
        CPU / "lorenz_T1000_ukf.yaml",
        "--model.init_args.ssm_checkpoint",
        str(ssm_ckpt),
        "--model.init_args.results_dir",
        str(tmp_path / "results"),
        "--model.init_args.figures_dir",
        str(tmp_path / "figures"),
        "--trainer.limit_test_batches",
        "1",
        *TINY["lorenz"],
        *CHEAP_ANALYSIS,
    )
    saved = json.loads((tmp_path / "results" / "lorenz_T1000_cpu.json").read_text())["runs"]["ukf"]
    row = study.main(
        [
            str(ssm_ckpt),
            "--results",
            str(tmp_path / "results" / "lorenz_T1000_cpu.json"),
            "--ukf",
            "ukf",
            "--out",
            str(tmp_path / "rows.jsonl"),
        ]
    )
    ckpt = torch.load(ssm_ckpt, weights_only=False)
    assert (row["epochs"], row["steps"]) == (ckpt["epoch"] + 1, ckpt["global_step"])
    assert row["data"] == {"n_train": 4, "train_steps": 10000, "noise_std": 2.5}  # the TINY data of this test
    assert row["ukf_mse"] == saved["summary"]["ukf/clean/mse"]["mean"]
    assert row["largest"] == saved["analysis"]["dynamics"]["lyapunov"]["largest"] and len(row["exponents"]) == 3
    assert row["largest_true"] == saved["analysis"]["true_system"]["largest"]
    assert json.loads((tmp_path / "rows.jsonl").read_text()) == row
