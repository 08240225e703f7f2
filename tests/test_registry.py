"""The experiment registry (configs/experiments.yaml) names every experiment's stages: each path it names exists, each
runnable config is named by it (a config runs as a stage because the registry says so, not by its file name), and its
suites hold registered experiments only; its paper tables name registered experiments, whose results files are named
as the renderer looks them up, and its README tables name results files that exist."""

from __future__ import annotations

from pathlib import Path

import pytest

from experiments.registry import (
    REGISTRY,
    SIZE_SUFFIX,
    paper_table,
    read_registry,
    registered_experiment,
    stage_configs,
)
from experiments.reproduce import known_experiments

ROOT = Path(__file__).resolve().parents[1]
STAGES = {"ssm", "ukf", "optimise", "control", "record", "encoder", "baselines"}


def named_paths(registry: dict) -> list[str]:
    paths = []
    for sizes in registry["experiments"].values():
        for stages in sizes.values():
            paths += [path for _, path in stage_configs(stages)]
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


def paper_experiments(registry: dict) -> list[str]:
    """The experiments the paper's tables name (a table with columns: its columns' experiments)."""
    names = []
    for table in registry["paper_tables"].values():
        names += list(table["columns"]) if "columns" in table else table["experiments"]
    return names


def test_paper_tables_name_registered_experiments_once_and_hold_cells():
    registry = read_registry()
    names = paper_experiments(registry)
    assert set(names) <= set(registry["experiments"]) and len(names) == len(set(names))
    for key, table in registry["paper_tables"].items():
        assert set(table) <= {
            "caption",
            "experiments",
            "columns",
            "column_labels",
            "metric",
            "inference_rows",
            "rows",
            "notes",
        }
        cells = [c for row in table["rows"].values() for c in row.values()]
        assert all(isinstance(c, str) or (isinstance(c, list) and len(c) == 2) for c in cells), key
        if "columns" in table:  # every row has a cell in every column, and every column its label
            columns = set(table["columns"].values())
            assert set(table["column_labels"]) == columns and "{column}" in table["caption"], key
            assert all(set(row) == columns for row in table["rows"].values()), key
        assert set((table.get("inference_rows") or {}).values()) <= set(table["rows"]), key


def test_a_results_file_finds_its_experiment_and_table():
    assert registered_experiment("pendulum_fc_cpu") == ("pendulum_fc", "cpu")
    assert registered_experiment("lorenz_T1000_cpu_seed2") == ("lorenz_T1000", "cpu")
    assert registered_experiment("lorenz_T1000_noiseless") is None  # the variant is registered at CPU size alone
    assert registered_experiment("my_own") is None
    assert paper_table("quad_fc")["table"].startswith("Table 2") and paper_table("mnist_sprites_cpu") is None
    assert paper_table("lorenz_T100_cpu")["rows"]["SSM-UKF"] == {"clean/mse": (10.999, None)}


def test_the_experiments_of_the_paper_tables_write_the_results_files_the_renderer_reads():
    """A paper table's experiment at a size writes results/<experiment><suffix>.json (SIZE_SUFFIX: the CPU-sized
    twin's ``_cpu``) from every stage that scores: the file its paper rows are looked up by."""
    from experiments.configs import experiment_name

    registry = read_registry()
    wrong = []
    for name in paper_experiments(registry):
        for size, stages in registry["experiments"][name].items():
            for kind, config in stage_configs(stages):
                if kind != "ssm" and experiment_name(ROOT / config) != name + SIZE_SUFFIX[size]:
                    wrong.append((config, experiment_name(ROOT / config)))
    assert wrong == []


def test_the_readme_tables_name_results_files_that_exist():
    registry = read_registry()
    files = []
    for name, spec in registry["readme_tables"].items():
        assert spec["kind"] in ("methods", "sweep", "benchmarks"), name
        for group in spec.get("groups", []):
            files += [experiment for experiment, _ in group["rows"]] + [group["reference"]["file"]]
        files += list(spec.get("files", {}).values()) + ([spec["noise_free"]["file"]] if "noise_free" in spec else [])
    assert files and [f for f in files if not (ROOT / "results" / f"{f}.json").is_file()] == []


def test_every_scoring_stage_names_its_results_folder():
    """A forecaster or controller without ``results_dir`` writes into its run's own folder: every registered stage
    that scores states where its results go (results/, results/benchmarks/, a run folder), so that make reproduce
    and the README's commands write where the committed results are."""
    from experiments.configs import config_value

    registry = read_registry()
    configs = [b["test"] for b in registry["benchmarks"].values()]
    for sizes in registry["experiments"].values():
        for stages in sizes.values():
            configs += [config for kind, config in stage_configs(stages) if kind != "ssm"]
    unnamed = [c for c in configs if config_value(ROOT / c, "model.init_args.results_dir") is None]
    assert unnamed == []
