"""The experiment registry, ``configs/experiments.yaml``: every experiment's stages and their configs per size
(``make reproduce``: :mod:`experiments.reproduce`), the benchmarks and suites, the paper's tables and the experiments
scored against each (:func:`paper_table`: :mod:`experiments.results`), and which results the README's generated
tables show (``readme_tables``: :mod:`experiments.readme`). Read with omegaconf alone (no Lightning, no torch)."""

from __future__ import annotations

import functools
import re
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[1]
REGISTRY = ROOT / "configs" / "experiments.yaml"
SIZE_SUFFIX = {"paper": "", "cpu": "_cpu"}  # results/<experiment><suffix>.json: the results file of each size
LISTED = ("control", "baselines")  # the stages that name a list of configs (run in order); the others name one


def stage_configs(stages: dict[str, Any]) -> list[tuple[str, str]]:
    """``(stage, config path)`` for every config one experiment's stages name at one size, in the registry's order."""
    return [(kind, path) for kind, value in stages.items() for path in (value if kind in LISTED else [value])]


def read_registry() -> dict:
    """The experiment registry (:data:`REGISTRY`): ``experiments`` (name -> size -> stage -> config path),
    ``benchmarks`` (name -> ``fit`` and ``test`` configs), ``suites`` (name -> experiments), ``paper_tables``,
    ``readme_tables``."""
    return OmegaConf.to_container(OmegaConf.load(REGISTRY))


@functools.cache
def _registry() -> dict:
    return read_registry()


def _cell(value: Any) -> Any:
    """A paper cell as the registry writes it (``[mean, std]`` or words) -> ``(mean, std)`` or the words."""
    return tuple(value) if isinstance(value, list) else value


def paper_tables(registry: dict | None = None) -> dict[str, dict[str, Any]]:
    """``{experiment: table}``: the paper's table each experiment is scored against, as a results file shows it:
    ``table`` (its caption), ``rows`` (``{method: {"<target>/<metric>": cell}}``, a cell ``(mean, std)`` or words),
    ``notes`` (lines), ``inference_rows`` (``{inference: row}``, possibly empty)."""
    registry = _registry() if registry is None else registry
    out = {}
    for table in (registry.get("paper_tables") or {}).values():
        common = {"inference_rows": table.get("inference_rows") or {}}
        if "columns" not in table:
            rows = {m: {c: _cell(v) for c, v in cells.items()} for m, cells in table["rows"].items()}
            for experiment in table["experiments"]:
                out[experiment] = {"table": table["caption"], "rows": rows, "notes": table.get("notes"), **common}
            continue
        labels = table["column_labels"]
        whole = ["", "| method | " + " | ".join(labels.values()) + " |", "|---" * (len(labels) + 1) + "|"]
        whole += [
            f"| {method} | " + " | ".join(paper_cell(_cell(cells[c])) for c in labels) + " |"
            for method, cells in table["rows"].items()
        ]
        for experiment, column in table["columns"].items():
            out[experiment] = {
                "table": table["caption"].format(column=column),
                "rows": {m: {table["metric"]: _cell(cells[column])} for m, cells in table["rows"].items()},
                "notes": [*(table.get("notes") or []), *whole],
                **common,
            }
    return out


def paper_cell(cell: Any) -> str:
    """A paper cell: ``mean ± std``, ``mean`` or its words."""
    if cell is None:
        return "—"
    if isinstance(cell, str):
        return cell
    mean, std = cell
    return f"{mean}" if std is None else f"{mean} ± {std}"


def registered_experiment(results_name: str, registry: dict | None = None) -> tuple[str, str] | None:
    """``(experiment, size)`` of a results file's name: ``<experiment>`` at the paper's size, ``<experiment>_cpu``
    the CPU-sized twin, either with ``_seed<N>`` (``make reproduce ... SEED=N``); None for a name the registry does
    not know (a variant of an experiment, a user's own)."""
    registry = _registry() if registry is None else registry
    experiments = registry.get("experiments", {})
    name = re.sub(r"_seed\d+$", "", results_name)
    for size, suffix in SIZE_SUFFIX.items():
        base = name[: len(name) - len(suffix)] if suffix and name.endswith(suffix) else name if not suffix else None
        if base is not None and size in experiments.get(base, {}):
            return base, size
    return None


def paper_table(results_name: str, registry: dict | None = None) -> dict[str, Any] | None:
    """The paper's table (:func:`paper_tables`) a results file's runs are shown beside, or None."""
    found = registered_experiment(results_name, registry)
    return paper_tables(registry).get(found[0]) if found else None
