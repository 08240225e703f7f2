"""The ``analysis`` options of every forecaster (``model.init_args.analysis``): typed dataclasses, and the
mapping a config writes for them.

:class:`AnalysisSettings` and its sections (:class:`ValidTimeSettings`, :class:`DynamicsSettings`,
:class:`TrueSystemSettings`) are what the code reads. A config writes them as a mapping, e.g.
``{valid_time: {}, dynamics: {runs: 16, free_steps: 200}}``; :class:`ForecastModule
<ssm_ms.forecasting.protocol.ForecastModule>` declares that argument as :data:`AnalysisOptions`, a ``TypedDict``
derived from the dataclasses' fields, so LightningCLI (jsonargparse) checks the mapping when it parses the
config: an unknown key (at any depth) or a value of the wrong type is one ``error:`` line before any work. The
ranges (a whole number >= 1, a threshold > 0) are checked when the dataclasses are built, with a message naming
the option. (A mapping, not the dataclasses themselves, because jsonargparse reads a dataclass-typed argument
as a group of its own: it then lets an unknown section written as ``{}`` pass unnoticed, merges a value given
later into the one given before instead of replacing it, and refuses a dotted key into it after a ``config:``
include, which the configs' overlays use.)

The mapping, as before the dataclasses (:meth:`AnalysisSettings.of`):

* no mapping (``null``, the default) or ``{}``: no analysis;
* a section named (``valid_time: {}``, ``dynamics: {runs: 4}``, or ``valid_time:`` with nothing, ``null``) is
  computed, with the defaults below for the options it does not give; a section left out is not computed;
* ``true_system`` is computed whenever the analysis runs (with its defaults unless given), where the data set
  can give the true system's exponents;
* ``dt``: seconds per step (null: the data set's ``sample_period``).

The same mapping is what a checkpoint's hyperparameters hold; an unknown key in it is refused naming the keys
its section takes.
"""

from __future__ import annotations

import dataclasses
import typing
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, Optional, TypedDict

# the whole-number options that may be 0; every other one is >= 1
_MAY_BE_ZERO = ("transient", "align", "seed")


def _section_type(hint: Any) -> type | None:
    """The section class in a field's type hint (``ValidTimeSettings | None`` -> ``ValidTimeSettings``), if any."""
    return next((t for t in (hint, *typing.get_args(hint)) if isinstance(t, type) and issubclass(t, _Section)), None)


@dataclass(frozen=True)
class _Section:
    """What every section shares: the range checks, and building one from a config's mapping."""

    key: ClassVar[str]  # where the section sits in a config, for messages: "analysis.valid_time"

    def __post_init__(self) -> None:
        hints = typing.get_type_hints(type(self))
        for f in dataclasses.fields(self):
            value, types = getattr(self, f.name), (hints[f.name], *typing.get_args(hints[f.name]))
            section = _section_type(hints[f.name])
            if value is None and type(None) in types:
                continue
            if section is not None:
                if not isinstance(value, section):
                    raise ValueError(f"{self.key}.{f.name} must be a {section.__name__}, got {value!r}")
            elif int in types:
                least = 0 if f.name in _MAY_BE_ZERO else 1
                if isinstance(value, bool) or not isinstance(value, int) or value < least:
                    raise ValueError(f"{self.key}.{f.name} must be a whole number >= {least}, got {value!r}")
            elif float in types:
                if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
                    raise ValueError(f"{self.key}.{f.name} must be > 0, got {value!r}")
                object.__setattr__(self, f.name, float(value))

    @classmethod
    def of(cls, value: Any) -> Any:
        """``value`` as this section: itself, or a config's mapping of its options (the defaults for those it does
        not give; a nested section named with a mapping or ``None`` is computed with its defaults for what that does
        not give). An unknown key is refused naming the keys the section takes."""
        if isinstance(value, cls):
            return value
        names = sorted(f.name for f in dataclasses.fields(cls))
        if not isinstance(value, Mapping):
            raise ValueError(f"{cls.key} must be a mapping of {names}, got {value!r}")
        unknown = sorted(set(value) - set(names))
        if unknown:
            raise ValueError(f"{cls.key} takes {names}, got {unknown}")
        hints = typing.get_type_hints(cls)
        kwargs = {}
        for name, item in value.items():
            section = _section_type(hints[name])
            kwargs[name] = item if section is None else section.of({} if item is None else item)
        return cls(**kwargs)

    def as_dict(self) -> dict[str, Any]:
        """The config's mapping of these settings (:meth:`of` reads it back): plain values, nested sections as
        mappings, a section that is ``None`` left out (not computed). What a checkpoint's hyperparameters hold
        (read with ``weights_only``)."""
        hints = typing.get_type_hints(type(self))
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, _Section):
                out[f.name] = value.as_dict()
            elif value is not None or _section_type(hints[f.name]) is None:
                out[f.name] = value
        return out


@dataclass(frozen=True)
class ValidTimeSettings(_Section):
    """The valid prediction time, for every forecaster: each test sequence is forecast ``horizon`` steps after
    ``n_filter`` given ones; the forecast is valid while its normalised error against the noiseless truth stays
    <= ``threshold`` (the reservoir-computing convention, Vlachas et al. 2020; docs/analysis.md).

    Args:
        n_filter: measurements given before the forecast (None: the protocol's ``n_filter``).
        horizon: steps forecast (None: the protocol's ``n_predict``, else the rest of each sequence).
        threshold: the largest normalised error of a valid forecast.
    """

    key: ClassVar[str] = "analysis.valid_time"
    n_filter: int | None = None
    horizon: int | None = None
    threshold: float = 0.5


@dataclass(frozen=True)
class DynamicsSettings(_Section):
    """SSMs only: ``f`` on its own, from shooting nodes drawn with ``seed``: its Lyapunov spectrum from ``runs``
    nodes, and long free runs from ``free_runs`` nodes decoded against the data
    (:func:`ssm_ms.analysis.dynamics_report`).

    Args:
        runs: nodes the Lyapunov spectrum starts from.
        free_runs: nodes the free runs start from (None: ``runs``; more steady the attractor statistics).
        lyapunov_steps: steps of the Benettin QR iteration.
        transient: steps run before the exponents are counted.
        align: steps that align the tangent vectors before they are counted.
        free_steps: steps of each free run.
        seed: the draw of the nodes.
    """

    key: ClassVar[str] = "analysis.dynamics"
    runs: int = 16
    free_runs: int | None = None
    lyapunov_steps: int = 4000
    transient: int = 2000
    align: int = 600
    free_steps: int = 20_000
    seed: int = 0


@dataclass(frozen=True)
class TrueSystemSettings(_Section):
    """The true system's Lyapunov exponents, where the data set has its equations (``true_transition``): from the
    first states of ``runs`` test sequences; computed once per data set and settings, cached beside the data.

    Args:
        runs: test sequences whose first states start the runs.
        lyapunov_steps: steps of the Benettin QR iteration.
        transient: steps run before the exponents are counted.
        align: steps that align the tangent vectors before they are counted.
    """

    key: ClassVar[str] = "analysis.true_system"
    runs: int = 16
    lyapunov_steps: int = 4000
    transient: int = 2000
    align: int = 600


@dataclass(frozen=True)
class AnalysisSettings(_Section):
    """What the test computes beyond the score (docs/analysis.md), written to the results file's *Analysis*.

    Args:
        valid_time: the valid prediction time of the forecasts, any forecaster (None: not computed).
        dynamics: what the SSM's ``f`` does on its own, SSMs only (None: not computed).
        true_system: the true system's exponents, where the data set can give them (None: not computed).
        dt: seconds per step (None: the data set's ``sample_period``).
    """

    key: ClassVar[str] = "analysis"
    valid_time: ValidTimeSettings | None = None
    dynamics: DynamicsSettings | None = None
    true_system: TrueSystemSettings | None = TrueSystemSettings()
    dt: float | None = None

    @classmethod
    def of(cls, value: Any) -> AnalysisSettings | None:
        """The settings of ``analysis`` (itself, or a config's mapping: see the module doc); ``None`` for no
        analysis (``None`` or an empty mapping)."""
        if value is None or (isinstance(value, Mapping) and not value):
            return None
        return super().of(value)


def _options(cls: type) -> Any:
    """The mapping a config writes for section ``cls``: a ``TypedDict`` of its fields, every key optional, a
    nested section as its own mapping (or null)."""
    hints = typing.get_type_hints(cls)
    fields = {}
    for f in dataclasses.fields(cls):
        section = _section_type(hints[f.name])
        fields[f.name] = hints[f.name] if section is None else Optional[_options(section)]  # noqa: UP045 (a type built at run time)
    return TypedDict(cls.__name__.replace("Settings", "Options"), fields, total=False)


#: The type of ``analysis`` in a config (what jsonargparse checks): :class:`AnalysisSettings` as a mapping.
AnalysisOptions = _options(AnalysisSettings)
