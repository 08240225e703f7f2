"""Long end-to-end checks, excluded from `make test` (run them with `make test-slow`)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from ssm_ms.cli import main
from ssm_ms.module import MultipleShootingModule

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


def test_demo_learns_the_pendulum(tmp_path):
    """`make demo`'s config, as shipped: the full-length rollout from the first node follows the clean frames
    far better than the best constant image (the mean frame)."""
    cli = main(["fit", "--config", str(ROOT / "configs" / "cpu" / "pendulum.yaml"),
                "--trainer.logger.init_args.save_dir", str(tmp_path / "runs"),
                "--data.init_args.data_dir", str(tmp_path / "data"), "--trainer.enable_progress_bar", "false"])
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
    cli = main(["fit", "--config", str(ROOT / "configs" / "quad.yaml"),
                "--trainer.logger.init_args.save_dir", str(tmp_path / "runs"),
                "--data.init_args.data_dir", str(tmp_path / "data"), "--trainer.max_steps", "3",
                "--trainer.limit_val_batches", "1", "--trainer.enable_progress_bar", "false"])
    assert cli.trainer.global_step == 3
    assert cli.datamodule.num_train_trajectories == 2000
    assert (tmp_path / "runs" / "quad").is_dir()
