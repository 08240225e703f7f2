"""Reading an experiment's config files as ``python cli.py`` composes them (jsonargparse through
:func:`ssm_ms.cli.config_parser`), and the paths a stage of ``make reproduce`` writes to: its logger's run folder,
its results folder, relative to the repository root (:data:`ROOT`)."""

from __future__ import annotations

import importlib
import os
import sys
from pathlib import Path

from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[1]


class ConfigError(ValueError):
    """A config file that cannot be read or composed: a user's mistake, said in one line naming the file."""


def load_config(config: Path | str) -> dict:
    """The config file ``config`` as ``python cli.py`` composes it (:func:`ssm_ms.cli.config_parser`: its includes,
    section files, dotted keys and interpolations, the defaults it leaves out filled in), as a dict.

    Read, not checked: a required value that a stage receives on the command line (an encoder's
    ``ssm_checkpoint``) may be missing. A file that is not a whole config (a data config: ``class_path`` and
    ``init_args``) is its YAML as written."""
    path = Path(config)
    raw = OmegaConf.to_container(OmegaConf.load(path), resolve=False) or {}
    if not isinstance(raw, dict):
        raise ConfigError(f"{path} is not a config (a YAML mapping of options)")
    if "class_path" in raw:  # a section file of its own (configs/data/*.yaml)
        return raw
    from omegaconf.errors import InterpolationResolutionError

    from ssm_ms.cli import CommandLineError, config_parser, interpolation_message

    # jsonargparse parses in the config's folder: the working directory's place on sys.path ("" under python -c)
    # must name the folder the process started in, for the classes the config names
    saved = list(sys.path)
    sys.path[:] = [p or os.getcwd() for p in sys.path]
    try:  # jsonargparse's parse without its check of required values (the stage's checkpoint comes with the command)
        parsed = config_parser().parse_args(["--config", str(path)], _skip_validation=True).as_dict()
    except CommandLineError as e:
        raise ConfigError(f"{path}: {e.message}") from None
    except InterpolationResolutionError as e:
        raise ConfigError(f"{path}: {interpolation_message(e)}") from None
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
    its class refuses, raise ConfigError with one line naming the file."""
    name = config if isinstance(config, (str, Path)) else "the config"
    spec = load_config(config) if isinstance(config, (str, Path)) else config
    spec = spec.get("data", spec)
    path = spec.get("class_path") if isinstance(spec, dict) else None
    if not isinstance(path, str) or "." not in path:
        raise ConfigError(f"{name} describes no data module (a class_path and init_args, or a data section of them)")
    module, attr = path.rsplit(".", 1)
    try:
        cls = getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as e:
        raise ConfigError(f"{name}: no data module {path} ({e})") from e
    try:
        return cls(**{**(spec.get("init_args") or {}), **overrides})
    except TypeError as e:  # an argument the class does not take
        raise ConfigError(f"{name}: {path} refuses its arguments ({e})") from e


def config_value(config: Path | str | dict, key: str, default=None):
    """The dotted ``key`` (``trainer.logger.init_args.name``) of the composed ``config`` (a file, or its
    :func:`load_config` dict: read once where several values are wanted), else ``default``."""
    value = load_config(config) if isinstance(config, (str, Path)) else config
    for part in key.split("."):
        if not isinstance(value, dict) or part not in value:
            return default
        value = value[part]
    return value


def logger_dir(config: Path | dict) -> Path:
    """``save_dir/name`` of the TensorBoard logger a config (a file, or its :func:`load_config` dict) declares."""
    args = config_value(config, "trainer.logger.init_args")
    if not isinstance(args, dict) or "save_dir" not in args or "name" not in args:
        name = config if isinstance(config, (str, Path)) else "the config"
        raise ConfigError(f"{name} declares no TensorBoardLogger with save_dir and name: reproduce needs them")
    return Path(str(args["save_dir"])) / str(args["name"])


def results_dir(config: Path, version: str) -> Path:
    """The folder a test stage of ``config`` writes its results file to: its ``results_dir``, or where it names none,
    the stage's own run folder (``save_dir/name/version`` of its logger), as the library does."""
    value = config_value(config, "model.init_args.results_dir")
    return absolute(Path(str(value)) if value is not None else logger_dir(config) / version)


def experiment_name(config: Path, loaded: dict | None = None) -> str:
    """The experiment a config's results go under: its model's ``experiment``, else the file's name (``loaded``: the
    file's :func:`load_config` dict, where the caller has read it)."""
    return str(config_value(config if loaded is None else loaded, "model.init_args.experiment", default=config.stem))


def absolute(path: Path) -> Path:
    """``path``, relative to the repository root where it is not absolute (the stages run from the root)."""
    return path if path.is_absolute() else ROOT / path
