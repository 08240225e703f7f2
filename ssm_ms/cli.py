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
  model, is refused with a message. With ``--ckpt_path`` the model is rebuilt with the settings the
  checkpoint was trained with (Lightning's rule: a resumed run continues the saved model), replacing the
  config's and command line's ``model`` values; where a value given differs from the checkpoint's, one
  line on stderr says so (``note: --ckpt_path ...: model.init_args.lr = 0.01 from the checkpoint, not
  0.5 as given ...``). ``test``, ``validate`` and ``predict`` keep the reporting settings given on the command
  line (:data:`REPORTING`: which metrics, where results and figures go, the analysis, the experiment and method
  names; a config file's values do not count, so a pretrained model tested with its config writes where its
  checkpoint says): they change what is written about the model, not what it computes, so a trained model can be
  scored again with another metric into another folder. A checkpoint whose model does not fit this command's data
  (another experiment's) is refused naming that first (``the checkpoint ... was trained for another model or
  data ...``), then the detail (g's output shape against the data's, the trajectory length, the trajectory count).
- **Trainer settings.** An invalid ``trainer`` value that Lightning refuses when it builds the Trainer
  (a ``MisconfigurationException`` or ``ValueError``, e.g. ``--trainer.max_epochs -5``) is a user's
  mistake: one ``error: trainer: ...`` line, status 1.
- **Checkpoints every epoch.** A ``fit`` whose config names no :class:`ssm_ms.checkpointing.EpochCheckpoint` gets one
  (``last.ckpt`` at the end of every training epoch, in the run's ``checkpoints/``), so that a crash loses at most the
  epoch under way; ``trainer.enable_checkpointing: false`` turns it off, a config that names one sets its options.
- **Ctrl-C, SIGTERM.** An interrupted ``fit`` exits with status 130 and prints the command that resumes it from
  the last completed epoch's ``last.ckpt`` (written every epoch by
  :class:`ssm_ms.checkpointing.EpochCheckpoint`). SIGTERM (``kill <pid>``: what scripts and job schedulers send,
  and the way to stop a run started in the background, where SIGINT is ignored) stops it the same way: Lightning
  finishes the batch under way and raises its ``SIGTERMException``, which :meth:`SSMCLI.fit` turns into the same
  message.
- **Progress.** Where a config has a progress bar and names none, it is :class:`ssm_ms.progress.RunProgressBar`:
  Lightning's bar, also saying the epoch count and the time the remaining epochs take (``Epoch 445/1000, ~3.9 h
  to go``); where stdout is not a terminal (``> run.log``), plain lines, one per epoch. Lightning's advertisements
  and a deprecation warning it triggers are left out (:func:`ssm_ms.runtime.console.quiet_lightning`).
- **Counts of batches.** ``--trainer.limit_val_batches 1`` is one batch and ``1.0`` all of them, as Lightning documents
  (an int counts batches, a float is a fraction; the same for ``limit_{train,test,predict}_batches`` and
  ``overfit_batches``): :func:`counts_before_fractions` undoes a reordering that made the parser read the int 1 as
  1.0 (every batch).
- **Interpolation** (``${model.init_args.state_dim}``) is resolved after the command line is applied
  (jsonargparse's ``omegaconf+`` mode), so ``--model.init_args.state_dim 5`` reaches f and g too, and
  ``--print_config`` shows the values the run uses.
"""

from __future__ import annotations

import functools
import logging
import operator
import os
import re
import shlex
import signal
import sys
from argparse import ArgumentError
from pathlib import Path
from typing import Any, Union, get_args, get_origin

import lightning.pytorch as pl
import yaml
from jsonargparse import set_parsing_settings
from lightning.fabric.utilities.exceptions import MisconfigurationException
from lightning.pytorch.callbacks import ProgressBar
from lightning.pytorch.cli import LightningArgumentParser, LightningCLI
from lightning.pytorch.trainer.states import TrainerStatus
from lightning.pytorch.utilities.rank_zero import rank_zero_only
from omegaconf.errors import InterpolationResolutionError

from ssm_ms.checkpointing import EpochCheckpoint, holds_ssm, read_checkpoint
from ssm_ms.progress import RunProgressBar
from ssm_ms.runtime.console import quiet_lightning
from ssm_ms.runtime.perf import configure_allocator

TRACEBACK_ENV = "SSM_MS_TRACEBACK"
ROOT = Path(__file__).resolve().parents[1]
OWN_CODE = (ROOT / "ssm_ms", ROOT / "datamodules")
USER_ERROR_TYPES = (ValueError, OSError, FloatingPointError)
SUBCOMMANDS = ("fit", "validate", "test", "predict")
LIGHTNING_CKPT_ALIASES = ("last", "best", "hpc", "registry")
# model settings that say what is reported about a model and where, not what it computes: outside fit, the command's
# own win over a --ckpt_path checkpoint's
REPORTING = ("metrics", "results_dir", "figures_dir", "analysis", "experiment", "method_name")


class CommandLineError(ArgumentError):
    """The command line or a config file could not be parsed (raised instead of printing the usage)."""

    def __init__(self, message: str):
        super().__init__(None, message)


class Interrupted(Exception):
    """``fit`` was stopped by Ctrl-C (SIGINT) or SIGTERM; the message says how to resume."""


class _Parser(LightningArgumentParser):
    """Lightning's parser, raising on errors (one message from :func:`main`) instead of printing the usage."""

    def error(self, message: str, ex: Exception | None = None):
        raise CommandLineError(message) from ex

    def parse_path(self, cfg_path: Any, *args: Any, **kwargs: Any):
        problem = section_file_with_dotted_keys(Path(str(getattr(cfg_path, "absolute", cfg_path))))
        if problem:
            self.error(problem)
        return super().parse_path(cfg_path, *args, **kwargs)


def section_file_with_dotted_keys(path: Path) -> str | None:
    """What is wrong with a config file that gives a section as a file (``model: parts/x.yaml``) and changes it with
    dotted keys (``model.init_args.lr``) in the same file: jsonargparse then drops the file and changes the included
    config's section. ``None`` where the file has no such pair (or is not a mapping)."""
    try:
        raw = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError):
        return None  # jsonargparse reports what it cannot read
    if not isinstance(raw, dict):
        return None
    for key, value in raw.items():
        dotted = [k for k in raw if isinstance(k, str) and k.startswith(f"{key}.")]
        if isinstance(value, str) and value.endswith((".yaml", ".yml")) and dotted:
            return (
                f"{path}: '{key}: {value}' and '{dotted[0]}' in one file: the dotted key would drop {value} and "
                f"change the included config's {key} instead. Move the dotted keys to a config that includes this "
                f"one (config: {path.name}, as configs/benchmarks/cascaded_tanks_amortised_adam.yaml does), or "
                f"restate the section in full"
            )
    return None


class SSMCLI(LightningCLI):
    """``LightningCLI`` that checks checkpoints before use and turns Ctrl-C into a resume command."""

    def __init__(self, *args: Any, argv: list[str] | None = None, **kwargs: Any):
        self._argv = list(sys.argv[1:] if argv is None else argv)
        self._checkpoint_source: str | None = None  # "<--ckpt_path> (trained on ...)", for the model's messages
        self._model_as_given: dict[str, Any] = {}  # the model section as given, before --ckpt_path replaces it
        super().__init__(*args, args=argv, **kwargs)

    def parse_arguments(self, parser: LightningArgumentParser, args: Any) -> None:
        super().parse_arguments(parser, args)
        subcommand = self.config.get("subcommand")
        config = self.config[subcommand] if subcommand else self.config
        given = config.get("model")
        self._model_as_given = given.clone().as_dict() if given is not None else {}  # before --ckpt_path's
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
            self._checkpoint_source = f"{ckpt}" + _trained_on(saved)
        model_args = config.get("model", {}).get("init_args") if config.get("model") else None
        ssm = model_args.get("ssm_checkpoint") if model_args is not None else None
        if ssm:
            saved = read_checkpoint(ssm, "model.init_args.ssm_checkpoint")
            if not holds_ssm(saved):
                kind = (
                    saved.get("hyper_parameters", {}).get("_class_path") or saved.get("forecaster") or "another model"
                )
                raise ValueError(
                    f"model.init_args.ssm_checkpoint {ssm} is the checkpoint of {kind}, not of an SSM: give the "
                    "last.ckpt of an SSM run (python cli.py fit --config configs/<experiment>.yaml)"
                )

    def before_instantiate_classes(self) -> None:
        """With ``--ckpt_path`` Lightning has replaced the model's settings by the checkpoint's (between
        :meth:`parse_arguments` and this hook): outside ``fit`` the reporting settings given come back (see the
        module doc), and one line names each other value given that the checkpoint's replaced."""
        subcommand = self.config.get("subcommand")
        after = self.config[subcommand].get("model") if subcommand else None
        after = after.as_dict() if after is not None else {}
        given_args, saved_args = self._model_as_given.get("init_args") or {}, after.get("init_args") or {}
        if subcommand != "fit" and self._checkpoint_source is not None:
            for key in REPORTING:
                flag = f"--model.init_args.{key}"
                on_command_line = any(arg == flag or arg.startswith(flag + "=") for arg in self._argv)
                if on_command_line and key in saved_args and saved_args[key] != given_args.get(key):
                    self.config[subcommand][f"model.init_args.{key}"] = given_args[key]
                    saved_args[key] = given_args[key]
        old, new = _flatten(self._model_as_given, "model"), _flatten(after, "model")
        replaced, other_class = [], []
        for key, value in old.items():
            if value is None or key not in new or new[key] == value:
                continue
            if any(key.startswith(prefix) for prefix in other_class):
                continue  # the init_args of a network replaced by another class
            if key.endswith(".class_path"):
                other_class.append(key[: -len("class_path")])
            replaced.append(f"{key} = {new[key]!r} from the checkpoint, not {value!r} as given")
        if replaced and rank_zero_only.rank == 0:
            shown = "; ".join(replaced[:6]) + (f"; and {len(replaced) - 6} more" if len(replaced) > 6 else "")
            print(
                f"note: --ckpt_path resumes the model the checkpoint was trained with, so its settings win over "
                f"this command's: {shown} (to train with other model settings, start a fresh run without "
                "--ckpt_path)",
                file=sys.stderr,
            )

    def after_instantiate_classes(self) -> None:
        super().after_instantiate_classes()
        if self._checkpoint_source is not None and hasattr(self.model, "checkpoint_source"):
            self.model.checkpoint_source = self._checkpoint_source  # its data checks then name the checkpoint first

    def instantiate_trainer(self, **kwargs: Any) -> pl.Trainer:
        """The trainer with the house's callbacks where the config names none of their kind: a fit writes
        ``last.ckpt`` every epoch (:class:`EpochCheckpoint`, unless ``enable_checkpointing: false``) and the console
        shows :class:`RunProgressBar` (unless ``enable_progress_bar: false``)."""
        trainer = self._get(self.config_init, "trainer", default={})
        given = trainer.get("callbacks") or []
        callbacks = list(given if isinstance(given, list) else [given])
        before, after = [], []
        checkpointing = trainer.get("enable_checkpointing") is not False
        if self.subcommand == "fit" and checkpointing and not any(isinstance(c, EpochCheckpoint) for c in callbacks):
            before.append(EpochCheckpoint())  # first of the checkpoint callbacks: trainer.checkpoint_callback
        if trainer.get("enable_progress_bar") is not False and not any(isinstance(c, ProgressBar) for c in callbacks):
            after.append(RunProgressBar())  # in place of Lightning's own bar
        if before or after:
            kwargs.setdefault("callbacks", [*before, *callbacks, *after])
        try:
            return super().instantiate_trainer(**kwargs)
        except (MisconfigurationException, ValueError) as err:  # Lightning refusing a trainer setting
            raise ValueError(f"trainer: {err}") from err

    def fit(self, model: pl.LightningModule, **kwargs: Any) -> None:
        try:
            self.trainer.fit(model, **kwargs)
        except SystemExit:
            # Lightning answers Ctrl-C by shutting down gracefully and calling sys.exit(1), and SIGTERM by raising
            # SIGTERMException (a SystemExit) after the batch under way
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
        return (
            f"interrupted during epoch {epoch}; the last completed epoch is saved in {last}. Resume with:\n  {command}"
        )


def _flatten(value: Any, prefix: str) -> dict[str, Any]:
    """``{"a": {"b": 1}}`` as ``{"<prefix>.a.b": 1}`` (lists are values)."""
    if isinstance(value, dict):
        out: dict[str, Any] = {}
        for key, item in value.items():
            out.update(_flatten(item, f"{prefix}.{key}"))
        return out
    return {prefix: value}


def _trained_on(checkpoint: dict[str, Any]) -> str:
    """`` (trained on the 'pendulum' data of PendulumDataModule)`` from the data module's state Lightning saves
    under its class name; empty where the checkpoint holds none."""
    for key, value in checkpoint.items():
        if isinstance(value, dict) and "generator_params" in value and "name" in value:
            return f" (trained on the {value['name']!r} data of {key})"
    return ""


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
        if isinstance(current, InterpolationResolutionError):
            return interpolation_message(current), 1
        if isinstance(current, CommandLineError):
            cause = current.__cause__
            while cause is not None:  # a wrapped error of our own code says it best
                if isinstance(cause, USER_ERROR_TYPES) and _raised_by_own_code(cause):
                    return str(cause), 1
                cause = cause.__cause__
            return _parse_error_message(current.message), 2
        current = current.__cause__
    return None


def interpolation_message(exc: InterpolationResolutionError) -> str:
    """One line for a config interpolation that does not resolve: where, and how to write it instead."""
    key = getattr(exc, "full_key", None) or ""
    head, _, rest = key.partition(".")
    where = f" (at {rest if head in SUBCOMMANDS else key})" if key else ""
    return (
        f"a config interpolation cannot be resolved{where}: {str(exc).splitlines()[0]}; an interpolation works in a "
        'nested section, not under a dotted key (docs/cli.md, "Configs as overlays"): write the value there, or '
        "restate the section"
    )


def _help_command(args: list[str] | None) -> str:
    argv = sys.argv[1:] if args is None else args
    subcommand = next((a for a in argv if a in SUBCOMMANDS), None)
    return f"python cli.py {subcommand} --help" if subcommand else "python cli.py --help"


class _StderrHandler(logging.StreamHandler):
    """Writes to ``sys.stderr`` as it is when a line is logged, not as it was when the handler was made: a stderr
    redirected or captured since (``main`` called again in one process, under pytest) gets the lines, and a closed
    one is never written to."""

    def emit(self, record: logging.LogRecord) -> None:
        self.stream = sys.stderr
        super().emit(record)


def show_package_log() -> None:
    """The ``ssm_ms`` logger's INFO lines (e.g. which decoder backend ``auto`` chose) on stderr, as Lightning shows its
    own; once per process."""
    log = logging.getLogger("ssm_ms")
    if not log.handlers:
        handler = _StderrHandler()
        handler.setFormatter(logging.Formatter("%(message)s"))
        log.addHandler(handler)
        log.setLevel(logging.INFO)
        log.propagate = False


def counts_before_fractions() -> None:
    """Let the parser read ``--trainer.limit_val_batches 1`` as the int 1 (one batch), not 1.0 (every batch).

    Lightning annotates ``limit_*_batches`` and ``overfit_batches`` as ``Union[int, float]`` (an int counts batches,
    a float is a fraction) and jsonargparse tries a union's types in order. But typing caches unions by equality and
    ``Union[int, float] == Union[float, int]``: where the other order was built first in the process (it is, by the
    time Lightning is imported), the Trainer's annotation is ``Union[float, int, None]``: the int 1, on the command line
    or in a config, became the float 1.0 (every batch) and ``--print_config`` showed every count as a float
    (github.com/Lightning-AI/pytorch-lightning/issues/21259). Here each annotation of ``Trainer.__init__`` whose float
    comes before its int is rebuilt int first as a PEP 604 union (``int | float | None``, not cached). Idempotent."""
    annotations = pl.Trainer.__init__.__annotations__  # the wrapped __init__ shares the function's dict
    for name, hint in annotations.items():
        members = get_args(hint)
        if get_origin(hint) is not Union or int not in members or float not in members:
            continue
        if members.index(float) < members.index(int):
            annotations[name] = functools.reduce(operator.or_, [int, *(m for m in members if m is not int)])


def _parsing_settings() -> None:
    """What every parse of a config needs, by :func:`main` or :func:`config_parser`: interpolation paths written from
    the config's root (the subcommand's level), the int before the float in the Trainer's counts."""
    set_parsing_settings(omegaconf_absolute_to_relative_paths=True)
    counts_before_fractions()


def _cli(cls: type[SSMCLI], args: list[str] | None, run: bool) -> SSMCLI:
    return cls(
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


class _ParserBuilt(Exception):
    def __init__(self, parser: LightningArgumentParser):
        super().__init__("parser built")
        self.parser = parser


class _ParserOnly(SSMCLI):
    """Stops once the parser is built, before anything is parsed, seeded or instantiated."""

    def parse_arguments(self, parser: LightningArgumentParser, args: Any) -> None:
        raise _ParserBuilt(parser)


@functools.cache
def config_parser() -> LightningArgumentParser:
    """The parser of ``python cli.py`` without a subcommand (``trainer``, ``model``, ``data``, ``seed_everything``),
    built as :func:`main` builds it, once per process: a config read through it composes exactly as the command
    line composes it (includes, section files, dotted keys, interpolations)."""
    _parsing_settings()
    try:
        _cli(_ParserOnly, [], run=False)
    except _ParserBuilt as built:
        return built.parser
    raise RuntimeError("LightningCLI parsed without calling parse_arguments")  # pragma: no cover


def main(args: list[str] | None = None, run: bool = True) -> LightningCLI:
    """Parse ``args`` (default: ``sys.argv``) and run the subcommand.

    Subclass mode for model and data (configs name them by ``class_path``) and the omegaconf parser
    (configs may interpolate, e.g. ``state_dim: ${model.init_args.state_dim}``), resolved after the
    command line. A user's mistake exits with one message on stderr (see the module docstring).
    """
    configure_allocator()  # large CPU tensors: reuse freed memory instead of page-faulting it back
    show_package_log()
    quiet_lightning()  # Lightning's advertisements and a deprecation warning it triggers: nothing to act on
    _parsing_settings()
    sigint = signal.getsignal(signal.SIGINT)  # Lightning ignores SIGINT after a Ctrl-C: restore it after
    try:
        return _cli(SSMCLI, args, run)
    except (Exception, KeyboardInterrupt) as exc:
        if os.environ.get(TRACEBACK_ENV, "") not in ("", "0"):
            raise
        found = user_error(exc)
        if found is None:
            raise
        message, status = found
        hint = {
            1: f"\n(set {TRACEBACK_ENV}=1 for the full traceback)",
            2: f"\n({_help_command(args)} lists every option)",
        }
        hint = hint.get(status, "")
        prefix = "" if status == 130 else "error: "  # Ctrl-C is not an error
        print(f"{prefix}{message}{hint}", file=sys.stderr)
        raise SystemExit(status) from None
    finally:
        signal.signal(signal.SIGINT, sigint)
