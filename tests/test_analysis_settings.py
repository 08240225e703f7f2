"""The ``analysis`` options (``ssm_ms.forecasting.analysis_settings``): what a config's mapping means, written out
by hand; the ranges refused by name; and through the real command line (``ssm_ms.cli.main``, in-process, as
tests/test_bad_input.py runs it), an unknown key or a wrong type is one ``error:`` line before any work, the
shipped configs' mappings are read as written, and a checkpoint keeps them as plain values that load again."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from ssm_ms.baselines import LSTMBaseline
from ssm_ms.cli import main
from ssm_ms.forecasting.analysis_settings import (
    AnalysisSettings,
    DynamicsSettings,
    TrueSystemSettings,
    ValidTimeSettings,
)

# the defaults, as docs/analysis.md states them
VALID_TIME = {"n_filter": None, "horizon": None, "threshold": 0.5}
DYNAMICS = {
    "runs": 16,
    "free_runs": None,
    "lyapunov_steps": 4000,
    "transient": 2000,
    "align": 600,
    "free_steps": 20_000,
    "seed": 0,
}
TRUE_SYSTEM = {"runs": 16, "lyapunov_steps": 4000, "transient": 2000, "align": 600}


def plain(settings: AnalysisSettings | None) -> dict | None:
    return None if settings is None else dataclasses.asdict(settings)


# ---------------------------------------------------------------------------- the mapping
def test_a_config_mapping_means_what_it_meant_before_the_dataclasses():
    # no mapping, or an empty one: no analysis at all
    assert AnalysisSettings.of(None) is None and AnalysisSettings.of({}) is None
    # a section named with {} is computed with its defaults; one left out is not; the true system's exponents
    # whenever the analysis runs
    assert plain(AnalysisSettings.of({"valid_time": {}})) == {
        "valid_time": VALID_TIME,
        "dynamics": None,
        "true_system": TRUE_SYSTEM,
        "dt": None,
    }
    # YAML's `valid_time:` with nothing after it (null): computed with its defaults too
    assert plain(AnalysisSettings.of({"valid_time": None, "true_system": None})) == {
        "valid_time": VALID_TIME,
        "dynamics": None,
        "true_system": TRUE_SYSTEM,
        "dt": None,
    }
    # what a section gives replaces the default, key by key
    shipped = {
        "valid_time": {},
        "dynamics": {"runs": 16, "lyapunov_steps": 1000, "transient": 200, "align": 100, "free_steps": 200},
    }
    assert plain(AnalysisSettings.of(shipped))["dynamics"] == {
        "runs": 16,
        "free_runs": None,
        "lyapunov_steps": 1000,
        "transient": 200,
        "align": 100,
        "free_steps": 200,
        "seed": 0,
    }
    lorenz = AnalysisSettings.of(
        {
            "valid_time": {"n_filter": 1000, "horizon": 1000},
            "dt": 0.01,
            "true_system": {"runs": 2},
            "dynamics": {"runs": 16, "free_runs": 64},
        }
    )
    assert lorenz.valid_time == ValidTimeSettings(n_filter=1000, horizon=1000, threshold=0.5)
    assert lorenz.true_system == TrueSystemSettings(runs=2, lyapunov_steps=4000, transient=2000, align=600)
    assert lorenz.dynamics.free_runs == 64 and lorenz.dynamics.free_steps == 20_000 and lorenz.dt == 0.01
    # dt alone still runs the analysis (the true system's exponents), as before
    assert plain(AnalysisSettings.of({"dt": 0.05})) == {
        "valid_time": None,
        "dynamics": None,
        "true_system": TRUE_SYSTEM,
        "dt": 0.05,
    }
    # the mapping of a settings object reads back to it
    for settings in (lorenz, AnalysisSettings.of(shipped), AnalysisSettings(dynamics=DynamicsSettings(seed=3))):
        assert AnalysisSettings.of(settings.as_dict()) == settings


@pytest.mark.parametrize(
    "mapping, message",
    [
        ({"chaos": {}}, r"analysis takes \['dt', 'dynamics', 'true_system', 'valid_time'\], got \['chaos'\]"),
        (
            {"valid_time": {"steps": 3}},
            r"analysis.valid_time takes \['horizon', 'n_filter', 'threshold'\], got \['steps'\]",
        ),
        ({"valid_time": 3}, r"analysis.valid_time must be a mapping of \['horizon', 'n_filter', 'threshold'\], got 3"),
        ({"valid_time": {"horizon": 0}}, r"analysis.valid_time.horizon must be a whole number >= 1, got 0"),
        ({"valid_time": {"threshold": 0}}, r"analysis.valid_time.threshold must be > 0, got 0"),
        ({"dynamics": {"transient": -1}}, r"analysis.dynamics.transient must be a whole number >= 0, got -1"),
        ({"dynamics": {"runs": True}}, r"analysis.dynamics.runs must be a whole number >= 1, got True"),
        ({"dynamics": {"free_steps": 2.5}}, r"analysis.dynamics.free_steps must be a whole number >= 1, got 2.5"),
        ({"true_system": {"runs": None}}, r"analysis.true_system.runs must be a whole number >= 1, got None"),
        ({"dt": -0.1}, r"analysis.dt must be > 0, got -0.1"),
    ],
)
def test_a_mapping_out_of_the_schema_is_refused_naming_the_option(mapping, message):
    with pytest.raises(ValueError, match=message):
        AnalysisSettings.of(mapping)


def test_zero_is_a_transient_and_ints_are_floats_where_floats_are_asked():
    settings = AnalysisSettings.of(
        {"dynamics": {"transient": 0, "align": 0, "seed": 0}, "dt": 1, "valid_time": {"threshold": 2}}
    )
    assert (settings.dynamics.transient, settings.dynamics.align) == (0, 0)
    assert settings.dt == 1.0 and isinstance(settings.dt, float) and settings.valid_time.threshold == 2.0


def test_a_forecaster_takes_the_mapping_or_the_dataclass_and_saves_plain_values(tmp_path):
    mapping = {"valid_time": {"threshold": 0.3}, "dt": 0.1}
    given = AnalysisSettings(valid_time=ValidTimeSettings(threshold=0.3), dt=0.1)
    from_mapping = LSTMBaseline(n_filter=8, network={"hidden": 8}, analysis=mapping)
    from_python = LSTMBaseline(n_filter=8, network={"hidden": 8}, analysis=given)
    assert from_mapping.analysis_settings == from_python.analysis_settings == given
    assert from_mapping.hparams["analysis"] == mapping  # as given, as a checkpoint recorded it before
    # the dataclass given in Python is recorded as its mapping: a checkpoint reads with weights_only
    torch.save(dict(from_python.hparams), tmp_path / "hparams.pt")
    saved = torch.load(tmp_path / "hparams.pt", weights_only=True)
    assert AnalysisSettings.of(saved["analysis"]) == given
    assert LSTMBaseline(n_filter=8, analysis=None).analysis_settings is None


# ---------------------------------------------------------------------------- the command line
CONFIG = """\
seed_everything: 0
trainer:
  max_epochs: 1
  accelerator: cpu
  logger: false
  enable_progress_bar: false
  enable_model_summary: false
  num_sanity_val_steps: 0
  default_root_dir: {root}/runs
  callbacks:
    - class_path: ssm_ms.checkpointing.EpochCheckpoint
model:
  class_path: ssm_ms.baselines.LSTMBaseline
  init_args:
    n_filter: 8
    network: {{hidden: 8}}
    metrics: [mse]
    results_dir: {root}/results
    analysis:
      valid_time: {{n_filter: 6, horizon: 4}}
      dt: 0.1
data:
  class_path: datamodules.files.FileDataModule
  init_args: {{train_path: {root}/y.npz, key: y, batch_size: 4, val_trajectories: 2}}
"""


@pytest.fixture
def config(tmp_path):
    rng = np.random.default_rng(0)
    phase = rng.uniform(0, 6.28, (8, 1)) + 0.3 * np.arange(12)
    np.savez(tmp_path / "y.npz", y=np.stack([np.cos(phase), np.sin(phase)], -1).astype(np.float32))
    (tmp_path / "config.yaml").write_text(CONFIG.format(root=tmp_path))
    return tmp_path


def fails(capsys, root, analysis: str, status: int, *words: str) -> None:
    """``fit`` with ``--model.init_args.analysis <analysis>``: the exit status, one ``error:`` line (and the hint),
    no traceback, and no training (no checkpoint written)."""
    with pytest.raises(SystemExit) as exit_info:
        main(["fit", "--config", str(root / "config.yaml"), "--model.init_args.analysis", analysis])
    err = capsys.readouterr().err
    assert exit_info.value.code == status, err
    lines = err.strip().splitlines()
    assert lines[0].startswith("error: ") and len(lines) <= 2 and "Traceback" not in err, err
    for word in words:
        assert word in lines[0], err
    assert not list((root / "runs").glob("**/*.ckpt"))


def test_an_unknown_analysis_key_is_one_error_line(config, capsys):
    fails(capsys, config, '{"valid_tme": {}}', 2, "model.init_args.analysis", "valid_tme")  # also written as {}
    fails(capsys, config, '{"valid_time": {"steps": 3}}', 2, "model.init_args.analysis", "steps")


def test_a_wrong_type_is_one_error_line(config, capsys):
    fails(
        capsys, config, '{"valid_time": {"horizon": "long"}}', 2, "model.init_args.analysis", "Expected a <class 'int'>"
    )
    fails(capsys, config, '{"dynamics": {"runs": 1.5}}', 2, "model.init_args.analysis", "Expected a <class 'int'>")
    fails(capsys, config, '{"dt": "fast"}', 2, "model.init_args.analysis", "float")


def test_an_option_out_of_range_is_one_error_line(config, capsys):
    fails(
        capsys,
        config,
        '{"valid_time": {"horizon": 0}}',
        1,
        "analysis.valid_time.horizon must be a whole number >= 1, got 0",
    )
    fails(capsys, config, '{"dynamics": {}}', 1, "analysis.dynamics studies an SSM's f; a baseline has none")


def test_the_config_mapping_is_read_as_written_and_reloads_from_the_checkpoint(config):
    cli = main(["fit", "--config", str(config / "config.yaml")])
    expected = AnalysisSettings(valid_time=ValidTimeSettings(n_filter=6, horizon=4), dt=0.1)
    assert cli.model.analysis_settings == expected
    (ckpt,) = (config / "runs").glob("**/last.ckpt")
    saved = torch.load(ckpt, weights_only=True)["hyper_parameters"]["analysis"]
    assert saved == {"valid_time": {"n_filter": 6, "horizon": 4}, "dt": 0.1}  # the config's mapping, plain
    assert LSTMBaseline.load_from_checkpoint(ckpt).analysis_settings == expected
    # a command line mapping replaces the config's, as a mapping did before (no merge of the two)
    cli = main(["--config", str(config / "config.yaml"), "--model.init_args.analysis", '{"dt": 0.2}'], run=False)
    assert cli.model.analysis_settings == AnalysisSettings(dt=0.2)
    cli = main(["--config", str(config / "config.yaml"), "--model.init_args.analysis", "null"], run=False)
    assert cli.model.analysis_settings is None


def test_an_older_checkpoint_with_an_unknown_analysis_key_is_refused_by_name(tmp_path):
    model = LSTMBaseline(n_filter=8, network={"hidden": 8}, obs_shape=[2], analysis={"valid_time": {}})
    ckpt = {
        "state_dict": model.state_dict(),
        "hyper_parameters": {**model.hparams, "analysis": {"valid_tme": {}}},
        "pytorch-lightning_version": "2.6.0",
    }
    torch.save(ckpt, tmp_path / "old.ckpt")
    with pytest.raises(
        ValueError,
        match=r"analysis takes \['dt', 'dynamics', 'true_system', 'valid_time'\], "
        r"got \['valid_tme'\]",
    ):
        LSTMBaseline.load_from_checkpoint(tmp_path / "old.ckpt")
