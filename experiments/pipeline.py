"""The stages of one ``make reproduce`` run: each ``python cli.py ...`` in a process of its own
(:func:`run_stage`: Ctrl-C and signals stop it as ``fit`` stops, a failure ends in one line), recorded as they
start and finish so that ``--resume`` runs only what is left (:class:`Pipeline`)."""

from __future__ import annotations

import json
import shlex
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path

from experiments import configs
from experiments.configs import ROOT, logger_dir
from experiments.results import write_pipeline
from ssm_ms.runtime.machine import describe

WAIT_TICK = 30.0  # seconds between the records of a running stage's time (Pipeline)

BUDGETS = ("encoder_epochs", "baseline_epochs")  # options a resumed run may raise: its fits continue to the new count
# options a resumed run may give or drop: dropping --no-encoder adds the encoder's stages to a finished run, giving it
# ends a run whose encoder cannot finish (its last.ckpt kept, for a resume without it)
STAGE_CHOICES = ("no_encoder",)


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
    return ckpt if configs.absolute(ckpt).is_file() else None


def without_option(args: list[str], name: str) -> list[str]:
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
    return best if configs.absolute(best).is_file() else checkpoints / "last.ckpt"


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
        alone = without_option(args, "--ckpt_path") if ckpt else args
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
            unbudgeted = without_option(recorded.split(" ")[2:], "--trainer.max_epochs")
            return args[0] == "fit" and ckpt is not None and unbudgeted == without_option(args, "--trainer.max_epochs")

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
            mtime = configs.absolute(saved).stat().st_mtime if saved is not None else 0.0
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
