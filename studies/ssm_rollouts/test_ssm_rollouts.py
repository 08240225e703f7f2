"""Tests of ssm_rollouts.py, frozen with the study: `make test` does not collect studies/ (testpaths: tests/).
Run: `.venv/bin/python -m pytest studies/ssm_rollouts`."""

import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))  # the repository's packages and studies/, from wherever pytest runs


def test_ssm_rollouts_score_the_first_node_rolled_out_as_a_naive_loop(tmp_path):
    """ssm_rollouts.py on the pretrained pendulum SSM and 8 generated training trajectories (4 picked,
    evenly: 0, 2, 5, 7): its MSE over all frames equals g(f^k(first node)) against the clean frames, computed here
    step by step; one figure per SSM, rows measured / clean / model per trajectory."""
    import yaml
    from PIL import Image

    from datamodules.pendulum import PendulumDataModule
    from ssm_ms.forecasting.metrics import ssim_per_sequence
    from ssm_ms.loading import load_ssm
    from studies.ssm_rollouts import ssm_rollouts

    spec = yaml.safe_load((ROOT / "configs/data/pendulum.yaml").read_text())
    args = {**spec["init_args"], "n_train": 8, "n_test": 1, "data_dir": str(tmp_path / "data")}
    config = tmp_path / "pendulum.yaml"
    config.write_text(yaml.safe_dump({"class_path": spec["class_path"], "init_args": args}))
    out = tmp_path / "rollouts.md"
    ckpt = str(ROOT / "pretrained/pendulum.ckpt")
    ssm_rollouts.main(["--ssm", ckpt, "--data-config", str(config), "--out", str(out)])
    row = next(line for line in out.read_text().splitlines() if line.startswith("| `"))
    reported, ssim = float(row.split("|")[5]), float(row.split("|")[6])

    model, _ = load_ssm(ckpt)
    dm = PendulumDataModule(**args)
    dm.prepare_data()
    item = dm.load("train").__getitems__([0, 2, 5, 7])
    with torch.no_grad():
        x = model.node_states(torch.tensor([0, 2, 5, 7]))[:, 0]
        frames = []
        for _ in range(item["y"].shape[1]):
            frames.append(model.g(x))
            x = model.f(x)
    naive = (torch.stack(frames, 1) - item["y_clean"]).pow(2).mean().item()
    assert reported == pytest.approx(naive, abs=6e-5)  # the table's 4 decimals
    assert ssim == pytest.approx(ssim_per_sequence(torch.stack(frames, 1), item["y_clean"]).mean().item(), abs=6e-5)
    image = Image.open(out.with_name("rollouts_0.png"))
    assert image.size == (2 * (10 * 25 + 1), 2 * (4 * 3 * 25 + 1))  # 10 frames of 24 px + 1 px borders, 12 rows, x2
