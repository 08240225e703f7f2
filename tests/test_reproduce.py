"""`make reproduce`'s stage list: which configs run, in which order, handing which checkpoints on
(the stages themselves are recorded, not run: each is a CLI run tested elsewhere)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from lightning.pytorch.callbacks import Callback

from experiments import configs, pipeline, reproduce


@pytest.fixture
def recorded(monkeypatch, tmp_path):
    """Stages recorded, not run (each takes 0 s); run folders (runs/...) under tmp_path."""
    calls: list[list[str]] = []
    written = {}
    monkeypatch.setattr(
        pipeline,
        "run_stage",
        lambda args, number, resume_pipeline=None, on_wait=None: (
            calls.append(args) or written.update(resume_pipeline=resume_pipeline) or 0.0
        ),
    )
    monkeypatch.setattr(configs, "absolute", lambda path: tmp_path / path)
    monkeypatch.setattr(
        pipeline,
        "write_pipeline",
        lambda results_dir, experiment, command, pipeline, replaces=None: (
            written.update(experiment=experiment, command=command, pipeline=pipeline, replaces=replaces)
            or configs.ROOT / "README.md"
        ),
    )
    return calls, written


def option(args: list[str], name: str) -> str:
    return args[args.index(name) + 1]


def test_an_experiment_runs_its_ssm_stages_then_every_baseline(recorded, capsys):
    calls, written = recorded
    reproduce.main(["lorenz_T1000", "--size", "cpu"])
    configs = [(a[0], option(a, "--config")) for a in calls]
    assert configs == [
        ("fit", "configs/cpu/lorenz_T1000.yaml"),
        ("test", "configs/cpu/lorenz_T1000_ukf.yaml"),  # the SSM alone: before the encoder's long fit
        ("fit", "configs/cpu/lorenz_T1000_encoder.yaml"),
        ("test", "configs/cpu/lorenz_T1000_encoder.yaml"),
        ("fit", "configs/cpu/baselines/lorenz_T1000_lstm.yaml"),
        ("test", "configs/cpu/baselines/lorenz_T1000_lstm.yaml"),
        ("fit", "configs/cpu/baselines/lorenz_T1000_rkn.yaml"),
        ("test", "configs/cpu/baselines/lorenz_T1000_rkn.yaml"),
    ]
    version = option(calls[0], "--trainer.logger.init_args.version")
    assert all(option(a, "--trainer.logger.init_args.version") == version for a in calls)
    ssm_ckpt = f"runs/lorenz_T1000_cpu/{version}/checkpoints/last.ckpt"
    assert all(option(a, "--model.init_args.ssm_checkpoint") == ssm_ckpt for a in calls[1:4])
    assert option(calls[3], "--ckpt_path") == f"runs/lorenz_T1000_encoder_cpu/{version}/checkpoints/last.ckpt"
    assert option(calls[5], "--ckpt_path") == f"runs/lorenz_T1000_lstm_cpu/{version}/checkpoints/last.ckpt"
    assert "--model.init_args.ssm_checkpoint" not in calls[4] + calls[5]
    assert (
        written["experiment"] == "lorenz_T1000_cpu" and written["command"] == "make reproduce EXP=lorenz_T1000 SIZE=cpu"
    )
    assert len(written["pipeline"]["stages"]) == 8
    assert all(s["command"] == "python cli.py " + " ".join(a) for s, a in zip(written["pipeline"]["stages"], calls))


def test_a_baseline_alone_and_without_baselines(recorded):
    calls, written = recorded
    reproduce.main(["pendulum_rkn"])
    assert [(a[0], option(a, "--config")) for a in calls] == [
        ("fit", "configs/baselines/pendulum_rkn.yaml"),
        ("test", "configs/baselines/pendulum_rkn.yaml"),
    ]
    assert written["experiment"] == "pendulum"  # the same results file as the SSM's
    calls.clear()
    reproduce.main(["pendulum", "--no-baselines"])
    assert [(a[0], option(a, "--config")) for a in calls] == [
        ("fit", "configs/pendulum.yaml"),
        ("test", "configs/pendulum_optimise.yaml"),  # states fitted through the SSM alone: before the encoder
        ("fit", "configs/pendulum_encoder.yaml"),
        ("test", "configs/pendulum_encoder.yaml"),
    ]
    version = option(calls[0], "--trainer.logger.init_args.version")
    assert option(calls[1], "--model.init_args.ssm_checkpoint") == f"runs/pendulum/{version}/checkpoints/last.ckpt"
    assert (
        written["command"] == "python -m experiments.reproduce pendulum --no-baselines"
    )  # not make's: it has no such option


def test_epoch_budgets_go_to_their_own_stages_only(recorded, capsys):
    """--encoder-epochs sets the encoder fit's max_epochs, --baseline-epochs each baseline fit's; the SSM fit and
    the tests keep their configs' (they take no epochs), and the results file names the command with the budgets."""
    calls, written = recorded
    reproduce.main(["pendulum", "--encoder-epochs", "7", "--baseline-epochs", "5"])
    budget = {
        (a[0], Path(option(a, "--config")).stem): option(a, "--trainer.max_epochs")
        for a in calls
        if "--trainer.max_epochs" in a
    }
    assert budget == {("fit", "pendulum_encoder"): "7", ("fit", "pendulum_lstm"): "5", ("fit", "pendulum_rkn"): "5"}
    assert len(calls) == 8
    assert written["command"] == "python -m experiments.reproduce pendulum --encoder-epochs 7 --baseline-epochs 5"
    with pytest.raises(SystemExit):
        reproduce.main(["pendulum_lstm", "--baseline-epochs", "0"])
    assert "--baseline-epochs must be >= 1, got 0" in capsys.readouterr().err


def test_no_encoder_runs_the_ssm_and_its_own_tests_only(recorded, capsys):
    """--no-encoder: the SSM fit, its tests of the SSM alone (UKF; fitted states; control with the UKF), the baselines;
    no encoder fit and nothing that needs the encoder. Refused before any stage where nothing would then score the
    SSM, or beside an encoder budget."""
    calls, written = recorded
    reproduce.main(["lorenz_T1000", "--size", "cpu", "--no-encoder"])
    assert [(a[0], option(a, "--config")) for a in calls] == [
        ("fit", "configs/cpu/lorenz_T1000.yaml"),
        ("test", "configs/cpu/lorenz_T1000_ukf.yaml"),
        ("fit", "configs/cpu/baselines/lorenz_T1000_lstm.yaml"),
        ("test", "configs/cpu/baselines/lorenz_T1000_lstm.yaml"),
        ("fit", "configs/cpu/baselines/lorenz_T1000_rkn.yaml"),
        ("test", "configs/cpu/baselines/lorenz_T1000_rkn.yaml"),
    ]
    assert written["experiment"] == "lorenz_T1000_cpu" and len(written["pipeline"]["stages"]) == 6
    assert written["command"] == "python -m experiments.reproduce lorenz_T1000 --size cpu --no-encoder"
    calls.clear()
    reproduce.main(["pendulum_torque", "--no-encoder", "--no-baselines"])
    assert [(a[0], option(a, "--config")) for a in calls] == [
        ("fit", "configs/pendulum_torque.yaml"),
        ("test", "configs/pendulum_torque_control.yaml"),  # the UKF estimating the state; not again with an encoder
        ("test", "configs/pendulum_torque_control_2nm.yaml"),  # each control setting
    ]
    assert "--model.init_args.encoder_checkpoint" not in calls[1] + calls[2]
    calls.clear()
    reproduce.main(["pendulum", "--no-encoder", "--no-baselines"])
    assert [(a[0], option(a, "--config")) for a in calls] == [
        ("fit", "configs/pendulum.yaml"),
        ("test", "configs/pendulum_optimise.yaml"),  # its one test of the SSM alone
    ]
    calls.clear()
    for argv, message in [
        (
            ["quad", "--no-encoder"],
            "--no-encoder: quad has no test of its SSM alone (no ukf, optimise or control stage in "
            "configs/experiments.yaml)",
        ),
        (["lorenz_T1000", "--no-encoder", "--encoder-epochs", "5"], "--encoder-epochs budgets the encoder stage"),
        (["pendulum_control", "--no-encoder"], "--no-encoder: pendulum_control is a suite of experiments"),
    ]:
        with pytest.raises(SystemExit):
            reproduce.main(argv)
        assert message in capsys.readouterr().err
    assert calls == []


def test_no_encoder_given_or_dropped_on_resume(recorded, tmp_path):
    """Dropped on resume, a run that ended without its encoder gains the encoder's stages alone, and its results
    record replaces the one without; given on resume, a run stopped in its encoder fit ends without it."""
    import json

    calls, written = recorded
    base = ["lorenz_T1000", "--size", "cpu", "--no-baselines"]
    reproduce.main([*base, "--no-encoder"])
    assert len(calls) == 2
    version = option(calls[0], "--trainer.logger.init_args.version")
    calls.clear()
    reproduce.main([*base, "--resume", version])
    assert [(a[0], option(a, "--config")) for a in calls] == [
        ("fit", "configs/cpu/lorenz_T1000_encoder.yaml"),
        ("test", "configs/cpu/lorenz_T1000_encoder.yaml"),
    ]
    assert written["command"] == "python -m experiments.reproduce lorenz_T1000 --size cpu --no-baselines"
    assert written["replaces"] == "python -m experiments.reproduce lorenz_T1000 --size cpu --no-baselines --no-encoder"
    assert len(written["pipeline"]["stages"]) == 4
    # a new run, stopped during its encoder fit (the SSM fit and its UKF test finished), then given --no-encoder
    calls.clear()
    reproduce.main(base)
    version = option(calls[0], "--trainer.logger.init_args.version")
    record = tmp_path / "runs" / "lorenz_T1000_cpu" / version / "reproduce.json"
    finished = json.loads(record.read_text())
    ssm_fit, ukf, encoder_fit = finished["stages"][:3]
    running = {"command": encoder_fit["command"], "seconds": 0.0, "runs": 1}
    record.write_text(json.dumps({"options": finished["options"], "stages": [ssm_fit, ukf], "running": running}))
    calls.clear()
    reproduce.main([*base, "--no-encoder", "--resume", version])
    assert calls == []  # nothing left to run: the results file's record is written
    assert [s["command"] for s in written["pipeline"]["stages"]] == [ssm_fit["command"], ukf["command"]]
    assert written["command"] == "python -m experiments.reproduce lorenz_T1000 --size cpu --no-baselines --no-encoder"


def test_options_after_a_double_dash_go_to_every_stage_last(recorded, tmp_path):
    """``-- ARGS`` (make's ARGS) is appended to every stage's command after its own options (the last value wins in
    LightningCLI), the results file names it, and a resume given other ARGS is refused."""
    calls, written = recorded
    reproduce.main(
        ["pendulum", "--encoder-epochs", "7", "--", "--trainer.max_epochs", "1", "--data.init_args.n_test", "9"]
    )
    assert len(calls) == 8
    assert all(a[-4:] == ["--trainer.max_epochs", "1", "--data.init_args.n_test", "9"] for a in calls)
    encoder_fit = calls[2]
    assert encoder_fit.index("7") < len(encoder_fit) - 3  # the budget first, the appended value last
    assert written["command"] == (
        "python -m experiments.reproduce pendulum --encoder-epochs 7 -- --trainer.max_epochs 1 --data.init_args.n_test 9"
    )
    calls.clear()
    reproduce.main(["pendulum", "--", "--trainer.max_epochs", "1"])
    assert written["command"] == "make reproduce EXP=pendulum ARGS='--trainer.max_epochs 1'"
    version = option(calls[0], "--trainer.logger.init_args.version")
    with pytest.raises(SystemExit, match="started with other options"):
        reproduce.main(["pendulum", "--resume", version, "--", "--trainer.max_epochs", "2"])


def test_unknown_experiment_lists_the_known_ones(recorded):
    with pytest.raises(SystemExit, match=r"no paper-size experiment 'pendulm'.*'pendulum'.*'pendulum_lstm'"):
        reproduce.main(["pendulm"])
    with pytest.raises(SystemExit, match=r"no cpu-size experiment 'pendulum_torque'.*'pendulum_fc'"):
        reproduce.main(["pendulum_torque", "--size", "cpu"])  # a paper-size experiment only


def test_a_config_that_does_not_compose_stops_with_one_line_before_any_stage(recorded, monkeypatch, tmp_path):
    """An interpolation under a dotted key (it resolves relative to the wrong section): one line naming the file and
    the fix, no stage run, no traceback."""
    fit = tmp_path / "bad.yaml"
    fit.write_text(
        "config: " + str(configs.ROOT / "configs/benchmarks/cascaded_tanks_amortised.yaml") + "\n"
        'model.init_args.g: {class_path: ssm_ms.nets.MLPReadout, init_args: {state_dim: "${init_args.state_dim}", '
        "out_features: 1}}\n"
    )
    monkeypatch.setattr(reproduce, "read_registry", lambda: {"benchmarks": {"bad": {"fit": fit, "test": fit}}})
    with pytest.raises(SystemExit, match=r"^error: .*bad\.yaml: a config interpolation cannot be resolved") as stop:
        reproduce.main(["bad"])
    assert "\n" not in str(stop.value) and recorded[0] == []


# ---------------------------------------------------------------------------- a stage interrupted or failing
def _stage_in_own_group(tmp_path, args, sigint_ignored: bool = False):
    """``pipeline.run_stage(args)`` in a new process group, with SIGINT's default disposition (as a terminal runs
    ``make reproduce``; the tests themselves may run where SIGINT is ignored, e.g. started in the background by a
    script, and a child inherits that), or with SIGINT ignored (``sigint_ignored``: as ``nohup ... &`` from a
    script starts it)."""
    import signal
    import subprocess
    import sys

    script = f"from experiments import pipeline; pipeline.run_stage({args!r}, 1)"
    out = open(tmp_path / "stage.log", "w")
    env = dict(__import__("os").environ, OMP_NUM_THREADS="1")
    return subprocess.Popen(
        [sys.executable, "-c", script],
        cwd=configs.ROOT,
        start_new_session=True,
        stdout=out,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN if sigint_ignored else signal.SIG_DFL),
    )


def _long_stage_past_its_first_checkpoint(tmp_path, sigint_ignored: bool = False):
    """A ``fit`` stage of 100000 epochs started by ``_stage_in_own_group``, returned once its first ``last.ckpt`` is
    written: ``(reproduce's process, the stage's args, that checkpoint)``."""
    import os
    import signal
    import time

    from tests.test_cli import ROTATION

    config = tmp_path / "rot.yaml"
    config.write_text(ROTATION.format(root=tmp_path).replace("max_epochs: 4", "max_epochs: 100000"))
    args = ["fit", "--config", str(config), "--trainer.logger.init_args.version", "reproduce-x"]
    ckpt = tmp_path / "runs" / "rot" / "reproduce-x" / "checkpoints" / "last.ckpt"
    proc = _stage_in_own_group(tmp_path, args, sigint_ignored=sigint_ignored)
    deadline = time.time() + 120
    while not ckpt.is_file() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.2)
    if not ckpt.is_file():
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        raise AssertionError(f"no checkpoint within 120 s (reproduce's status: {proc.poll()})")
    return proc, args, ckpt


# make test runs Ctrl-C (the stage and reproduce signalled together; reproduce's handler forwards SIGTERM to the stage
# then too); make test-slow the signals to reproduce alone, SIGTERM and SIGINT started ignored (the same handler and
# forwarding; ~25 s each on the slowest CPUs: a stage's start, then reproduce's own import of Lightning to name the
# checkpoint, which a real reproduce has made before its first stage)
@pytest.mark.parametrize(
    "how", ["ctrl-c", *(pytest.param(how, marks=pytest.mark.slow) for how in ("sigterm", "sigint-background"))]
)
def test_ctrl_c_or_sigterm_during_a_stage_names_it_and_the_command_that_resumes_it(tmp_path, how):
    """Ctrl-C reaches the stage and reproduce together (SIGINT to the process group); SIGTERM or SIGINT to reproduce
    alone (``kill <pid>``, ``kill -INT <pid>``) is forwarded to the stage, SIGINT even where reproduce was started
    with it ignored (``nohup ... &`` from a script). Either way: no traceback, status 130, the stage stopped (not
    left running: the stage trains for 100000 epochs), named, and the command that resumes it from the last
    completed epoch."""
    import os
    import shlex
    import signal

    import torch

    proc, args, ckpt = _long_stage_past_its_first_checkpoint(tmp_path, sigint_ignored=how == "sigint-background")
    stage = _children(proc.pid)
    assert len(stage) == 1
    if how == "ctrl-c":
        os.killpg(proc.pid, signal.SIGINT)  # what Ctrl-C in the terminal does
    else:  # reproduce's pid only
        proc.send_signal(signal.SIGTERM if how == "sigterm" else signal.SIGINT)
    try:
        _, err = proc.communicate(timeout=120)
        assert not Path(f"/proc/{stage[0]}").exists() or _state(stage[0]) == "Z", "the stage was left running"
    finally:  # a failure must not leave reproduce or its stage training beside the next tests
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        if Path(f"/proc/{stage[0]}").exists():
            os.kill(stage[0], signal.SIGKILL)
    assert proc.returncode == 130 and "Traceback" not in err, err
    assert (
        f"reproduce was interrupted during stage 1 (python cli.py {shlex.join(args)}); its last completed epoch "
        f"is saved in {ckpt}. Resume that stage with:" in err
    ), err
    resume = err.split("Resume that stage with:")[1].strip().splitlines()[0]
    assert resume == "python cli.py " + shlex.join(args) + f" --ckpt_path {ckpt}"
    assert torch.load(ckpt, weights_only=True)["epoch"] >= 0  # a completed epoch to resume from


def test_a_stage_killed_from_outside_names_the_signal_and_what_is_kept(tmp_path):
    """A stage killed with SIGKILL (what the kernel's out-of-memory killer sends) prints nothing itself: reproduce
    names the signal, the likely killer and the checkpoint kept, and exits with 137 as a shell would."""
    import os
    import signal

    proc, args, ckpt = _long_stage_past_its_first_checkpoint(tmp_path)
    try:
        (stage,) = _children(proc.pid)
        os.kill(stage, signal.SIGKILL)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 137 and "Traceback" not in err, err
    line = err.strip().splitlines()[-1]
    assert line.startswith("error: reproduce stopped: stage 1 (python cli.py fit --config "), line
    assert "was killed by SIGKILL (on Linux most often the kernel's out-of-memory killer" in line, line
    assert f"its last completed epoch is kept in {ckpt}" in line, line


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


# ---------------------------------------------------------------------------- --resume
class KillAt(Callback):
    """SIGKILL to the whole process group (reproduce and its stage: the machine going away) at the start of epoch
    ``$KILL_AT_EPOCH``; each epoch started appended to the file ``$EPOCH_LOG``; nothing without those variables."""

    def on_train_epoch_start(self, trainer, pl_module):
        import os
        import signal

        if "EPOCH_LOG" in os.environ:
            with open(os.environ["EPOCH_LOG"], "a") as log:
                log.write(f"{trainer.current_epoch}\n")
        if os.environ.get("KILL_AT_EPOCH") == str(trainer.current_epoch):
            os.killpg(os.getpgrp(), signal.SIGKILL)


def test_resume_runs_what_is_left_and_continues_the_interrupted_fit(recorded, tmp_path, capsys):
    """A run stopped during its encoder fit (record: SSM fit finished, encoder fit running, 100 s kept up to its
    last.ckpt): resumed, the SSM fit is not run again, the encoder fit continues from its last.ckpt, every later
    stage runs; the encoder stage's seconds are the 100 kept plus the resumed run's."""
    import json

    calls, written = recorded
    reproduce.main(["lorenz_T1000", "--size", "cpu", "--no-baselines"])
    version = option(calls[0], "--trainer.logger.init_args.version")
    record = tmp_path / "runs" / "lorenz_T1000_cpu" / version / "reproduce.json"
    finished = json.loads(record.read_text())
    assert (
        f"finish it with:\n  python -m experiments.reproduce lorenz_T1000 --size cpu --no-baselines --resume {version}"
        in capsys.readouterr().out
    )  # said at the start: a run killed outright prints nothing at its end
    assert finished["running"] is None and len(finished["stages"]) == 4
    assert finished["options"]["experiment"] == "lorenz_T1000" and finished["options"]["no_baselines"] is True
    # as the record reads when the machine stopped during stage 3 (the SSM fit and its UKF test finished)
    stage1, ukf, stage3 = finished["stages"][:3]
    record.write_text(
        json.dumps(
            {
                "options": finished["options"],
                "stages": [{**stage1, "seconds": 3000.0}, {**ukf, "seconds": 40.0}],
                "running": {"command": stage3["command"], "seconds": 100.0, "runs": 1},
            }
        )
    )
    enc_ckpt = tmp_path / "runs" / "lorenz_T1000_encoder_cpu" / version / "checkpoints" / "last.ckpt"
    enc_ckpt.parent.mkdir(parents=True)
    enc_ckpt.write_bytes(b"")
    calls.clear()
    reproduce.main(["lorenz_T1000", "--no-baselines", "--size", "cpu", "--resume", version])  # options in any order
    assert [(a[0], option(a, "--config")) for a in calls] == [
        ("fit", "configs/cpu/lorenz_T1000_encoder.yaml"),
        ("test", "configs/cpu/lorenz_T1000_encoder.yaml"),
    ]
    assert option(calls[0], "--ckpt_path") == f"runs/lorenz_T1000_encoder_cpu/{version}/checkpoints/last.ckpt"
    stages = written["pipeline"]["stages"]
    assert [s["seconds"] for s in stages] == [3000.0, 40.0, 100.0, 0.0] and stages[2]["runs"] == 2
    assert stages[2]["command"] == stage3["command"]  # the stage's command, without the --ckpt_path it resumed with
    assert written["command"] == "python -m experiments.reproduce lorenz_T1000 --no-baselines --size cpu"  # no --resume
    assert (
        written["resume_pipeline"] == f"python -m experiments.reproduce lorenz_T1000 --no-baselines --size cpu "
        f"--resume {version}"
    )  # what an interrupted stage prints
    assert json.loads(record.read_text())["running"] is None


def test_a_stage_keeps_the_time_to_its_last_checkpoint_when_copied_to_another_machine(recorded, tmp_path, monkeypatch):
    """The time a stopped fit kept is measured while it runs (its last checkpoint's time against the run's start,
    on its own machine), not on resume from the file's time, which a copy to another machine sets to the copy's.
    Run 1 writes a checkpoint 50 s into the run (the record then says so), works on and is lost; the checkpoint
    is copied (its time now a day later) and the run resumed: the stage's seconds are the 50 kept plus run 2's."""
    import json
    import os

    calls, written = recorded
    base = ["lorenz_T1000", "--size", "cpu", "--no-baselines"]
    reproduce.main(base)
    version = option(calls[0], "--trainer.logger.init_args.version")
    record = tmp_path / "runs" / "lorenz_T1000_cpu" / version / "reproduce.json"
    finished = json.loads(record.read_text())
    record.write_text(json.dumps({**finished, "stages": finished["stages"][:2]}))  # stopped before the encoder fit
    ckpt = tmp_path / "runs" / "lorenz_T1000_encoder_cpu" / version / "checkpoints" / "last.ckpt"
    seen = []

    def lost(args, number, resume_pipeline=None, on_wait=None):
        if "lorenz_T1000_encoder" not in option(args, "--config") or args[0] != "fit":
            return 7.0
        start = time.time()
        ckpt.parent.mkdir(parents=True, exist_ok=True)
        ckpt.write_bytes(b"")
        os.utime(ckpt, (start + 50, start + 50))  # the epoch's checkpoint, 50 s into the run
        on_wait()  # the tick after it
        seen.append(json.loads(record.read_text())["running"]["seconds"])
        raise KeyboardInterrupt  # the machine is lost later in the run

    with monkeypatch.context() as patch:
        patch.setattr(pipeline, "run_stage", lost)
        with pytest.raises(KeyboardInterrupt):
            reproduce.main([*base, "--resume", version])
    assert seen and 49.0 <= seen[0] <= 51.0
    later = time.time() + 86_400
    os.utime(ckpt, (later, later))  # copied to another machine a day later
    reproduce.main([*base, "--resume", version])
    encoder_fit = next(s for s in written["pipeline"]["stages"] if "lorenz_T1000_encoder" in s["command"])
    assert encoder_fit["runs"] == 2 and 49.0 <= encoder_fit["seconds"] <= 51.0  # 50 kept + run 2's 0 s


def test_a_running_stage_calls_on_wait_every_tick_and_once_at_its_end(monkeypatch, capfd):
    """What keeps the record's time current: ``run_stage`` calls ``on_wait`` while the stage runs and after it."""
    ticks = []
    monkeypatch.setattr(pipeline, "WAIT_TICK", 0.002)
    # a stage refused before Lightning's import (a missing config: ~0.1 s, not the ~10 s of a real start)
    with pytest.raises(SystemExit):
        pipeline.run_stage(["fit", "--config", "missing.yaml"], 1, on_wait=lambda: ticks.append(time.monotonic()))
    assert "missing.yaml" in capfd.readouterr().err  # the stage ran, for well over a tick
    assert len(ticks) >= 3


def test_resume_refuses_another_run_or_other_options(recorded, tmp_path):
    calls, _ = recorded
    with pytest.raises(SystemExit, match=r"--resume: reproduce-20990101-000000 has no record of a reproduce run"):
        reproduce.main(["pendulum_rkn", "--resume", "reproduce-20990101-000000"])
    reproduce.main(["lorenz_T1000", "--size", "cpu", "--seed", "1"])
    version = option(calls[0], "--trainer.logger.init_args.version")
    calls.clear()
    with pytest.raises(SystemExit, match=r"was started with other options \(seed: 1 then, 2 now\)"):
        reproduce.main(["lorenz_T1000", "--size", "cpu", "--seed", "2", "--resume", version])
    assert calls == []  # refused before any stage


def test_a_pipeline_killed_mid_fit_resumes_to_the_same_model_as_an_uninterrupted_run(tmp_path, monkeypatch):
    """SIGKILL (the machine going away) during a fit stage, then the same stage resumed through the pipeline's
    record: it continues from the last completed epoch and ends with the parameters of a run never stopped."""
    import os
    import signal
    import subprocess
    import sys

    import torch

    from ssm_ms.cli import main as cli_main
    from tests.test_cli import ROTATION

    config = tmp_path / "rot.yaml"
    config.write_text(ROTATION.format(root=tmp_path).replace("max_epochs: 4", "max_epochs: 6"))

    def args(version):
        return [
            "fit",
            "--config",
            str(config),
            "--trainer.logger.init_args.version",
            version,
            "--trainer.callbacks+=tests.test_reproduce.KillAt",
        ]

    def ckpt(version):
        return tmp_path / "runs" / "rot" / version / "checkpoints" / "last.ckpt"

    record = tmp_path / "reproduce.json"
    script = (
        f"from pathlib import Path; from experiments import pipeline; "
        f"pipeline.Pipeline(Path({str(record)!r}), {{}}, 'resume', resume=False).stage({args('cut')!r})"
    )
    env = dict(os.environ, OMP_NUM_THREADS="1", KILL_AT_EPOCH="3")
    proc = subprocess.Popen(
        [sys.executable, "-c", script],
        cwd=configs.ROOT,
        start_new_session=True,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    assert proc.wait(timeout=300) == -signal.SIGKILL
    assert torch.load(ckpt("cut"), weights_only=True)["epoch"] == 2  # epochs 0-2 kept, the run stopped in epoch 3

    monkeypatch.setenv("EPOCH_LOG", str(tmp_path / "epochs.txt"))
    resumed = pipeline.Pipeline(record, {}, "resume", resume=True)
    resumed.stage(args("cut"))
    assert (tmp_path / "epochs.txt").read_text().split() == ["3", "4", "5"]  # continued, not started again
    assert resumed.stages[0]["runs"] == 2
    monkeypatch.delenv("EPOCH_LOG")
    cli_main(args("full"))  # in this process: one interpreter start less
    full, resumed = (torch.load(ckpt(v), weights_only=True) for v in ("full", "cut"))
    assert resumed["epoch"] == full["epoch"] == 5 and resumed["global_step"] == full["global_step"]
    for key, value in full["state_dict"].items():
        torch.testing.assert_close(resumed["state_dict"][key], value, rtol=0, atol=0)


# ---------------------------------------------------------------------------- --resume with a larger epoch budget
def test_a_budget_raised_on_resume_continues_that_fit_and_tests_again(recorded, tmp_path, capsys):
    """A finished run resumed with a larger --encoder-epochs: the encoder fit continues from its last.ckpt to the new
    count (its earlier seconds kept), its test runs again on the new checkpoint; the SSM fit and the UKF test, which
    do not depend on the encoder, are not run again. Lowering a budget, or changing another option, is refused."""
    import json

    calls, written = recorded
    reproduce.main(["lorenz_T1000", "--size", "cpu", "--no-baselines", "--encoder-epochs", "7"])
    version = option(calls[0], "--trainer.logger.init_args.version")
    record = tmp_path / "runs" / "lorenz_T1000_cpu" / version / "reproduce.json"
    saved = json.loads(record.read_text())
    saved["stages"][2]["seconds"] = 500.0  # the 7 epochs took 500 s (stage 3, after the SSM fit and UKF test)
    record.write_text(json.dumps(saved))
    enc_ckpt = tmp_path / "runs" / "lorenz_T1000_encoder_cpu" / version / "checkpoints" / "last.ckpt"
    enc_ckpt.parent.mkdir(parents=True)
    enc_ckpt.write_bytes(b"")

    calls.clear()
    with pytest.raises(SystemExit, match=r"cannot be cut back to --encoder-epochs 5 \(it was run with 7\)"):
        reproduce.main(
            ["lorenz_T1000", "--size", "cpu", "--no-baselines", "--encoder-epochs", "5", "--resume", version]
        )
    with pytest.raises(SystemExit, match=r"other options \(seed: None then, 1 now\)"):
        reproduce.main(
            [
                "lorenz_T1000",
                "--size",
                "cpu",
                "--no-baselines",
                "--encoder-epochs",
                "9",
                "--seed",
                "1",
                "--resume",
                version,
            ]
        )
    assert calls == []

    reproduce.main(["lorenz_T1000", "--size", "cpu", "--no-baselines", "--encoder-epochs", "9", "--resume", version])
    assert [(a[0], option(a, "--config")) for a in calls] == [
        ("fit", "configs/cpu/lorenz_T1000_encoder.yaml"),
        ("test", "configs/cpu/lorenz_T1000_encoder.yaml"),
    ]
    assert option(calls[0], "--trainer.max_epochs") == "9"
    assert option(calls[0], "--ckpt_path") == f"runs/lorenz_T1000_encoder_cpu/{version}/checkpoints/last.ckpt"
    stages = written["pipeline"]["stages"]
    assert len(stages) == 4 and stages[2]["seconds"] == 500.0 and stages[2]["runs"] == 2
    assert "--trainer.max_epochs 9" in stages[2]["command"] and "--ckpt_path" not in stages[2]["command"]
    assert (
        written["command"]
        == "python -m experiments.reproduce lorenz_T1000 --size cpu --no-baselines --encoder-epochs 9"
    )
    # the results file keeps one record of this run: the 9-epoch command's replaces the 7-epoch one's
    assert (
        written["replaces"]
        == "python -m experiments.reproduce lorenz_T1000 --size cpu --no-baselines --encoder-epochs 7"
    )
    # the record now holds the raised budget: resuming it again with that budget runs nothing
    assert json.loads(record.read_text())["options"]["encoder_epochs"] == 9
    assert len(json.loads(record.read_text())["stages"]) == 4
    calls.clear()
    reproduce.main(["lorenz_T1000", "--size", "cpu", "--no-baselines", "--encoder-epochs", "9", "--resume", version])
    assert calls == []


def test_a_raised_budget_interrupted_and_resumed_again_still_replaces_the_first_record(recorded, tmp_path, monkeypatch):
    """Started with --encoder-epochs 7 (finished: the results file holds its record), resumed with 9 and stopped
    during that fit, resumed with 9 again: the finished run's record replaces the 7-epoch one's, not a record of
    the 9-epoch command that was never written (which would leave both in the results file)."""
    calls, written = recorded
    base = ["lorenz_T1000", "--size", "cpu", "--no-baselines"]
    reproduce.main([*base, "--encoder-epochs", "7"])
    version = option(calls[0], "--trainer.logger.init_args.version")
    first = written["command"]
    enc_ckpt = tmp_path / "runs" / "lorenz_T1000_encoder_cpu" / version / "checkpoints" / "last.ckpt"
    enc_ckpt.parent.mkdir(parents=True)
    enc_ckpt.write_bytes(b"")

    def stopped(args, number, resume_pipeline=None, on_wait=None):
        raise KeyboardInterrupt  # the machine stops during the extended fit

    with monkeypatch.context() as patch:
        patch.setattr(pipeline, "run_stage", stopped)
        with pytest.raises(KeyboardInterrupt):
            reproduce.main([*base, "--encoder-epochs", "9", "--resume", version])
    written.clear()
    reproduce.main([*base, "--encoder-epochs", "9", "--resume", version])
    assert written["command"] == first.replace("--encoder-epochs 7", "--encoder-epochs 9")
    assert written["replaces"] == first
    written.clear()
    calls.clear()
    reproduce.main([*base, "--encoder-epochs", "11", "--resume", version])  # raised once more, uninterrupted
    assert written["replaces"] == first.replace("--encoder-epochs 7", "--encoder-epochs 9")


def test_a_baseline_budget_raised_on_resume_continues_the_fit_and_tests_again(recorded, tmp_path):
    calls, written = recorded
    reproduce.main(["pendulum_lstm", "--baseline-epochs", "5"])
    version = option(calls[0], "--trainer.logger.init_args.version")
    ckpt = tmp_path / "runs" / "pendulum_lstm" / version / "checkpoints" / "last.ckpt"
    ckpt.parent.mkdir(parents=True)
    ckpt.write_bytes(b"")
    calls.clear()
    reproduce.main(["pendulum_lstm", "--baseline-epochs", "8", "--resume", version])
    assert [(a[0], option(a, "--trainer.max_epochs") if a[0] == "fit" else None) for a in calls] == [
        ("fit", "8"),
        ("test", None),
    ]
    assert option(calls[0], "--ckpt_path").endswith(f"pendulum_lstm/{version}/checkpoints/last.ckpt")


def test_a_fit_extended_on_resume_ends_as_a_fit_given_that_budget_from_the_start(tmp_path, monkeypatch):
    """Real fits: 2 epochs, then the pipeline resumed with 5: epochs 2-4 run (not 0-4 again) and the parameters
    equal those of a 5-epoch run (the schedule's milestone at epoch 2 falls in the extension). The stages run in this
    process (a command-line start is ~10 s of imports on the slowest CPUs); a fit resumed in a process of its own is
    test_a_pipeline_killed_mid_fit_resumes_to_the_same_model_as_an_uninterrupted_run."""
    import torch

    from ssm_ms.cli import main as cli_main
    from tests.test_cli import ROTATION

    def in_process(args, number, resume_pipeline=None, on_wait=None):  # run_stage's python cli.py *args, here
        start = time.time()
        cli_main(args)
        return time.time() - start

    monkeypatch.setattr(pipeline, "run_stage", in_process)
    config = tmp_path / "rot.yaml"
    config.write_text(ROTATION.format(root=tmp_path))

    def args(version, epochs):
        return [
            "fit",
            "--config",
            str(config),
            "--trainer.max_epochs",
            str(epochs),
            "--trainer.logger.init_args.version",
            version,
            "--trainer.callbacks+=tests.test_reproduce.KillAt",
        ]

    record = tmp_path / "reproduce.json"
    pipeline.Pipeline(record, {}, "resume", resume=False).stage(args("cut", 2))
    monkeypatch.setenv("EPOCH_LOG", str(tmp_path / "epochs.txt"))
    resumed = pipeline.Pipeline(record, {}, "resume", resume=True)
    assert resumed.stage(args("cut", 5)) is True
    assert (tmp_path / "epochs.txt").read_text().split() == ["2", "3", "4"]  # continued, not started again
    assert resumed.stages[0]["runs"] == 2
    monkeypatch.delenv("EPOCH_LOG")
    cli_main(args("full", 5))
    ckpt = tmp_path / "runs" / "rot" / "{}" / "checkpoints" / "last.ckpt"
    full, cut = (torch.load(str(ckpt).format(v), weights_only=True) for v in ("full", "cut"))
    assert cut["epoch"] == full["epoch"] == 4 and cut["global_step"] == full["global_step"]
    for key, value in full["state_dict"].items():
        torch.testing.assert_close(cut["state_dict"][key], value, rtol=0, atol=0)


def test_control_stages_and_a_suite_of_experiments(recorded):
    """An SSM's control test runs before its encoder stages, with the SSM's checkpoint, then again after them with the
    encoder estimating the state (the SSM has one); a controller without an SSM
    (the true model) is one test stage; a suite (configs/experiments.yaml) runs its experiments one after the other."""
    calls, written = recorded
    reproduce.main(["pendulum_control"])
    stages = [(a[0], option(a, "--config")) for a in calls]
    assert stages == [
        ("fit", "configs/pendulum_torque.yaml"),
        ("test", "configs/pendulum_torque_control.yaml"),  # the SSM and the UKF: before the encoder, each setting
        ("test", "configs/pendulum_torque_control_2nm.yaml"),
        ("fit", "configs/pendulum_torque_encoder.yaml"),
        ("test", "configs/pendulum_torque_encoder.yaml"),
        ("test", "configs/pendulum_torque_control.yaml"),  # again, the encoder estimating the state
        ("test", "configs/pendulum_torque_control_2nm.yaml"),
        ("test", "configs/pendulum_torque_record.yaml"),  # its own episodes recorded, with the encoder
        ("fit", "configs/pendulum_torque_dagger.yaml"),  # trained again with them
        ("test", "configs/pendulum_torque_dagger_control.yaml"),
        ("fit", "configs/pendulum_torque_dagger_encoder.yaml"),
        ("test", "configs/pendulum_torque_dagger_encoder.yaml"),
        ("test", "configs/pendulum_torque_dagger_control.yaml"),
        ("fit", "configs/pendulum_torque_single.yaml"),
        ("test", "configs/pendulum_torque_single_control.yaml"),
        ("fit", "configs/pendulum_torque_single_encoder.yaml"),
        ("test", "configs/pendulum_torque_single_encoder.yaml"),
        ("test", "configs/pendulum_torque_single_control.yaml"),
        ("test", "configs/pendulum_true_control.yaml"),  # the true model: its settings one after the other
        ("test", "configs/pendulum_true_control_2nm.yaml"),
        ("fit", "configs/pendulum_sensors.yaml"),
        ("test", "configs/pendulum_sensors_control.yaml"),
        ("fit", "configs/pendulum_sensors_encoder.yaml"),
        ("test", "configs/pendulum_sensors_encoder.yaml"),
        ("test", "configs/pendulum_sensors_control.yaml"),
        ("fit", "configs/pendulum_torque_amortised.yaml"),  # no encoder stage: its control test once
        ("test", "configs/pendulum_torque_amortised_control.yaml"),
        ("test", "configs/pendulum_torque_amortised_control_2nm.yaml"),
    ]
    version = option(calls[0], "--trainer.logger.init_args.version")
    ssm = f"runs/pendulum_torque/{version}/checkpoints/last.ckpt"
    encoder = f"runs/pendulum_torque_encoder/{version}/checkpoints/last.ckpt"
    for call in calls[1:3]:
        assert (
            "--model.init_args.encoder_checkpoint" not in call
            and option(call, "--model.init_args.ssm_checkpoint") == ssm
        )
    for call in calls[5:8]:  # both settings and the recording: the same SSM and encoder
        assert option(call, "--model.init_args.ssm_checkpoint") == ssm
        assert option(call, "--model.init_args.encoder_checkpoint") == encoder
    assert option(calls[12], "--model.init_args.ssm_checkpoint") == (
        f"runs/pendulum_torque_dagger/{option(calls[8], '--trainer.logger.init_args.version')}/checkpoints/last.ckpt"
    )
    single = option(calls[13], "--trainer.logger.init_args.version")
    assert (
        option(calls[14], "--model.init_args.ssm_checkpoint")
        == f"runs/pendulum_torque_single/{single}/checkpoints/last.ckpt"
    )
    assert (
        option(calls[17], "--model.init_args.encoder_checkpoint")
        == f"runs/pendulum_torque_single_encoder/{single}/checkpoints/last.ckpt"
    )
    assert "--model.init_args.ssm_checkpoint" not in calls[18] + calls[19]
    assert written["experiment"] == "pendulum_control_2nm"  # the last results file the suite's last stage wrote
    with pytest.raises(SystemExit):
        reproduce.main(["pendulum_control", "--resume", "reproduce-1"])


def fit_writing_best(calls, root, run):
    """A ``run_stage`` that records its calls and, for the fit of the run logged under ``runs/<run>/``, writes the
    ``best.ckpt`` a config keeping its best epoch would."""

    def stage(args, number, resume_pipeline=None, on_wait=None):
        calls.append(args)
        if args[0] == "fit" and Path(option(args, "--config")).stem == run:  # its config names the run
            version = option(args, "--trainer.logger.init_args.version")
            best = root / "runs" / run / version / "checkpoints" / "best.ckpt"
            best.parent.mkdir(parents=True)
            best.touch()
        return 0.0

    return stage


def test_an_encoder_that_kept_its_best_epoch_is_tested_from_it(recorded, monkeypatch, tmp_path):
    """An encoder fit that wrote best.ckpt (a config with a ModelCheckpoint on its validation) hands that file to its
    test and to the control's; one that did not hands its last.ckpt on (the test above)."""
    calls, _ = recorded
    monkeypatch.setattr(pipeline, "run_stage", fit_writing_best(calls, tmp_path, "pendulum_torque_encoder"))
    reproduce.main(["pendulum_torque", "--no-baselines"])
    version = option(calls[0], "--trainer.logger.init_args.version")
    best = f"runs/pendulum_torque_encoder/{version}/checkpoints/best.ckpt"
    handed = [option(a, "--ckpt_path") for a in calls if a[0] == "test" and "--ckpt_path" in a]
    handed += [
        option(a, "--model.init_args.encoder_checkpoint") for a in calls if "--model.init_args.encoder_checkpoint" in a
    ]
    assert handed and set(handed) == {best}


def test_a_baseline_that_kept_its_best_epoch_is_tested_from_it(recorded, monkeypatch, tmp_path):
    """The same for a baseline (validate_held_out and a ModelCheckpoint on val/loss): its test gets best.ckpt."""
    calls, _ = recorded
    monkeypatch.setattr(pipeline, "run_stage", fit_writing_best(calls, tmp_path, "pendulum_lstm"))
    reproduce.main(["pendulum_lstm"])
    fit, test = calls
    version = option(fit, "--trainer.logger.init_args.version")
    assert (fit[0], test[0]) == ("fit", "test")
    assert option(test, "--ckpt_path") == f"runs/pendulum_lstm/{version}/checkpoints/best.ckpt"


def test_a_benchmark_fits_then_tests_from_the_epoch_its_validation_chose(recorded, monkeypatch, tmp_path):
    """``make reproduce EXP=cascaded_tanks``: the fit of configs/benchmarks/cascaded_tanks.yaml, then its protocol
    (cascaded_tanks_test.yaml) on the fit's best.ckpt; ARGS reach both stages."""
    calls, _ = recorded
    monkeypatch.setattr(pipeline, "run_stage", fit_writing_best(calls, tmp_path, "cascaded_tanks"))
    reproduce.main(["cascaded_tanks", "--", "--data.init_args.dir_placement", "here"])
    fit, test = calls
    assert (fit[0], option(fit, "--config")) == ("fit", "configs/benchmarks/cascaded_tanks.yaml")
    assert (test[0], option(test, "--config")) == ("test", "configs/benchmarks/cascaded_tanks_test.yaml")
    version = option(fit, "--trainer.logger.init_args.version")
    assert option(test, "--model.init_args.ssm_checkpoint") == f"runs/cascaded_tanks/{version}/checkpoints/best.ckpt"
    assert option(fit, "--data.init_args.dir_placement") == option(test, "--data.init_args.dir_placement") == "here"
    with pytest.raises(SystemExit, match="is a benchmark"):
        reproduce.main(["cascaded_tanks", "--size", "cpu"])


def test_a_benchmark_with_orders_tests_the_one_its_validation_chose(recorded, monkeypatch, tmp_path):
    """``--orders 2 4 8``: one fit per state_dim, each in its own run folder; the test reads the best.ckpt of the one
    whose kept validation score (its ModelCheckpoint's best_model_score) is lowest, here d = 4."""
    import json

    import torch

    calls, _ = recorded
    val = {"2": 1.5, "4": 0.9, "8": 1.1}

    def stage(args, number, resume_pipeline=None, on_wait=None):
        calls.append(args)
        if args[0] == "fit":
            d = option(args, "--model.init_args.state_dim")
            best = tmp_path / "runs" / "silverbox" / option(args, "--trainer.logger.init_args.version") / "checkpoints"
            best.mkdir(parents=True)
            state = {"monitor": "val/sim_rmse", "best_model_score": torch.tensor(val[d])}
            torch.save({"callbacks": {"ModelCheckpoint{'monitor': 'val/sim_rmse'}": state}}, best / "best.ckpt")
        return 0.0

    monkeypatch.setattr(pipeline, "run_stage", stage)
    reproduce.main(["silverbox", "--orders", "2", "4", "8"])
    fits, (test,) = calls[:3], calls[3:]
    assert [option(a, "--model.init_args.state_dim") for a in fits] == ["2", "4", "8"]
    versions = [option(a, "--trainer.logger.init_args.version") for a in fits]
    assert len(set(versions)) == 3 and versions[1].endswith("-d4")
    assert option(test, "--model.init_args.ssm_checkpoint") == f"runs/silverbox/{versions[1]}/checkpoints/best.ckpt"
    selection = json.loads(option(test, "--model.init_args.selection"))
    assert selection["chosen"] == 4 and selection["state_dim, by val/sim_rmse"] == pytest.approx(val)
    with pytest.raises(SystemExit):
        reproduce.main(["pendulum", "--orders", "2"])


def test_a_benchmark_cross_validated_over_time_tests_the_end_s_fit_and_chooses_by_the_mean(recorded, monkeypatch, tmp_path):  # fmt: skip
    """``--folds 3``: per order, the fit holding out the end (val_fraction 1/3, its own run folder, the one tested)
    and the fits holding out the first and the second third (val_at 0 and 1/3); the order whose three validation
    scores have the lowest mean is chosen, here d = 4 (mean 1.0) although d = 2's end validated better (0.5 against
    0.9; d = 2's mean 1.5). The results file gets every fold's score and the means."""
    import json

    import torch

    calls, _ = recorded
    val = {("2", None): 0.5, ("2", "0.0"): 2.0, ("2", "0.3333333333333333"): 2.0}
    val |= {("4", None): 0.9, ("4", "0.0"): 1.0, ("4", "0.3333333333333333"): 1.1}

    resumes = []

    def stage(args, number, resume_pipeline=None, on_wait=None):
        calls.append(args)
        resumes.append(resume_pipeline)
        if args[0] == "fit":
            at = option(args, "--data.init_args.val_at") if "--data.init_args.val_at" in args else None
            score = val[option(args, "--model.init_args.state_dim"), at]
            best = tmp_path / "runs" / "silverbox" / option(args, "--trainer.logger.init_args.version") / "checkpoints"
            best.mkdir(parents=True)
            state = {"monitor": "val/sim_rmse", "best_model_score": torch.tensor(score)}
            torch.save({"callbacks": {"ModelCheckpoint{'monitor': 'val/sim_rmse'}": state}}, best / "best.ckpt")
        return 0.0

    monkeypatch.setattr(pipeline, "run_stage", stage)
    reproduce.main(["silverbox", "--orders", "2", "4", "--folds", "3"])
    fits, (test,) = calls[:6], calls[6:]
    assert {option(a, "--data.init_args.val_fraction") for a in fits} == {"0.3333333333333333"}
    held = [option(a, "--data.init_args.val_at") if "--data.init_args.val_at" in a else "end" for a in fits]
    assert held == ["end", "0.0", "0.3333333333333333"] * 2
    versions = [option(a, "--trainer.logger.init_args.version") for a in fits]
    assert len(set(versions)) == 6 and versions[3].endswith("-d4") and versions[4] == versions[3] + "-fold0"
    assert option(test, "--model.init_args.ssm_checkpoint") == f"runs/silverbox/{versions[3]}/checkpoints/best.ckpt"
    selection = json.loads(option(test, "--model.init_args.selection"))
    assert selection["chosen"] == 4 and selection["folds"] == 3
    by_fold = selection["val/sim_rmse by fold (the held-out end first)"]
    assert by_fold["2"] == pytest.approx([0.5, 2.0, 2.0]) and by_fold["4"] == pytest.approx([0.9, 1.0, 1.1])
    assert selection["cross-validated (mean over the folds)"] == pytest.approx({"2": 1.5, "4": 1.0})

    calls.clear()  # one order: its folds scored, nothing chosen, the end's fit tested; the record names the folds
    reproduce.main(["silverbox", "--folds", "2", "--", "--model.init_args.state_dim", "2"])
    (end, first), (test,) = calls[:2], calls[2:]
    assert "--data.init_args.val_at" not in end and option(first, "--data.init_args.val_at") == "0.0"
    assert option(test, "--model.init_args.ssm_checkpoint").endswith(option(end, "--trainer.logger.init_args.version") + "/checkpoints/best.ckpt")  # fmt: skip
    assert "chosen" not in json.loads(option(test, "--model.init_args.selection"))
    version = option(end, "--trainer.logger.init_args.version")
    record = json.loads((tmp_path / "runs" / "silverbox" / version / "reproduce.json").read_text())
    assert record["command"].startswith("make reproduce EXP=silverbox FOLDS=2 ARGS=")
    # the command that finishes it gives --resume to reproduce, not to the stages after the --
    resume = resumes[-1]
    assert resume.endswith(f"--folds 2 --resume {version} -- --model.init_args.state_dim 2"), resume
    for wrong in (["pendulum", "--folds", "3"], ["silverbox", "--folds", "1"]):
        with pytest.raises(SystemExit):
            reproduce.main(wrong)
