"""Long end-to-end checks, excluded from `make test` (run them with `make test-slow`)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from ssm_ms.cli import main
from ssm_ms.module import MultipleShootingModule

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow

# What the CPU-sized Lorenz twin must reach (docs/results.md states the targets). (With 16 free runs W1 moved between
# 0.70 and 1.14 from one snapshot to the next, studies/lorenz_cpu_study/lorenz_cpu_study.md; the stage configs now
# draw 64 free runs, analysis.dynamics.free_runs, and results/lorenz_T1000_cpu.md has 0.68.)
WINGS_SHARE = 1.0  # share of the 64 free runs that visit both wings: every one
MAX_W1 = 1.0  # 1-Wasserstein distance of the free runs' x to the training set's noiseless x
EXPONENT_TOLERANCE = 0.3  # largest Lyapunov exponent within 30% of the true system's


def test_demo_learns_the_pendulum(tmp_path):
    """`make demo`'s config, as shipped: the full-length rollout from the first node follows the clean frames
    far better than the best constant image (the mean frame)."""
    cli = main(
        [
            "fit",
            "--config",
            str(ROOT / "configs" / "cpu" / "pendulum.yaml"),
            "--trainer.logger.init_args.save_dir",
            str(tmp_path / "runs"),
            "--data.init_args.data_dir",
            str(tmp_path / "data"),
            "--trainer.enable_progress_bar",
            "false",
        ]
    )
    model: MultipleShootingModule = cli.model
    dm = cli.datamodule
    batch = next(iter(dm.val_dataloader()))
    with torch.no_grad():
        _, y_hat = model(model.node_states(batch["index"])[:, 0], batch["y"].shape[1])
    clean = batch["y_clean"]
    mean_frame = torch.from_numpy(dm.load_arrays("train")["y_clean"][:64].astype("float32") / 255).mean((0, 1))
    model_mse = (y_hat - clean).pow(2).mean().item()
    constant_mse = (mean_frame - clean).pow(2).mean().item()
    assert model_mse < 0.6 * constant_mse, (model_mse, constant_mse)


def test_quadruple_pendulum_paper_config_starts_and_trains(tmp_path):
    """configs/quad.yaml as written (paper-size data: 4000 trajectories generated), a few optimizer steps."""
    cli = main(
        [
            "fit",
            "--config",
            str(ROOT / "configs" / "quad.yaml"),
            "--trainer.logger.init_args.save_dir",
            str(tmp_path / "runs"),
            "--data.init_args.data_dir",
            str(tmp_path / "data"),
            "--trainer.max_steps",
            "3",
            "--trainer.limit_val_batches",
            "1",
            "--trainer.enable_progress_bar",
            "false",
        ]
    )
    assert cli.trainer.global_step == 3
    assert cli.datamodule.num_train_trajectories == 2000
    assert (tmp_path / "runs" / "quad").is_dir()


def test_lorenz_cpu_twin_recovers_the_attractor(tmp_path):
    """`make reproduce EXP=lorenz_T1000 SIZE=cpu`'s SSM stage, as shipped, then its UKF test with the analysis:
    the learned f, iterated alone, has the Lorenz attractor's statistics (the targets below; figures
    from the shipped run: results/lorenz_T1000_cpu.md). 30 to 55 minutes on 2 cores, depending on the CPU."""
    import json

    common = [
        "--trainer.logger.init_args.save_dir",
        str(tmp_path / "runs"),
        "--trainer.logger.init_args.version",
        "slow",
        "--data.init_args.data_dir",
        str(tmp_path / "data"),
        "--trainer.enable_progress_bar",
        "false",
    ]
    main(["fit", "--config", str(ROOT / "configs" / "cpu" / "lorenz_T1000.yaml"), *common])
    ckpt = tmp_path / "runs" / "lorenz_T1000_cpu" / "slow" / "checkpoints" / "last.ckpt"
    main(
        [
            "test",
            "--config",
            str(ROOT / "configs" / "cpu" / "lorenz_T1000_ukf.yaml"),
            *common,
            "--model.init_args.ssm_checkpoint",
            str(ckpt),
            "--model.init_args.results_dir",
            str(tmp_path / "results"),
            "--model.init_args.figures_dir",
            str(tmp_path / "figures"),
        ]
    )
    run = json.loads((tmp_path / "results" / "lorenz_T1000_cpu.json").read_text())["runs"]["ukf"]
    analysis = run["analysis"]
    free, ly = analysis["dynamics"]["free_run"], analysis["dynamics"]["lyapunov"]
    true = analysis["true_system"]["largest"]
    assert free["both_wings_share"] >= WINGS_SHARE, free
    assert free["wasserstein"][0] <= MAX_W1, free
    assert abs(ly["largest"] - true) <= EXPONENT_TOLERANCE * true, (ly, true)
    assert run["summary"]["ukf/clean/mse"]["mean"] < run["summary"]["last/clean/mse"]["mean"]
