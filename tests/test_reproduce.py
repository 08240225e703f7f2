"""`make reproduce`'s stage list: which configs run, in which order, handing which checkpoints on
(the stages themselves are recorded, not run: each is a CLI run tested elsewhere)."""

from __future__ import annotations

from pathlib import Path

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
    assert written["command"] == "python -m ssm_ms.reproduce pendulum --no-baselines"  # not make's: it has no such option


def test_unknown_experiment_lists_the_known_ones(recorded):
    with pytest.raises(SystemExit, match=r"no configs for experiment 'pendulm'.*'pendulum'.*'pendulum_lstm'"):
        reproduce.main(["pendulm"])


# ---------------------------------------------------------------------------- a stage interrupted or failing
def _stage_in_own_group(tmp_path, args):
    """``reproduce.run_stage(args)`` in a new process group (as a terminal runs ``make reproduce``)."""
    import subprocess
    import sys

    script = f"from ssm_ms import reproduce; reproduce.run_stage({args!r}, [])"
    out = open(tmp_path / "stage.log", "w")
    env = dict(__import__("os").environ, OMP_NUM_THREADS="1")
    return subprocess.Popen([sys.executable, "-c", script], cwd=reproduce.ROOT, start_new_session=True, stdout=out,
                            stderr=subprocess.PIPE, text=True, env=env)


@pytest.mark.parametrize("how", ["ctrl-c", "sigterm"])
def test_ctrl_c_or_sigterm_during_a_stage_names_it_and_the_command_that_resumes_it(tmp_path, how):
    """Ctrl-C reaches the stage and reproduce together (SIGINT to the process group); SIGTERM to reproduce alone
    (``kill <pid>``) is forwarded to the stage. Either way: no traceback, status 130, the stage stopped (not left
    running), named, and the command that resumes it from the last completed epoch."""
    import os
    import shlex
    import signal
    import time

    import torch

    from tests.test_cli import ROTATION

    config = tmp_path / "rot.yaml"
    config.write_text(ROTATION.format(root=tmp_path).replace("max_epochs: 4", "max_epochs: 100000"))
    args = ["fit", "--config", str(config), "--trainer.logger.init_args.version", "reproduce-x"]
    ckpt = tmp_path / "runs" / "rot" / "reproduce-x" / "checkpoints" / "last.ckpt"
    proc = _stage_in_own_group(tmp_path, args)
    deadline = time.time() + 120
    while not ckpt.is_file() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.2)
    assert ckpt.is_file(), proc.poll()
    stage = _children(proc.pid)
    assert len(stage) == 1
    if how == "ctrl-c":
        os.killpg(proc.pid, signal.SIGINT)  # what Ctrl-C in the terminal does
    else:
        proc.send_signal(signal.SIGTERM)  # reproduce's pid only
    try:
        _, err = proc.communicate(timeout=120)
        assert not Path(f"/proc/{stage[0]}").exists() or _state(stage[0]) == "Z", "the stage was left running"
    finally:  # a failure must not leave the stage training beside the next tests
        if Path(f"/proc/{stage[0]}").exists():
            os.kill(stage[0], signal.SIGKILL)
    assert proc.returncode == 130 and "Traceback" not in err, err
    assert f"reproduce was interrupted during stage 1 (python cli.py {shlex.join(args)}); its last completed epoch " \
           f"is saved in {ckpt}. Resume that stage with:" in err, err
    resume = err.split("Resume that stage with:")[1].strip().splitlines()[0]
    assert resume == "python cli.py " + shlex.join(args) + f" --ckpt_path {ckpt}"
    assert torch.load(ckpt, weights_only=True)["epoch"] >= 0  # a completed epoch to resume from


def _children(pid: int) -> list[int]:
    return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]


def _state(pid: int) -> str:
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]


def test_a_failing_stage_is_one_error_line_not_a_traceback(tmp_path):
    args = ["fit", "--config", str(tmp_path / "missing.yaml")]
    proc = _stage_in_own_group(tmp_path, args)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 2 and "Traceback" not in err and "CalledProcessError" not in err, err
    assert err.strip().splitlines()[-1].startswith("error: reproduce stopped: stage 1 (python cli.py fit --config ")
    assert "failed with status 2" in err


def test_another_seed_seeds_every_stage_and_writes_its_own_results(recorded):
    calls, written = recorded
    reproduce.main(["lorenz_T1000", "--size", "cpu", "--seed", "2"])
    assert all(option(a, "--seed_everything") == "2" for a in calls)
    assert "seed2" in option(calls[0], "--trainer.logger.init_args.version")
    assert "--model.init_args.experiment" not in calls[0]  # the SSM stage writes no results
    assert all(option(a, "--model.init_args.experiment") == "lorenz_T1000_cpu_seed2" for a in calls[1:])
    assert written["experiment"] == "lorenz_T1000_cpu_seed2"
    assert written["command"] == "make reproduce EXP=lorenz_T1000 SIZE=cpu SEED=2"
    calls.clear()
    reproduce.main(["lorenz_T1000", "--size", "cpu"])  # without --seed: the configs' seed, the usual names
    assert not any("--seed_everything" in a or "--model.init_args.experiment" in a for a in calls)
