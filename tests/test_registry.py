"""The experiment registry (configs/experiments.yaml) names every experiment's stages: each path it names exists, each
runnable config is named by it (a config runs as a stage because the registry says so, not by its file name), and its
suites hold registered experiments only."""

from __future__ import annotations

from pathlib import Path

import pytest

from experiments.reproduce import REGISTRY, known_experiments, read_registry

ROOT = Path(__file__).resolve().parents[1]
STAGES = {"ssm", "ukf", "optimise", "control", "record", "encoder", "baselines"}


def named_paths(registry: dict) -> list[str]:
    paths = []
    for sizes in registry["experiments"].values():
        for stages in sizes.values():
            for kind, value in stages.items():
                paths += value if kind == "baselines" else [value]
    for benchmark in registry["benchmarks"].values():
        paths += [benchmark["fit"], benchmark["test"]]
    return paths


def test_every_path_the_registry_names_exists_once():
    registry = read_registry()
    paths = named_paths(registry)
    assert [p for p in paths if not (ROOT / p).is_file()] == []
    assert len(paths) == len(set(paths)), "a config named by two stages"


def test_every_runnable_config_is_named_by_the_registry():
    runnable = {
        str(p.relative_to(ROOT))
        for p in (ROOT / "configs").rglob("*.yaml")
        if p.parent.name not in ("data", "examples", "parts") and p != REGISTRY
    }
    assert sorted(runnable - set(named_paths(read_registry()))) == []


def test_stages_sizes_and_suites_are_the_known_ones():
    registry = read_registry()
    for name, sizes in registry["experiments"].items():
        assert set(sizes) <= {"paper", "cpu"}, name
        for size, stages in sizes.items():
            assert set(stages) <= STAGES, (name, size)
            # an experiment trains its SSM and scores it, or is a controller's test alone (the true model)
            assert ("ssm" in stages and set(stages) & {"ukf", "optimise", "control", "encoder"}) or set(stages) == {
                "control"
            }, (name, size)
    for suite, experiments in registry["suites"].items():
        assert set(experiments) <= set(registry["experiments"]), suite


@pytest.mark.parametrize("size", ["paper", "cpu"])
def test_the_known_names_include_baselines_alone_and_no_data_sections(size):
    known = known_experiments(read_registry(), size)
    assert "pendulum_lstm" in known and "pendulum" in known and "silverbox" in known
    assert "lorenz_T1000_noiseless" in known if size == "cpu" else "lorenz_T1000_noiseless" not in known
    assert not any(name.startswith("data") for name in known)
