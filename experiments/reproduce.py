"""One command per experiment: SSM fit -> the tests that need the SSM alone (UKF test, states fitted by optimisation,
control test with the UKF, where their configs exist) -> encoder fit -> test (-> the control again, the encoder
estimating the state), then every baseline of the experiment (fit -> test); or one baseline alone. The SSM's own tests
come first: they train nothing (seconds to minutes), and their rows land even where a long encoder stage then stops or
fails.

    python -m experiments.reproduce pendulum            # the stages configs/experiments.yaml names for pendulum
    python -m experiments.reproduce pendulum --size cpu # the CPU-sized twins under configs/cpu/
    python -m experiments.reproduce pendulum_lstm       # configs/baselines/pendulum_lstm.yaml alone
    python -m experiments.reproduce pendulum --no-baselines
    python -m experiments.reproduce lorenz_T1000 --no-encoder --no-baselines   # the SSM and its UKF test only
    python -m experiments.reproduce pendulum --encoder-epochs 120   # the encoder stage on a stated epoch budget
    python -m experiments.reproduce pendulum_lstm --baseline-epochs 120   # a baseline on a stated epoch budget
    python -m experiments.reproduce lorenz_T1000 --size cpu --seed 1  # another seed: results/lorenz_T1000_cpu_seed1.md
    python -m experiments.reproduce pendulum -- --trainer.max_epochs 1   # options after -- go to every stage's cli.py
    python -m experiments.reproduce silverbox -- --data.init_args.dir_placement ../shared/data/nonlinear_benchmarks
                                                   # a benchmark: configs/benchmarks/silverbox{,_test}.yaml

(``make reproduce EXP=pendulum [SIZE=cpu] [SEED=1] [ARGS="..."]``.) Options after ``--`` (make's ``ARGS``) are
appended to every stage's ``python cli.py`` command, after the stage's own: a smoke test of the whole pipeline
(``-- --trainer.max_epochs 1 --trainer.limit_train_batches 2``), or another data directory; they are part of the
recorded commands, and a resumed run must be given the same. ``--seed N`` runs every stage with ``--seed_everything N``:
the networks' and shooting nodes' initial values change; the data and their order do not (they follow the data
section's own ``seed``). Its results go to ``results/<experiment>_seed<N>.md``; ``python -m experiments.seeds
<experiment>`` gathers the seeds' scores as mean and std.

Each stage is ``python cli.py ...`` in its own process, logged under ``runs/<name>/reproduce-<stamp>/``, so the
checkpoints each stage hands to the next are known: an SSM's ``last.ckpt``; an encoder's or a baseline's
``best.ckpt`` where its config keeps its best epoch (:func:`tested_checkpoint`), else its ``last.ckpt``. Every
method lands in the same ``results/<experiment>.md``, which ends with the commands and their durations.

Ctrl-C (or ``kill <pid>``, SIGTERM or SIGINT) during a stage stops the stage as ``fit`` stops (its last completed epoch
kept); this process waits for it, prints which stage was interrupted, the command that resumes that stage alone
(``--ckpt_path`` its ``last.ckpt``) and the one that resumes the whole pipeline, and exits with status 130. A failing
stage ends in one ``error:`` line naming it, with the stage's status. No traceback either way; the later stages do
not run. See :func:`run_stage`.

    python -m experiments.reproduce pendulum --resume reproduce-20261125-040251   # finish that run (make: RESUME=...)

``--resume VERSION`` finishes a run that stopped, whatever stopped it (Ctrl-C, ``kill``, a crash, the machine going
away while ``runs/`` stays): the stages it finished are not run again, its interrupted ``fit`` continues from its
last completed epoch, then the remaining stages and the results file run as usual. Each run keeps its record in
``<first stage's run folder>/reproduce.json`` (see :class:`Pipeline`). The epoch budgets may be raised on resume
(``--resume VERSION --encoder-epochs 330``): that fit continues to the new count and the stages depending on it run
again. ``--no-encoder`` may be given or dropped on resume: dropped, a run that ended without its encoder gains the
encoder's stages (the finished ones are not run again); given, a run whose encoder stage cannot finish on this machine
ends with the SSM's own tests and its results file (the encoder's ``last.ckpt`` kept for a resume without it).
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import os
import shlex
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path

from omegaconf import OmegaConf

from experiments.registry import LISTED, REGISTRY, read_registry
from experiments.results import write_pipeline
from ssm_ms.runtime.machine import describe

ROOT = Path(__file__).resolve().parents[1]
WAIT_TICK = 30.0  # seconds between the records of a running stage's time (Pipeline)


BUDGETS = ("encoder_epochs", "baseline_epochs")  # options a resumed run may raise: its fits continue to the new count
# options a resumed run may give or drop: dropping --no-encoder adds the encoder's stages to a finished run, giving it
# ends a run whose encoder cannot finish (its last.ckpt kept, for a resume without it)
STAGE_CHOICES = ("no_encoder",)


def known_experiments(registry: dict, size: str) -> list[str]:
    """Every name ``make reproduce EXP=...`` takes at ``size``: experiments, baselines alone, suites, benchmarks."""
    experiments = registry.get("experiments", {})
    known = [name for name, sizes in experiments.items() if size in sizes]
    known += [Path(p).stem for sizes in experiments.values() for p in sizes.get(size, {}).get("baselines", [])]
    return sorted({*known, *registry.get("suites", {}), *registry.get("benchmarks", {})})


def load_config(config: Path | str) -> dict:
    """The config file ``config`` as ``python cli.py`` composes it (:func:`ssm_ms.cli.config_parser`: its includes,
    section files, dotted keys and interpolations, the defaults it leaves out filled in), as a dict.

    Read, not checked: a required value that a stage receives on the command line (an encoder's
    ``ssm_checkpoint``) may be missing. A file that is not a whole config (a data config: ``class_path`` and
    ``init_args``) is its YAML as written."""
    path = Path(config)
    raw = OmegaConf.to_container(OmegaConf.load(path), resolve=False) or {}
    if not isinstance(raw, dict):
        raise ValueError(f"{path} is not a config (a YAML mapping of options)")
    if "class_path" in raw:  # a section file of its own (configs/data/*.yaml)
        return raw
    from ssm_ms.cli import CommandLineError, config_parser

    # jsonargparse parses in the config's folder: the working directory's place on sys.path ("" under python -c)
    # must name the folder the process started in, for the classes the config names
    saved = list(sys.path)
    sys.path[:] = [p or os.getcwd() for p in sys.path]
    try:  # jsonargparse's parse without its check of required values (the stage's checkpoint comes with the command)
        parsed = config_parser().parse_args(["--config", str(path)], _skip_validation=True).as_dict()
    except CommandLineError as e:
        raise ValueError(f"{path}: {e.message}") from None
    finally:
        sys.path[:] = saved
    return _values(parsed)


def _values(node):
    """A parsed config less jsonargparse's records of the files read (``config``, ``__path__``)."""
    if isinstance(node, dict):
        return {k: _values(v) for k, v in node.items() if k not in ("config", "__path__")}
    if isinstance(node, list):
        return [_values(v) for v in node]
    return node


def build_datamodule(config: dict | Path | str, **overrides):
    """The data module a config describes, as ``cli.py`` would build it, with ``overrides`` on its ``init_args``.

    ``config``: a config file or its :func:`load_config` dict; a whole config (its ``data`` section) or a data config
    (``configs/data/*.yaml``: ``class_path`` and ``init_args``). A file that describes no data module, or arguments
    its class refuses, raise ValueError with one line naming the file."""
    name = config if isinstance(config, (str, Path)) else "the config"
    spec = load_config(config) if isinstance(config, (str, Path)) else config
    spec = spec.get("data", spec)
    path = spec.get("class_path") if isinstance(spec, dict) else None
    if not isinstance(path, str) or "." not in path:
        raise ValueError(f"{name} describes no data module (a class_path and init_args, or a data section of them)")
    module, attr = path.rsplit(".", 1)
    try:
        cls = getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as e:
        raise ValueError(f"{name}: no data module {path} ({e})") from e
    try:
        return cls(**{**(spec.get("init_args") or {}), **overrides})
    except TypeError as e:  # an argument the class does not take
        raise ValueError(f"{name}: {path} refuses its arguments ({e})") from e


def config_value(config: Path | str, key: str, default=None):
    """The dotted ``key`` (``trainer.logger.init_args.name``) of the composed ``config``, else ``default``."""
    value = load_config(config)
    for part in key.split("."):
        if not isinstance(value, dict) or part not in value:
            return default
        value = value[part]
    return value


def logger_dir(config: Path) -> Path:
    """``save_dir/name`` of the TensorBoard logger a config declares."""
    args = config_value(config, "trainer.logger.init_args")
    if not isinstance(args, dict) or "save_dir" not in args or "name" not in args:
        raise ValueError(f"{config} declares no TensorBoardLogger with save_dir and name: reproduce needs them")
    return Path(str(args["save_dir"])) / str(args["name"])


def results_dir(config: Path, version: str) -> Path:
    """The folder a test stage of ``config`` writes its results file to: its ``results_dir``, or where it names none,
    the stage's own run folder (``save_dir/name/version`` of its logger), as the library does."""
    value = config_value(config, "model.init_args.results_dir")
    return _absolute(Path(str(value)) if value is not None else logger_dir(config) / version)


def experiment_name(config: Path) -> str:
    return str(config_value(config, "model.init_args.experiment", default=config.stem))


def _stage_checkpoint(args: list[str]) -> Path | None:
    """The ``last.ckpt`` a ``fit`` stage writes (its config's logger folder, this run's version), if it exists."""
    if not args or args[0] != "fit" or "--config" not in args or "--trainer.logger.init_args.version" not in args:
        return None
    try:
        config = ROOT / args[args.index("--config") + 1]  # relative to the root, where the stage runs
        version = args[args.index("--trainer.logger.init_args.version") + 1]
        ckpt = logger_dir(config) / version / "checkpoints" / "last.ckpt"
    except (IndexError, ValueError, OSError):
        return None
    return ckpt if _absolute(ckpt).is_file() else None


def _without_option(args: list[str], name: str) -> list[str]:
    """``args`` less ``name VALUE`` (and ``name=VALUE``)."""
    out, skip = [], False
    for arg in args:
        if skip:
            skip = False
        elif arg == name:
            skip = True
        elif not arg.startswith(name + "="):
            out.append(arg)
    return out


def tested_checkpoint(checkpoints: Path) -> Path:
    """The checkpoint a trained stage (an encoder, a baseline) is tested from: ``best.ckpt`` where its config keeps
    its best epoch (a ``ModelCheckpoint`` writing it: docs/cli.md, "The best epoch"), else ``last.ckpt``."""
    best = checkpoints / "best.ckpt"
    return best if _absolute(best).is_file() else checkpoints / "last.ckpt"


def _absolute(path: Path) -> Path:
    return path if path.is_absolute() else ROOT / path


def run_stage(
    args: list[str], number: int, resume_pipeline: str | None = None, on_wait: Callable[[], None] | None = None
) -> float:
    """Run ``python cli.py *args`` from the root (stage ``number`` of the pipeline); return its duration in seconds.
    ``on_wait`` is called every :data:`WAIT_TICK` seconds while the stage runs and once when it has ended, however
    it ended (before the messages below).

    Ctrl-C reaches the stage and this process together (one process group); a SIGTERM or SIGINT sent to this process
    alone (``kill <pid>``, what scripts and job schedulers send, or ``kill -INT <pid>``) reaches the stage as SIGTERM.
    Either way the stage stops as ``fit`` does (keeping its last completed epoch), this process waits
    for it, then says which stage was interrupted, the command that resumes that stage alone (``--ckpt_path`` its
    ``last.ckpt`` for a ``fit`` that saved one, else the stage's own command) and ``resume_pipeline`` (the
    reproduce command that resumes it and runs the stages after it), and exits with status 130; a second Ctrl-C
    stops the stage at once. A stage that fails exits with its status after one ``error:`` line naming it (its
    own message is printed above); one killed by a signal from elsewhere (SIGKILL: most often the out-of-memory
    killer) has no message of its own: the line names the signal and the checkpoint kept, and this process exits
    with 128 + its number, as a shell does. Either way no traceback: the later stages and the results file do not
    run."""
    cmd = [sys.executable, "cli.py", *args]
    print("\n>>> " + " ".join(cmd), flush=True)
    start = time.time()
    interrupted = False
    proc: subprocess.Popen | None = None

    def stop(signum, frame):
        # Ctrl-C reached the stage too, `kill [-INT] <this pid>` this process alone: which one is not known here, and
        # SIGTERM stops the stage the same way in both cases (one already stopping on its Ctrl-C only notes it:
        # Lightning's handler sets a flag while it trains). A second SIGINT does not wait for a clean stop.
        nonlocal interrupted
        if proc is not None and interrupted and signum == signal.SIGINT:
            proc.kill()
        elif proc is not None:
            proc.send_signal(signal.SIGTERM)
        interrupted = True

    # Handlers, not KeyboardInterrupt: a process started in the background by a non-interactive shell inherits
    # SIGINT ignored, and Python then never raises KeyboardInterrupt. Installed before the stage starts, so that
    # the stage starts with SIGINT's default disposition (a handler is reset by exec, an ignored signal is not).
    previous = {sig: signal.signal(sig, stop) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        proc = subprocess.Popen(cmd, cwd=ROOT)
        if interrupted:  # stopped while the stage was starting
            proc.send_signal(signal.SIGTERM)
        while True:
            try:
                code = proc.wait(timeout=WAIT_TICK)
                break
            except subprocess.TimeoutExpired:
                if on_wait is not None:
                    on_wait()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if on_wait is not None:
        on_wait()
    stage = f"stage {number} (python cli.py {shlex.join(args)})"
    later = (
        f"Resume the whole pipeline (this stage, then the stages after it and the results file) with:\n"
        f"  {resume_pipeline}"
        if resume_pipeline
        else "(the stages after it and the results file did not run: run them after it, or reproduce again)"
    )
    if interrupted or code in (130, -signal.SIGINT):
        ckpt = _stage_checkpoint(args)
        alone = _without_option(args, "--ckpt_path") if ckpt else args
        resume = shlex.join(["python", "cli.py", *alone, *(["--ckpt_path", str(ckpt)] if ckpt else [])])
        saved = f"; its last completed epoch is saved in {ckpt}" if ckpt else ""
        print(
            f"\nreproduce was interrupted during {stage}{saved}. Resume that stage with:\n  {resume}\n{later}",
            file=sys.stderr,
        )
        raise SystemExit(130)
    if code > 0:
        print(
            f"error: reproduce stopped: {stage} failed with status {code} (its message is above); the "
            f"stages after it and the results file did not run. {later}",
            file=sys.stderr,
        )
        raise SystemExit(code)
    if code < 0:  # killed by a signal, with no message of its own: say which, and what is kept
        killer = signal.Signals(-code).name
        if -code == signal.SIGKILL:
            killer += " (on Linux most often the kernel's out-of-memory killer: `dmesg` or the system log names it)"
        ckpt = _stage_checkpoint(args)
        saved = f"; its last completed epoch is kept in {ckpt}" if ckpt else ""
        print(
            f"error: reproduce stopped: {stage} was killed by {killer}{saved}; the stages after it and the "
            f"results file did not run. {later}",
            file=sys.stderr,
        )
        raise SystemExit(128 - code)  # the shell's status for a process killed by that signal
    return round(time.time() - start, 1)


class Pipeline:
    """The stages of one reproduce command, recorded in ``record`` (a JSON file in the first stage's run folder) as
    they start and finish, so that the same command with ``--resume <version>`` runs only what is left.

    Resumed, a stage recorded as finished is not run again (its recorded duration is kept); a ``fit`` stage that
    has a ``last.ckpt`` continues from it (``--ckpt_path``); every other stage runs as new. A stage's seconds add,
    over the runs it took, the time up to its last completed epoch's checkpoint (the work kept), so a resumed
    stage's duration is the training it holds, not the work lost in the interrupted epoch. That time is measured
    while the stage runs, on its machine (the checkpoint's modification time against the run's start, recorded
    every :data:`WAIT_TICK` seconds), so that a record and checkpoint copied to another machine (their times then
    the copy's) or a machine lost mid-run keep it."""

    def __init__(self, record: Path, options: dict, resume_pipeline: str, resume: bool, command: str | None = None):
        self.record, self.options, self.resume_pipeline = record, options, resume_pipeline
        self.command = command  # the results file's record of this run is keyed by it
        # the command under which the results file holds this run's record (the last one that finished it; None
        # before it first finishes): a budget raised on resume replaces that record, however often it is resumed
        self.recorded_command: str | None = None
        self.done: list[dict] = []
        self.running: dict | None = None
        if resume:
            if not record.is_file():
                raise SystemExit(
                    f"error: --resume: {record.parent.name} has no record of a reproduce run "
                    f"({record} does not exist): give the version printed when it stopped "
                    "(reproduce-<date>-<time>), with the experiment and options it was started with"
                )
            try:
                saved = json.loads(record.read_text())
                done, running, started_with = saved["stages"], saved.get("running"), saved["options"]
            except (ValueError, KeyError, TypeError):
                raise SystemExit(
                    f"error: --resume: {record} is not a reproduce record (unreadable): reproduce "
                    "again without --resume"
                ) from None
            differ = [
                f"{k.replace('_', '-')}: {started_with.get(k)} then, {v} now"
                for k, v in options.items()
                if started_with.get(k) != v and k not in BUDGETS + STAGE_CHOICES
            ]
            if differ:
                raise SystemExit(
                    f"error: --resume: {record.parent.name} was started with other options ("
                    f"{'; '.join(differ)}): resume it with the experiment and options it was started with"
                )
            lowered = [
                f"--{k.replace('_', '-')} {options[k]} (it was run with {started_with[k]})"
                for k in BUDGETS
                if isinstance(options.get(k), int)
                and isinstance(started_with.get(k), int)
                and options[k] < started_with[k]
            ]
            if lowered:
                raise SystemExit(
                    f"error: --resume: {record.parent.name} cannot be cut back to {'; '.join(lowered)}: "
                    "its checkpoints are past that; give the same budget or a larger one"
                )
            self.done, self.running = done, running
            # (a record written before "recorded" was kept: the command it was last run with)
            self.recorded_command = saved.get("recorded", saved.get("command"))
        self.stages: list[dict] = []

    def _write(self) -> None:
        self.record.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.record.with_suffix(".tmp")
        tmp.write_text(
            json.dumps(
                {
                    "options": self.options,
                    "command": self.command,
                    "recorded": self.recorded_command,
                    "stages": self.stages + [s for s in self.done if s not in self.stages],
                    "running": self.running,
                },
                indent=2,
            )
            + "\n"
        )
        tmp.replace(self.record)

    def finished(self, files: list[tuple[Path, str]]) -> list[Path]:
        """Record the finished run in each ``(results_dir, experiment)`` results file its stages wrote, in place of the
        record of the command it was last finished with (a budget raised on resume), and note that command; return
        the results tables' paths."""
        replaces = self.recorded_command if self.recorded_command != self.command else None
        pipeline = {
            "stages": self.stages,
            "total_seconds": round(sum(s["seconds"] for s in self.stages), 1),
            "machine": describe(),
            "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "command": self.command,
        }
        written = [write_pipeline(d, e, self.command, replaces=replaces, pipeline=pipeline) for d, e in files]
        self.recorded_command = self.command
        self._write()
        return written

    def stage(self, args: list[str], again: bool = False) -> bool:
        """Run ``python cli.py *args`` unless the resumed run finished it (``again``: run it all the same, an
        earlier stage it depends on ran again); record it. Return whether it ran.

        A ``fit`` the resumed run finished with another ``--trainer.max_epochs`` (a budget raised on resume)
        continues from its ``last.ckpt`` to the new count, its seconds added to the earlier ones."""
        command = "python cli.py " + " ".join(args)
        number = len(self.stages) + 1
        finished = next((s for s in self.done if s["command"] == command), None)
        if finished is not None and not again:
            print(f"\n>>> stage {number} finished in the run resumed ({finished['seconds']} s): {command}", flush=True)
            self.stages.append(finished)
            return False
        kept, runs = 0.0, 1
        ckpt = _stage_checkpoint(args)

        def same_fit(recorded: str) -> bool:  # this fit, whatever its epoch budget (commands are " "-joined)
            unbudgeted = _without_option(recorded.split(" ")[2:], "--trainer.max_epochs")
            return args[0] == "fit" and ckpt is not None and unbudgeted == _without_option(args, "--trainer.max_epochs")

        earlier = (
            self.running
            if self.running is not None and (self.running["command"] == command or same_fit(self.running["command"]))
            else None
        )
        extended = next((s for s in self.done if s["command"] != command and same_fit(s["command"])), None)
        if finished is not None:  # run again from scratch (a test after its checkpoint changed)
            self.done.remove(finished)
        elif extended is not None:
            print(
                f"\n>>> stage {number} finished in the run resumed with another epoch budget; continued: {command}",
                flush=True,
            )
            self.done.remove(extended)
            runs, kept = extended.get("runs", 1) + 1, extended["seconds"]
        elif earlier is not None:
            runs, kept = earlier["runs"] + 1, earlier["seconds"]
        started = time.time()
        self.running = {"command": command, "seconds": kept, "runs": runs}
        self._write()

        def account() -> None:  # the time up to this run's last checkpoint, while its modification time is ours
            saved = _stage_checkpoint(args)
            mtime = _absolute(saved).stat().st_mtime if saved is not None else 0.0
            if self.running is not None and mtime >= started:
                self.running["seconds"] = round(kept + mtime - started, 1)
                self._write()

        seconds = run_stage(
            args + (["--ckpt_path", str(ckpt)] if ckpt else []), number, self.resume_pipeline, on_wait=account
        )
        entry = {"command": command, "seconds": round(kept + seconds, 1)}
        if runs > 1:
            entry["runs"] = runs
        self.stages.append(entry)
        self.running = None
        self._write()
        return True


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("experiment", help="e.g. pendulum, quad, lorenz_T1000, or a baseline: pendulum_lstm")
    parser.add_argument("--size", choices=["paper", "cpu"], default="paper")
    parser.add_argument("--no-baselines", action="store_true", help="only the SSM and its inference stages")
    parser.add_argument(
        "--no-encoder",
        action="store_true",
        help="no encoder stage, nor the stages that need it: the SSM and the tests of the SSM alone (UKF, states "
        "fitted by optimisation, control with the UKF); for experiments whose encoder does not fit the machine "
        "(may be given or dropped on resume)",
    )
    parser.add_argument(
        "--encoder-epochs",
        type=int,
        default=None,
        metavar="N",
        help="train the encoder stage for N epochs instead of its config's max_epochs (a budget for "
        "machines where the paper's count does not fit; the results file lists the command)",
    )
    parser.add_argument(
        "--baseline-epochs",
        type=int,
        default=None,
        metavar="N",
        help="train each baseline (LSTM, RKN) for N epochs instead of its config's max_epochs (the "
        "same kind of budget)",
    )
    parser.add_argument(
        "--seed",
        type=int,
        default=None,
        metavar="N",
        help="every stage with --seed_everything N instead of the configs' seed; results go to "
        "results/<experiment>_seed<N>.md",
    )
    parser.add_argument(
        "--orders",
        type=int,
        nargs="+",
        default=None,
        metavar="D",
        help="a benchmark: one fit per latent dimension D (state_dim, the same budget each); the one whose validation "
        "on the held-out end of the training recording (val/sim_rmse) is lowest is tested",
    )
    parser.add_argument(
        "--resume",
        default=None,
        metavar="VERSION",
        help="finish the run of this version (reproduce-<date>-<time>, printed when it stopped; the "
        "same experiment and options; the epoch budgets may be raised): its finished stages are not run "
        "again, its interrupted fit, or a fit whose budget was raised, continues from its last.ckpt",
    )
    argv = list(sys.argv[1:] if argv is None else argv)
    stage_args = argv[argv.index("--") + 1 :] if "--" in argv else []
    own = argv[: argv.index("--")] if "--" in argv else argv
    opts = parser.parse_args(own)
    opts.stage_args = stage_args
    for name in ("encoder_epochs", "baseline_epochs"):
        if getattr(opts, name) is not None and getattr(opts, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(opts, name)}")
    if opts.seed is not None and opts.seed < 0:
        parser.error(f"--seed must be >= 0, got {opts.seed}")
    registry = read_registry()
    if opts.orders is not None and opts.experiment not in registry.get("benchmarks", {}):
        parser.error("--orders chooses a benchmark's latent dimension (configs/benchmarks/): not for this experiment")
    if opts.no_encoder and opts.encoder_epochs is not None:
        parser.error("--encoder-epochs budgets the encoder stage that --no-encoder leaves out: give one of the two")
    suite = registry.get("suites", {}).get(opts.experiment)
    if suite is not None:  # several experiments into one results file, one after the other
        if opts.resume:
            parser.error(f"{opts.experiment} is a suite of experiments: resume each with its own reproduce command")
        if opts.no_encoder:  # a suite's experiments may train on what an earlier one's encoder-driven control records
            parser.error(
                f"--no-encoder: {opts.experiment} is a suite of experiments: give it to one experiment at a time"
            )
        for experiment in suite:
            main([experiment, *argv[1:]])
        return
    benchmark = registry.get("benchmarks", {}).get(opts.experiment)
    if benchmark is not None:
        run_benchmark(opts, argv, ROOT / benchmark["fit"], ROOT / benchmark["test"])
        return
    stages = {
        kind: [ROOT / p for p in paths] if kind in LISTED else ROOT / paths
        for kind, paths in registry.get("experiments", {}).get(opts.experiment, {}).get(opts.size, {}).items()
    }
    ssm_cfg, enc_cfg, record_cfg = (stages.get(k) for k in ("ssm", "encoder", "record"))
    controls = stages.get("control", [])
    alone = [
        ROOT / path
        for experiment in registry.get("experiments", {}).values()
        for path in experiment.get(opts.size, {}).get("baselines", [])
        if Path(path).stem == opts.experiment
    ]
    if alone:
        baselines, ssm_stages = alone[:1], False
    elif ssm_cfg is not None:
        baselines = [] if opts.no_baselines else stages.get("baselines", [])
        ssm_stages = True
    elif controls:  # a controller without a learned model (the true one): its tests alone
        baselines, ssm_stages = [], False
    else:
        raise SystemExit(
            f"no {opts.size}-size experiment {opts.experiment!r} in {REGISTRY.relative_to(ROOT)}: choose among "
            f"{known_experiments(registry, opts.size)}"
        )
    ssm_tests = [stages[k] for k in ("ukf", "optimise") if k in stages] + controls  # of the SSM, nothing to train
    if opts.no_encoder and ssm_stages and not ssm_tests:
        parser.error(
            f"--no-encoder: {opts.experiment} has no test of its SSM alone (no ukf, optimise or control stage in "
            f"{REGISTRY.relative_to(ROOT)}): without its encoder nothing would score it; drop --no-encoder"
        )
    use_encoder = enc_cfg is not None and not opts.no_encoder
    seeded = "" if opts.seed is None else f"seed{opts.seed}"
    version = opts.resume or "reproduce-" + (seeded + "-" if seeded else "") + datetime.now().strftime("%Y%m%d-%H%M%S")
    if "/" in version or not version.startswith("reproduce-"):
        parser.error(f"--resume takes the version folder's name (reproduce-<date>-<time>), got {version!r}")
    options = _without_option(argv, "--resume")
    first = ssm_cfg if ssm_stages else baselines[0] if baselines else controls[0]
    # options make does not pass: the module's command
    if opts.no_baselines or opts.no_encoder or opts.encoder_epochs is not None or opts.baseline_epochs is not None:
        command = shlex.join(["python", "-m", "experiments.reproduce", *options])
    else:
        command = (
            f"make reproduce EXP={opts.experiment}"
            + (" SIZE=cpu" if opts.size == "cpu" else "")
            + (f" SEED={opts.seed}" if seeded else "")
            + (f" ARGS={shlex.quote(shlex.join(stage_args))}" if stage_args else "")
        )
    pipeline = open_pipeline(opts, options, first, version, command)
    v = ["--trainer.logger.init_args.version", version]
    if seeded:
        v += ["--seed_everything", str(opts.seed)]
    v += stage_args  # after the stage's own options: they win

    def named(cfg: Path) -> list[str]:
        """A forecaster stage's results under the seed's own experiment name."""
        return ["--model.init_args.experiment", f"{experiment_name(cfg)}_{seeded}"] if seeded else []

    configs = []
    if ssm_stages:
        ssm_ckpt = logger_dir(ssm_cfg) / version / "checkpoints" / "last.ckpt"
        ssm_ran = pipeline.stage(["fit", "--config", str(ssm_cfg.relative_to(ROOT)), *v])
        with_ssm = ["--model.init_args.ssm_checkpoint", str(ssm_ckpt)]
        for stage_cfg in ssm_tests:  # seconds each: before a long encoder fit, which may stop or fail
            pipeline.stage(
                ["test", "--config", str(stage_cfg.relative_to(ROOT)), *with_ssm, *named(stage_cfg), *v],
                again=ssm_ran,
            )
        if use_encoder:
            enc_dir = logger_dir(enc_cfg) / version / "checkpoints"
            budget = [] if opts.encoder_epochs is None else ["--trainer.max_epochs", str(opts.encoder_epochs)]
            enc_ran = pipeline.stage(
                ["fit", "--config", str(enc_cfg.relative_to(ROOT)), *with_ssm, *budget, *named(enc_cfg), *v],
                again=ssm_ran,
            )
            enc_ckpt = tested_checkpoint(enc_dir)
            enc_test = ["test", "--config", str(enc_cfg.relative_to(ROOT)), *with_ssm, "--ckpt_path", str(enc_ckpt)]
            pipeline.stage([*enc_test, *named(enc_cfg), *v], again=ssm_ran or enc_ran)
            configs.append(enc_cfg)
        configs += ssm_tests  # the results files listed in the order they always were: encoder first
        if use_encoder:
            with_encoder = ["--model.init_args.encoder_checkpoint", str(enc_ckpt)]
            for control_cfg in controls:  # the control again, the encoder estimating the state
                test = ["test", "--config", str(control_cfg.relative_to(ROOT)), *with_ssm, *with_encoder]
                pipeline.stage([*test, *named(control_cfg), *v], again=ssm_ran or enc_ran)
            if controls and record_cfg is not None:  # the learned controller's episodes: a later experiment's data
                record = ["test", "--config", str(record_cfg.relative_to(ROOT)), *with_ssm, *with_encoder]
                pipeline.stage([*record, *v], again=ssm_ran or enc_ran)
    elif controls and not baselines:
        for control_cfg in controls:
            pipeline.stage(["test", "--config", str(control_cfg.relative_to(ROOT)), *named(control_cfg), *v])
        configs += controls
    baseline_budget = [] if opts.baseline_epochs is None else ["--trainer.max_epochs", str(opts.baseline_epochs)]
    for cfg in baselines:
        fit_ran = pipeline.stage(["fit", "--config", str(cfg.relative_to(ROOT)), *baseline_budget, *named(cfg), *v])
        ckpt = tested_checkpoint(logger_dir(cfg) / version / "checkpoints")
        pipeline.stage(
            ["test", "--config", str(cfg.relative_to(ROOT)), "--ckpt_path", str(ckpt), *named(cfg), *v], again=fit_ran
        )
        configs.append(cfg)
    files = []  # every results file the stages wrote (an SSM's stages may write to several, e.g. control)
    for cfg in configs:
        entry = (
            results_dir(cfg, version),
            experiment_name(cfg) + (f"_{seeded}" if seeded else ""),
        )
        if entry not in files:
            files.append(entry)
    for md in pipeline.finished(files):
        print(f"\nresults: {md.relative_to(ROOT)}\n")
        print(md.read_text())


def validation_score(checkpoint: Path) -> float:
    """The score a fit's ``ModelCheckpoint`` kept its best epoch by (``val/sim_rmse``), read from that checkpoint;
    infinite where there is none (a fit without that validation)."""
    path = _absolute(checkpoint)
    if not path.is_file():
        return math.inf
    import torch  # the stage is done: reading its checkpoint costs the import once

    from ssm_ms.checkpointing import kept_score

    score = kept_score(torch.load(path, map_location="cpu", weights_only=False), path)
    return math.inf if score is None else score


def open_pipeline(opts: argparse.Namespace, options: list[str], first: Path, version: str, command: str) -> Pipeline:
    """The record of this run (in the first stage's run folder), saying how to finish it if it stops."""
    pipeline = Pipeline(
        _absolute(logger_dir(first)) / version / "reproduce.json",
        {k: v for k, v in vars(opts).items() if k != "resume"},
        shlex.join(["python", "-m", "experiments.reproduce", *options, "--resume", version]),
        resume=opts.resume is not None,
        command=command,
    )
    print(f"reproduce run {version}; if it stops, finish it with:\n  {pipeline.resume_pipeline}", flush=True)
    return pipeline


def run_benchmark(opts: argparse.Namespace, argv: list[str], config: Path, test_cfg: Path) -> None:
    """An identification benchmark (``configs/benchmarks/<experiment>.yaml``): the SSM's fit, then the benchmark's
    protocol on the test recordings (``test_cfg``) from the epoch its validation chose (``best.ckpt``);
    its results file is the test's (``results/benchmarks/<experiment>.md``, the commands and durations in this run's
    record)."""
    if opts.size != "paper" or opts.no_encoder or opts.encoder_epochs or opts.baseline_epochs:
        raise SystemExit(f"error: {opts.experiment} is a benchmark: one size, no encoder or baselines to choose")
    seeded = "" if opts.seed is None else f"seed{opts.seed}"
    version = opts.resume or "reproduce-" + (seeded + "-" if seeded else "") + datetime.now().strftime("%Y%m%d-%H%M%S")
    options = _without_option(argv, "--resume")
    command = f"make reproduce EXP={opts.experiment}" + (f" SEED={opts.seed}" if seeded else "")
    command += f" ARGS={shlex.quote(shlex.join(opts.stage_args))}" if opts.stage_args else ""
    pipeline = open_pipeline(opts, options, config, version, command)
    seed = ["--seed_everything", str(opts.seed)] if seeded else []
    fits = {}  # the run folder of each fit: one, or one per order
    for d in opts.orders or [None]:
        run = version if d is None else f"{version}-d{d}"
        order = [] if d is None else ["--model.init_args.state_dim", str(d)]
        v = ["--trainer.logger.init_args.version", run, *seed, *order, *opts.stage_args]
        fits[d] = (pipeline.stage(["fit", "--config", str(config.relative_to(ROOT)), *v]), run)
    chosen, scores = None, {}
    if opts.orders:  # the order whose kept epoch validated best
        kept = {d: tested_checkpoint(logger_dir(config) / run / "checkpoints") for d, (_, run) in fits.items()}
        scores = {d: validation_score(path) for d, path in kept.items()}
        chosen = min(scores, key=lambda d: scores[d])
    ran, run = fits[chosen]
    ssm = tested_checkpoint(logger_dir(config) / run / "checkpoints")
    named = []  # the results file keys the row by method and the seed the fit recorded
    if opts.orders:
        chosen_by = {"state_dim, by val/sim_rmse": {str(d): scores[d] for d in scores}, "chosen": chosen}
        named += ["--model.init_args.selection", json.dumps(chosen_by)]
    test = ["test", "--config", str(test_cfg.relative_to(ROOT)), "--model.init_args.ssm_checkpoint", str(ssm)]
    pipeline.stage([*test, *named, *opts.stage_args], again=any(r for r, _ in fits.values()))
    md = results_dir(test_cfg, version) / f"{experiment_name(test_cfg)}.md"
    if md.is_file():
        print(f"\nresults: {md.relative_to(ROOT)}\n\n{md.read_text()}")


if __name__ == "__main__":
    main()
