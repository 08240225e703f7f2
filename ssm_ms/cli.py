"""The LightningCLI behind ``cli.py`` (importable, so that tests can run it in-process).

What the command line adds to Lightning's:

- **Errors.** A user's mistake (config, data, checkpoint) prints one line ``error: <what is wrong and
  what to do>`` to stderr and exits with status 2 (command line / config not parsed) or 1 (anything
  else), without a traceback. The rule: an error of the command line (jsonargparse's parsing, with its
  "Does not validate against any of the Union subtypes" wrapping removed), or a ``ValueError``,
  ``OSError`` (e.g. ``FileNotFoundError``) or ``FloatingPointError`` (the NaN-loss stop) *raised by this
  project's own code* (``ssm_ms/``, ``datamodules/``), also when jsonargparse wrapped it while building
  the model or the data. Anything else is a bug and shows its traceback. ``SSM_MS_TRACEBACK=1`` in the
  environment shows the full traceback for everything.
- **Checkpoints.** ``--ckpt_path`` and ``model.init_args.ssm_checkpoint`` are read (``weights_only``)
  before anything is built: a missing, truncated or foreign file, or the checkpoint of another kind of
  model, is refused with a message.
- **Ctrl-C.** An interrupted ``fit`` exits with status 130 and prints the command that resumes it from
  the last completed epoch's ``last.ckpt`` (written every epoch by
  :class:`ssm_ms.checkpointing.EpochCheckpoint`).
- **Interpolation** (``${model.init_args.state_dim}``) is resolved after the command line is applied
  (jsonargparse's ``omegaconf+`` mode), so ``--model.init_args.state_dim 5`` reaches f and g too, and
  ``--print_config`` shows the values the run uses.
"""

from __future__ import annotations

import os
import re
import shlex
import signal
import sys
from argparse import ArgumentError
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
from jsonargparse import set_parsing_settings
from lightning.pytorch.cli import LightningArgumentParser, LightningCLI
from lightning.pytorch.trainer.states import TrainerStatus

from ssm_ms.checkpointing import EpochCheckpoint, read_checkpoint
from ssm_ms.perf import configure_allocator

TRACEBACK_ENV = "SSM_MS_TRACEBACK"
ROOT = Path(__file__).resolve().parents[1]
OWN_CODE = (ROOT / "ssm_ms", ROOT / "datamodules")
USER_ERROR_TYPES = (ValueError, OSError, FloatingPointError)
LIGHTNING_CKPT_ALIASES = ("last", "best", "hpc", "registry")


class CommandLineError(ArgumentError):
    """The command line or a config file could not be parsed (raised instead of printing the usage)."""

    def __init__(self, message: str):
        super().__init__(None, message)


class Interrupted(Exception):
    """``fit`` was stopped by Ctrl-C (SIGINT); the message says how to resume."""


class _Parser(LightningArgumentParser):
    """Lightning's parser, raising on errors (one message from :func:`main`) instead of printing the usage."""

    def error(self, message: str, ex: Exception | None = None):
        raise CommandLineError(message) from ex


class SSMCLI(LightningCLI):
    """``LightningCLI`` that checks checkpoints before use and turns Ctrl-C into a resume command."""

    def __init__(self, *args: Any, argv: list[str] | None = None, **kwargs: Any):
        self._argv = list(sys.argv[1:] if argv is None else argv)
        super().__init__(*args, args=argv, **kwargs)

    def parse_arguments(self, parser: LightningArgumentParser, args: Any) -> None:
        super().parse_arguments(parser, args)
        subcommand = self.config.get("subcommand")
        config = self.config[subcommand] if subcommand else self.config
        ckpt = config.get("ckpt_path")
        expected = config.get("model", {}).get("class_path") if config.get("model") else None
        if ckpt and str(ckpt) not in LIGHTNING_CKPT_ALIASES:
            saved = read_checkpoint(ckpt, "--ckpt_path")
            kind = saved.get("hyper_parameters", {}).get("_class_path")
            if kind and expected and kind != expected:
                raise ValueError(
                    f"--ckpt_path {ckpt} is the checkpoint of a {kind}, but this config builds a {expected}: "
                    "give the last.ckpt of a run of this config (or the config of that run, saved as config.yaml "
                    "in its folder)"
                )
        model_args = config.get("model", {}).get("init_args") if config.get("model") else None
        ssm = model_args.get("ssm_checkpoint") if model_args is not None else None
        if ssm:
            saved = read_checkpoint(ssm, "model.init_args.ssm_checkpoint")
            if "nodes.weight" not in saved.get("state_dict", {}):
                kind = saved.get("hyper_parameters", {}).get("_class_path") or saved.get("forecaster") or "another model"
                raise ValueError(
                    f"model.init_args.ssm_checkpoint {ssm} is the checkpoint of {kind}, not of an SSM: give the "
                    "last.ckpt of an SSM run (python cli.py fit --config configs/<experiment>.yaml)"
                )

    def fit(self, model: pl.LightningModule, **kwargs: Any) -> None:
        try:
            self.trainer.fit(model, **kwargs)
        except SystemExit:
            # Lightning answers Ctrl-C by shutting down gracefully and calling sys.exit(1)
            if self.trainer.state.status == TrainerStatus.INTERRUPTED:
                raise Interrupted(self._resume_message()) from None
            raise

    def _resume_message(self) -> str:
        savers = sorted(self.trainer.checkpoint_callbacks, key=lambda c: not isinstance(c, EpochCheckpoint))
        last = next((c.last_model_path for c in savers if getattr(c, "last_model_path", "")), "")
        epoch = self.trainer.current_epoch
        if not last or not Path(last).is_file():
            return f"interrupted during epoch {epoch}; no checkpoint was written yet: nothing to resume, start again"
        argv, skip = [], False
        for arg in self._argv:  # the same command with --ckpt_path replaced
            if skip:
                skip = False
            elif arg == "--ckpt_path":
                skip = True
            elif not arg.startswith("--ckpt_path="):
                argv.append(arg)
        command = shlex.join(["python", "cli.py", *argv, "--ckpt_path", last])
        return f"interrupted during epoch {epoch}; the last completed epoch is saved in {last}. Resume with:\n  {command}"


# ---------------------------------------------------------------------------- user errors
_JSONARGPARSE_NOISE = (
    "Does not validate against any of the Union subtypes",
    "Subtypes:",
    "Errors:",
    "Given value type:",
    "Given value:",
    "Expected a <class 'NoneType'>",
    "Expected a <class 'dict'>",
)


def _parse_error_message(text: str) -> str:
    """jsonargparse's nested error text as ``<config key>: <problem>``."""
    keys: list[str] = []
    details: list[str] = []
    for raw in text.splitlines():
        line = raw.strip()
        while line.startswith("- "):
            line = line[2:].strip()
        if not line or line.startswith(_JSONARGPARSE_NOISE):
            continue
        m = re.match(r'Parser key "([^"]+)":\s*(.*)', line)
        if m:
            keys.append(m.group(1))
            line = m.group(2)
        m = re.match(r"Problem with given class_path '([^']+)':\s*(.*)", line)
        if m:
            keys.append("init_args")
            line = m.group(2)
        if line:
            details.append(line)
    key = ".".join(keys)
    if key.endswith(".init_args"):
        key = key[: -len(".init_args")]
    message = "; ".join(dict.fromkeys(details)) or text.strip()
    return f"{key}: {message}" if key else message


def _raised_by_own_code(exc: BaseException) -> bool:
    tb = exc.__traceback__
    if tb is None:
        return False
    while tb.tb_next is not None:
        tb = tb.tb_next
    filename = Path(tb.tb_frame.f_code.co_filename).resolve()
    return any(filename.is_relative_to(root) for root in OWN_CODE)


def user_error(exc: BaseException) -> tuple[str, int] | None:
    """The message and exit status of a user's mistake, or None for a bug (see the module docstring)."""
    if isinstance(exc, Interrupted):
        return str(exc), 130
    if isinstance(exc, KeyboardInterrupt):  # outside training: nothing to save
        return "interrupted", 130
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:  # jsonargparse wraps the original error
        seen.add(id(current))
        if isinstance(current, USER_ERROR_TYPES) and _raised_by_own_code(current):
            return str(current), 1
        if isinstance(current, CommandLineError):
            cause = current.__cause__
            while cause is not None:  # a wrapped error of our own code says it best
                if isinstance(cause, USER_ERROR_TYPES) and _raised_by_own_code(cause):
                    return str(cause), 1
                cause = cause.__cause__
            return _parse_error_message(current.message), 2
        current = current.__cause__
    return None


def _help_command(args: list[str] | None) -> str:
    argv = sys.argv[1:] if args is None else args
    subcommand = next((a for a in argv if a in ("fit", "validate", "test", "predict")), None)
    return f"python cli.py {subcommand} --help" if subcommand else "python cli.py --help"


def main(args: list[str] | None = None, run: bool = True) -> LightningCLI:
    """Parse ``args`` (default: ``sys.argv``) and run the subcommand.

    Subclass mode for model and data (configs name them by ``class_path``) and the omegaconf parser
    (configs may interpolate, e.g. ``state_dim: ${model.init_args.state_dim}``), resolved after the
    command line. A user's mistake exits with one message on stderr (see the module docstring).
    """
    configure_allocator()  # large CPU tensors: reuse freed memory instead of page-faulting it back
    # interpolation paths are written from the config's root (the subcommand's level)
    set_parsing_settings(omegaconf_absolute_to_relative_paths=True)
    sigint = signal.getsignal(signal.SIGINT)  # Lightning ignores SIGINT after a Ctrl-C: restore it after
    try:
        return SSMCLI(
            pl.LightningModule,
            pl.LightningDataModule,
            subclass_mode_model=True,
            subclass_mode_data=True,
            parser_class=_Parser,
            parser_kwargs={"parser_mode": "omegaconf+"},
            save_config_kwargs={"overwrite": True},
            argv=args,
            run=run,
        )
    except (Exception, KeyboardInterrupt) as exc:
        if os.environ.get(TRACEBACK_ENV, "") not in ("", "0"):
            raise
        found = user_error(exc)
        if found is None:
            raise
        message, status = found
        hint = {1: f"\n(set {TRACEBACK_ENV}=1 for the full traceback)", 2: f"\n({_help_command(args)} lists every option)"}
        hint = hint.get(status, "")
        prefix = "" if status == 130 else "error: "  # Ctrl-C is not an error
        print(f"{prefix}{message}{hint}", file=sys.stderr)
        raise SystemExit(status) from None
    finally:
        signal.signal(signal.SIGINT, sigint)
