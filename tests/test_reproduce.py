"""`make reproduce`'s stage list: which configs run, in which order, handing which checkpoints on
(the stages themselves are recorded, not run: each is a CLI run tested elsewhere)."""

from __future__ import annotations

import pytest

from ssm_ms import reproduce


@pytest.fixture
def recorded(monkeypatch):
    calls: list[list[str]] = []
    monkeypatch.setattr(reproduce, "run_stage", lambda args, stages: (calls.append(args), stages.append(
        {"command": " ".join(args), "seconds": 0.0})))
    written = {}
    monkeypatch.setattr(reproduce, "write_pipeline", lambda results_dir, experiment, command, pipeline: written.update(
        experiment=experiment, command=command, pipeline=pipeline) or reproduce.ROOT / "README.md")
    return calls, written


def option(args: list[str], name: str) -> str:
    return args[args.index(name) + 1]


def test_an_experiment_runs_its_ssm_stages_then_every_baseline(recorded, capsys):
    calls, written = recorded
    reproduce.main(["lorenz_T1000", "--size", "cpu"])
    configs = [(a[0], option(a, "--config")) for a in calls]
    assert configs == [
        ("fit", "configs/cpu/lorenz_T1000.yaml"),
        ("fit", "configs/cpu/lorenz_T1000_encoder.yaml"),
        ("test", "configs/cpu/lorenz_T1000_encoder.yaml"),
        ("test", "configs/cpu/lorenz_T1000_ukf.yaml"),
        ("fit", "configs/cpu/baselines/lorenz_T1000_lstm.yaml"),
        ("test", "configs/cpu/baselines/lorenz_T1000_lstm.yaml"),
        ("fit", "configs/cpu/baselines/lorenz_T1000_rkn.yaml"),
        ("test", "configs/cpu/baselines/lorenz_T1000_rkn.yaml"),
    ]
    version = option(calls[0], "--trainer.logger.init_args.version")
    assert all(option(a, "--trainer.logger.init_args.version") == version for a in calls)
    ssm_ckpt = f"runs/lorenz_T1000_cpu/{version}/checkpoints/last.ckpt"
    assert all(option(a, "--model.init_args.ssm_checkpoint") == ssm_ckpt for a in calls[1:4])
    assert option(calls[2], "--ckpt_path") == f"runs/lorenz_T1000_encoder_cpu/{version}/checkpoints/last.ckpt"
    assert option(calls[5], "--ckpt_path") == f"runs/lorenz_T1000_lstm_cpu/{version}/checkpoints/last.ckpt"
    assert "--model.init_args.ssm_checkpoint" not in calls[4] + calls[5]
    assert written["experiment"] == "lorenz_T1000_cpu" and written["command"] == "make reproduce EXP=lorenz_T1000 SIZE=cpu"
    assert len(written["pipeline"]["stages"]) == 8


def test_a_baseline_alone_and_without_baselines(recorded):
    calls, written = recorded
    reproduce.main(["pendulum_rkn"])
    assert [(a[0], option(a, "--config")) for a in calls] == [
        ("fit", "configs/baselines/pendulum_rkn.yaml"), ("test", "configs/baselines/pendulum_rkn.yaml")]
    assert written["experiment"] == "pendulum"  # the same results file as the SSM's
    calls.clear()
    reproduce.main(["pendulum", "--no-baselines"])
    assert [option(a, "--config") for a in calls] == ["configs/pendulum.yaml"] + ["configs/pendulum_encoder.yaml"] * 2


def test_unknown_experiment_lists_the_known_ones(recorded):
    with pytest.raises(SystemExit, match=r"no configs for experiment 'pendulm'.*'pendulum'.*'pendulum_lstm'"):
        reproduce.main(["pendulm"])
