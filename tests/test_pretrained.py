"""Pretrained checkpoints: stripping keeps what inference needs, and every committed file under pretrained/
rebuilds the architecture its config declares (strict state-dict load, same f and g)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from ssm_ms.pretrained import DROPPED, HALF_KEY, HALF_MIN_NUMEL, main, strip




def fake_checkpoint() -> dict:
    return {
        "epoch": 3, "global_step": 30, "pytorch-lightning_version": "2.6.0",
        "state_dict": {"big": torch.randn(HALF_MIN_NUMEL + 1), "small": torch.randn(7), "count": torch.tensor(4)},
        "optimizer_states": [{"state": {0: {"exp_avg": torch.randn(3)}}}], "lr_schedulers": [{}],
        "loops": {"fit_loop": {}}, "callbacks": {"EpochCheckpoint": {}},
        "hyper_parameters": {"ssm_checkpoint": "runs/x/version_0/checkpoints/last.ckpt", "n_filter": 50,
                             "results_dir": "results", "figures_dir": "results/figures"},
        "PendulumDataModule": {"name": "pendulum", "generator_params": {"seed": 0}},
    }


def test_strip_drops_training_state_and_keeps_the_rest():
    ckpt = fake_checkpoint()
    out = strip(ckpt)
    assert not set(DROPPED) & set(out)
    assert set(out) == set(ckpt) - set(DROPPED)
    for key, value in ckpt["state_dict"].items():
        assert torch.equal(out["state_dict"][key], value) and out["state_dict"][key].dtype == value.dtype
    assert out["PendulumDataModule"] == ckpt["PendulumDataModule"] and out["hyper_parameters"] == ckpt["hyper_parameters"]
    assert "optimizer_states" in ckpt  # the input is left alone


def test_strip_half_and_ssm_path():
    ckpt = fake_checkpoint()
    out = strip(ckpt, ssm_checkpoint="pretrained/x_ssm.ckpt", half=True, results_dir="runs/pretrained")
    big = out["state_dict"]["big"]
    assert big.dtype == torch.float16 and torch.equal(big, ckpt["state_dict"]["big"].to(torch.float16))
    assert out["state_dict"]["small"].dtype == torch.float32 and out["state_dict"]["count"].dtype == torch.int64
    assert out[HALF_KEY] == ["big"]
    # float16 loads back into a float32 parameter, rounded by at most 2**-11 relatively
    back = torch.empty(HALF_MIN_NUMEL + 1).copy_(big)
    ref = ckpt["state_dict"]["big"]
    assert ((back - ref).abs() <= ref.abs() * 2.0**-11 + 2.0**-24).all()
    assert out["hyper_parameters"]["ssm_checkpoint"] == "pretrained/x_ssm.ckpt"
    assert ckpt["hyper_parameters"]["ssm_checkpoint"].startswith("runs/")
    assert (out["hyper_parameters"]["results_dir"], out["hyper_parameters"]["figures_dir"]) == (
        "runs/pretrained", "runs/pretrained/figures")
    with pytest.raises(ValueError, match="records no SSM"):
        strip({"state_dict": {}, "hyper_parameters": {}}, ssm_checkpoint="x")
    with pytest.raises(ValueError, match="writes no results"):
        strip({"state_dict": {}, "hyper_parameters": {}}, results_dir="x")


def test_strip_command(tmp_path, capsys):
    src, dst = tmp_path / "last.ckpt", tmp_path / "out" / "model.ckpt"
    ckpt = fake_checkpoint()
    torch.save(ckpt, src)
    main([str(src), str(dst)])
    assert "MB" in capsys.readouterr().out
    saved = torch.load(dst, weights_only=True)
    assert "optimizer_states" not in saved and "loops" not in saved
    assert torch.equal(saved["state_dict"]["big"], ckpt["state_dict"]["big"])
    with pytest.raises(SystemExit) as err:
        main([str(tmp_path / "missing.ckpt"), str(dst)])
    assert err.value.code == 2
    assert "does not exist" in capsys.readouterr().err
