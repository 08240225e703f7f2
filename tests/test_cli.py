"""The command line on the shipped configs: every CPU-sized twin fits a few batches and writes a checkpoint
and TensorBoard events; the encoder and UKF stages run on the result; every paper-size config
instantiates as written; stage configs share their SSM config's data section."""

from __future__ import annotations

import importlib.util
import io
import json
import logging
import math
import os
import re
import signal
import sys
from pathlib import Path

import lightning.pytorch as pl
import pytest
import torch
from lightning.pytorch.callbacks import Callback, ModelCheckpoint
from omegaconf import OmegaConf

from experiments.cli import reports
from experiments.configs import config_value, load_config
from experiments.registry import read_registry, stage_configs
from ssm_ms.baselines import BaselineForecaster
from ssm_ms.cli import main, show_package_log
from ssm_ms.control import ClosedLoop
from ssm_ms.module import MultipleShootingModule
from tests.conftest import RotationDataModule, fast_trainer, rotation_model

ROOT = Path(__file__).resolve().parents[1]
CPU = ROOT / "configs" / "cpu"
MNIST_ROOT = ROOT.parent / "shared" / "data"
FILES = "datamodules.files.FileDataModule"  # a user's files: no data_dir to redirect
SSM_CONFIGS = sorted(p for p in CPU.glob("*.yaml") if not p.stem.endswith(("_encoder", "_ukf", "_optimise")))
# make test fits one config of each data set and model; the variants that differ from one of those only in their data's
# length (the Lorenz T-sweep beside lorenz_T1000), and the baselines on a data set whose SSM configs are fitted already,
# run in make test-slow (~5 s each of make test's 10 minutes on the slowest CPUs)
SLOW_CPU_CONFIGS = {"lorenz_T10", "lorenz_T100", "lorenz_T10000", "quad_lstm", "quad_rkn"}


def cpu_params(configs: list[Path]) -> list:
    """``configs`` as test parameters named by their stems, those of :data:`SLOW_CPU_CONFIGS` marked slow."""
    return [pytest.param(p, id=p.stem, marks=[pytest.mark.slow] * (p.stem in SLOW_CPU_CONFIGS)) for p in configs]


TINY = {  # data overrides that make each data set a handful of short trajectories
    "pendulum": ["--data.init_args.n_train", "8", "--data.init_args.n_test", "4", "--data.init_args.workers", "1"],
    "quad": ["--data.init_args.n_train", "4", "--data.init_args.n_test", "2", "--data.init_args.workers", "1"],
    "lorenz": [
        "--data.init_args.n_train",
        "4",
        "--data.init_args.n_test",
        "4",
        "--data.init_args.train_steps",
        "10000",
    ],
    "mnist": ["--data.init_args.n_train", "8", "--data.init_args.n_test", "4", "--data.init_args.batch_size", "4"],
}


# The analysis of the Lorenz stages at a size for tests (the shipped configs compute it at full length).
# (the true system's exponents take ~15 s of Benettin QR at the shipped length on 2 cores)
CHEAP_TRUE_SYSTEM = '"true_system": {"runs": 2, "lyapunov_steps": 50, "transient": 10, "align": 10}'
CHEAP_ANALYSIS = [
    "--model.init_args.analysis",
    '{"valid_time": {"n_filter": 1000, "horizon": 1000}, '
    '"dynamics": {"runs": 2, "lyapunov_steps": 50, "transient": 10, "align": 10, "free_steps": 200}, '
    f"{CHEAP_TRUE_SYSTEM}}}",
]
# the pendulum's (its configs' Lyapunov spectrum and free runs are ~5 s a test stage)
CHEAP_PENDULUM_ANALYSIS = [
    "--model.init_args.analysis",
    '{"valid_time": {}, "dynamics": {"runs": 2, "lyapunov_steps": 50, "transient": 10, "align": 10, "free_steps": 100}}',
]
# a baseline has no f to study: the valid time, in Lyapunov times of the true system
CHEAP_BASELINE_ANALYSIS = [
    "--model.init_args.analysis",
    f'{{"valid_time": {{"n_filter": 1000, "horizon": 1000}}, {CHEAP_TRUE_SYSTEM}}}',
]


def family(name: str) -> str:
    return next(k for k in TINY if name.startswith(k))


def run(tmp: Path, subcommand: str, config: Path, *extra: str):
    args = [
        subcommand,
        "--config",
        str(config),
        "--trainer.logger.init_args.save_dir",
        str(tmp / "runs"),
        "--trainer.logger.init_args.version",
        "t",
        "--trainer.enable_progress_bar",
        "false",
        "--trainer.enable_model_summary",
        "false",
    ]
    if "--data.init_args.data_dir" not in extra and load_config(config)["data"]["class_path"] != FILES:
        args += ["--data.init_args.data_dir", str(tmp / "data")]
    with reports():  # the results files' reports, as `python cli.py` renders them
        return main(args + list(extra))


def fit_tiny(tmp: Path, config: Path, *extra: str):
    return run(
        tmp,
        "fit",
        config,
        "--trainer.max_epochs",
        "1",
        "--trainer.limit_train_batches",
        "2",
        "--trainer.limit_val_batches",
        "1",
        "--trainer.check_val_every_n_epoch",
        "1",
        *TINY[family(config.stem)],
        *extra,
    )


def outputs(tmp: Path, config: Path) -> Path:
    name = load_config(config)["trainer"]["logger"]["init_args"]["name"]
    return tmp / "runs" / name / "t"


@pytest.mark.parametrize("config", cpu_params(SSM_CONFIGS))
def test_cpu_config_fits_and_writes_checkpoint_and_events(tmp_path, config):
    if family(config.stem) == "mnist" and not MNIST_ROOT.is_dir():
        pytest.skip(f"real MNIST files not found at {MNIST_ROOT}")
    fit_tiny(tmp_path, config)
    out = outputs(tmp_path, config)
    assert (out / "checkpoints" / "last.ckpt").is_file()
    assert list(out.glob("events.out.tfevents.*"))
    assert (out / "config.yaml").is_file()
    # a CLI-built SSM reloads from its checkpoint alone (f and g rebuilt from the saved config)
    model = MultipleShootingModule.load_from_checkpoint(out / "checkpoints" / "last.ckpt")
    saved = torch.load(out / "checkpoints" / "last.ckpt", weights_only=False)
    assert "networks" not in saved  # the config, not a pickle, describes f and g
    for key, value in saved["state_dict"].items():
        torch.testing.assert_close(model.state_dict()[key], value)


@pytest.fixture(scope="module")
def pendulum_ssm(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("pend")
    config = CPU / "pendulum.yaml"
    fit_tiny(tmp, config)
    return tmp, outputs(tmp, config) / "checkpoints" / "last.ckpt"


def test_encoder_stage_and_test_protocol_from_the_cli(pendulum_ssm):
    tmp, ssm_ckpt = pendulum_ssm
    config = CPU / "pendulum_encoder.yaml"
    stage = [
        "--model.init_args.ssm_checkpoint",
        str(ssm_ckpt),
        "--model.init_args.results_dir",
        str(tmp / "results"),
        "--model.init_args.figures_dir",
        str(tmp / "figures"),
        *TINY["pendulum"],
        *CHEAP_PENDULUM_ANALYSIS,
    ]
    run(
        tmp,
        "fit",
        config,
        "--trainer.max_epochs",
        "1",
        "--trainer.limit_train_batches",
        "2",
        "--trainer.limit_val_batches",
        "1",
        *stage,
    )
    enc_ckpt = outputs(tmp, config) / "checkpoints" / "last.ckpt"
    assert enc_ckpt.is_file()
    # the SSM's checkpoint need not be given again: --ckpt_path's recorded one is used
    run(tmp, "test", config, "--ckpt_path", str(enc_ckpt), *stage[2:])
    report = (tmp / "results" / "pendulum_cpu.md").read_text()
    assert "| SSM-LL + CNN-LSTM encoder |" in report  # and the paper's SSM-LL row of Table 1 beside it:
    assert "| SSM-LL | 0.2895 ± 0.0064 | 0.0152 ± 0.0022 |" in report
    assert (tmp / "figures" / "pendulum_cpu_encoder_mosaic.png").is_file()
    assert (tmp / "figures" / "pendulum_cpu_encoder.gif").is_file()
    # scored again with another metric into another folder: the command's reporting settings win over the
    # checkpoint's, the model is the same (the same MSE), the first results stay as they were
    again = ["--model.init_args.results_dir", str(tmp / "rescored"), "--model.init_args.metrics", "[mse, bce, ssim]"]
    run(tmp, "test", config, "--ckpt_path", str(enc_ckpt), *stage[2:], *again)
    first = json.loads((tmp / "results" / "pendulum_cpu.json").read_text())["runs"]["encoder"]["summary"]
    second = json.loads((tmp / "rescored" / "pendulum_cpu.json").read_text())["runs"]["encoder"]["summary"]
    assert "encoder/noisy/ssim" in second and "encoder/noisy/ssim" not in first
    assert second["encoder/noisy/mse"] == first["encoder/noisy/mse"]
    assert (tmp / "results" / "pendulum_cpu.md").read_text() == report
    # a config file's reporting values do not count (they are the repository's results/): the checkpoint's folder
    # stays, the metric given on the command line applies
    committed = ROOT / "results" / "pendulum_cpu.json"
    before = committed.read_bytes() if committed.exists() else None
    run(tmp, "test", config, "--ckpt_path", str(enc_ckpt), *TINY["pendulum"], again[2], "[mse, ssim]")
    third = json.loads((tmp / "results" / "pendulum_cpu.json").read_text())["runs"]["encoder"]["summary"]
    assert "encoder/noisy/ssim" in third and "encoder/noisy/bce" not in third
    assert (committed.read_bytes() if committed.exists() else None) == before


def test_ukf_stage_from_the_cli(tmp_path):
    ssm = CPU / "lorenz_T1000.yaml"
    fit_tiny(tmp_path, ssm)
    ssm_ckpt = outputs(tmp_path, ssm) / "checkpoints" / "last.ckpt"
    test = [
        "test",
        CPU / "lorenz_T1000_ukf.yaml",
        "--model.init_args.ssm_checkpoint",
        str(ssm_ckpt),
        "--model.init_args.results_dir",
        str(tmp_path / "results"),
        "--model.init_args.figures_dir",
        str(tmp_path / "figures"),
        "--trainer.limit_test_batches",
        "1",
        *TINY["lorenz"],
        *CHEAP_ANALYSIS,
    ]
    cli = run(tmp_path, *test)
    # the SSM loaded inside the CLI-built forecaster keeps its own hyperparameters, not the forecaster's
    assert cli.model.ssm.hparams["node_init_map"] == {0: 0} and "n_filter" not in cli.model.ssm.hparams
    saved = json.loads((tmp_path / "results" / "lorenz_T1000_cpu.json").read_text())["runs"]["ukf"]
    assert "ukf/clean/mse" in saved["summary"]
    # the analysis ran with the settings given on the command line, and the true system's exponents were cached
    assert (
        saved["analysis"]["dynamics"]["lyapunov"]["steps"] == 50 and saved["analysis"]["valid_time"]["horizon"] == 1000
    )
    assert saved["analysis"]["true_system"]["largest"] > 0
    assert list((tmp_path / "data").glob("lorenz-*/true_exponents_*.json"))
    assert (tmp_path / "figures" / "lorenz_T1000_cpu_ukf_lorenz_prediction.png").is_file()
    # the figures of f alone are the experiment's SSM's; a method with a name of its own (another SSM of the
    # experiment, as quad's `encoder_ssm1000`) writes its own and leaves the experiment's as they were
    shared = tmp_path / "figures" / "lorenz_T1000_cpu_attractor.png"
    written = shared.stat().st_mtime_ns
    run(tmp_path, *test, "--model.init_args.method_name", "ukf_other")
    assert (tmp_path / "figures" / "lorenz_T1000_cpu_ukf_other_attractor.png").is_file()
    assert shared.stat().st_mtime_ns == written
    runs = json.loads((tmp_path / "results" / "lorenz_T1000_cpu.json").read_text())["runs"]
    assert (runs["ukf"]["info"]["label"], runs["ukf_other"]["info"]["label"]) == (
        "SSM-LL + UKF",
        "SSM-LL + UKF (ukf_other)",
    )


# The Lorenz T-sweep's baselines (T = 10, 100, 10,000) differ from lorenz_T1000's only in the data's piece length,
# the training split and (T = 10,000 on CPU) the epochs: they are checked by test_lorenz_sweep_baselines_split_their_pieces
# and test_cpu_lorenz_baselines_see_as_many_measurements_for_every_t, not trained here (~25 s each).
SWEEP_BASELINES = ("lorenz_T10_", "lorenz_T100_", "lorenz_T10000_")
BASELINE_CONFIGS = sorted(p for p in (CPU / "baselines").glob("*.yaml") if not p.stem.startswith(SWEEP_BASELINES))


@pytest.fixture(scope="module")
def baseline_lorenz_data(tmp_path_factory) -> Path:
    """One data folder for the Lorenz baselines' tests: the data (and the true system's exponents, cached beside
    them) are made once for both."""
    return tmp_path_factory.mktemp("lorenz_data")


@pytest.mark.parametrize("config", cpu_params(BASELINE_CONFIGS))
def test_cpu_baseline_config_fits_and_tests(tmp_path, config, baseline_lorenz_data):
    """Each CPU-sized baseline trains a few batches, then the test protocol writes its row beside the paper's."""
    extra = [
        *TINY[family(config.stem)],
        "--model.init_args.results_dir",
        str(tmp_path / "results"),
        "--model.init_args.figures_dir",
        str(tmp_path / "figures"),
    ]
    if family(config.stem) == "lorenz":  # 1000-step test forecasts on two sequences are enough here
        extra += [
            "--data.init_args.n_test",
            "2",
            *CHEAP_BASELINE_ANALYSIS,
            "--data.init_args.data_dir",
            str(baseline_lorenz_data),
        ]
    run(
        tmp_path,
        "fit",
        config,
        "--trainer.max_epochs",
        "1",
        "--trainer.limit_train_batches",
        "2",
        "--trainer.limit_val_batches",
        "1",
        *extra,
    )
    ckpt = outputs(tmp_path, config) / "checkpoints" / "last.ckpt"
    run(tmp_path, "test", config, "--ckpt_path", str(ckpt), "--trainer.limit_test_batches", "1", *extra)
    model = "LSTM" if config.stem.endswith("lstm") else "RKN"
    experiment = load_config(config)["model"]["init_args"]["experiment"]
    report = (tmp_path / "results" / f"{experiment}.md").read_text()
    assert f"| {model} |" in report and f"| {model} | " in report.split("## The paper")[1]
    assert "Valid prediction time" in report
    assert list((tmp_path / "figures").glob(f"{experiment}_{model.lower()}_*"))


@pytest.mark.parametrize(
    "config",
    sorted(
        p
        for folder in (CPU, ROOT / "configs")
        for p in (folder / "baselines").glob("lorenz_T10*_*.yaml")
        if p.stem.startswith(SWEEP_BASELINES)
    ),
    ids=lambda p: str(p.relative_to(ROOT)),
)
def test_lorenz_sweep_baselines_split_their_pieces(config, tmp_path):
    """Pieces of T = 10 steps cannot hold the protocol's 10 predicted steps: 5 given, 5 predicted; pieces of 100 are
    trained whole, 90 given and 10 predicted; pieces of 10,000 whole at the paper's size, in 200-step windows (190
    given) on CPU, as lorenz_T1000's CPU twin (the test protocol is the same for every T)."""
    cli = main(["--config", str(config), "--trainer.logger.init_args.save_dir", str(tmp_path)], run=False)
    piece = load_config(config)["data"]["init_args"]["piece_length"]
    cpu = config.parent.parent == CPU
    window, given = {10: (None, 5), 100: (None, 90), 10000: (200, 190) if cpu else (None, 9990)}[piece]
    assert cli.model.train_window == window
    assert cli.model.training_split(window or piece) == given
    assert (cli.model.n_filter, cli.model.n_predict) == (1990, 10)


def test_cpu_lorenz_baselines_see_as_many_measurements_for_every_t():
    """The CPU twins' baselines for T = 1000 and 10,000 train on 200-step windows; the T = 10,000 data hold 4 pieces a
    step (the SSM's batch) where T = 1000's hold 40, so its epochs are 10x: the same steps x windowed measurements."""

    def seen(stem: str) -> int:
        cfg = OmegaConf.create(load_config(CPU / "baselines" / f"{stem}.yaml"))
        data = cfg.data.init_args
        steps_per_epoch = math.ceil(data.n_train * data.train_steps / data.piece_length / data.batch_size)
        return cfg.trainer.max_epochs * steps_per_epoch * data.batch_size * cfg.model.init_args.train_window

    for model in ("lstm", "rkn"):
        assert seen(f"lorenz_T10000_{model}") == seen(f"lorenz_T1000_{model}")


def oscillator_file(tmp: Path) -> Path:
    """The README's worked example: data written by examples/make_oscillator_data.py."""
    spec = importlib.util.spec_from_file_location("make_osc", ROOT / "examples" / "make_oscillator_data.py")
    make_osc = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(make_osc)
    path = tmp / "osc.npz"
    make_osc.main(["--out", str(path), "--n", "16"])
    return path


def test_own_data_example_config(tmp_path):
    path = oscillator_file(tmp_path)
    config = ROOT / "configs" / "oscillator.yaml"
    run(
        tmp_path,
        "fit",
        config,
        "--trainer.max_epochs",
        "1",
        "--trainer.limit_train_batches",
        "2",
        "--trainer.limit_val_batches",
        "1",
        "--data.init_args.train_path",
        str(path),
    )
    assert (outputs(tmp_path, config) / "checkpoints" / "last.ckpt").is_file()


PAPER_CONFIGS = sorted(p for p in (ROOT / "configs").glob("*.yaml") if p.name != "experiments.yaml") + sorted(
    (ROOT / "configs" / "baselines").glob("*.yaml")
)  # every config at the paper's size; configs/experiments.yaml is the registry that names them


STAGE_OF = {
    ROOT / path: kind
    for sizes in read_registry()["experiments"].values()
    for stages in sizes.values()
    for kind, path in stage_configs(stages)
}  # each config's stage, as the registry names it


@pytest.mark.parametrize("config", PAPER_CONFIGS, ids=[p.stem for p in PAPER_CONFIGS])
def test_paper_configs_parse_and_instantiate(tmp_path, config):
    stage = STAGE_OF[config]
    if stage in ("encoder", "ukf", "optimise") or (
        stage == "control" and not config_value(config, "model.init_args.true_model")
    ):
        pytest.skip("stage configs need a trained SSM checkpoint (covered above on CPU twins, and in test_control)")
    if stage == "record" or "_dagger" in config.stem:
        pytest.skip("recording needs a trained SSM, training on recordings needs them (both in test_control)")
    extra = ["--data.init_args.train_path", str(oscillator_file(tmp_path))] if config.stem == "oscillator" else []
    cli = main(["--config", str(config), "--trainer.logger.init_args.save_dir", str(tmp_path), *extra], run=False)
    kind = BaselineForecaster if stage == "baselines" else MultipleShootingModule
    assert isinstance(cli.model, ClosedLoop if stage == "control" else kind)
    assert cli.datamodule.num_train_trajectories > 0


def data_section(config: Path) -> dict:
    """The data section a config composes to (a stage's and its SSM's are the same file, or the same values), less
    ``val_trajectories``: which training sequences validate (an encoder may hold more out) is not what the data are."""
    section = load_config(config)["data"]
    return {**section, "init_args": {k: v for k, v in section["init_args"].items() if k != "val_trajectories"}}


@pytest.mark.parametrize("folder", ["configs", "configs/cpu"])
def test_stage_configs_use_their_ssm_data(folder):
    stages = [p for kind in ("encoder", "ukf", "optimise") for p in sorted((ROOT / folder).glob(f"*_{kind}.yaml"))]
    baselines = sorted((ROOT / folder / "baselines").glob("*.yaml"))
    assert stages and baselines
    ssm_data: dict[Path, dict] = {}  # each SSM config read once (a read costs ~0.3 s)
    for stage in stages + baselines:
        ssm = (ROOT / folder / stage.stem.rsplit("_", 1)[0]).with_suffix(".yaml")
        if ssm not in ssm_data:
            ssm_data[ssm] = data_section(ssm)
        assert data_section(stage) == ssm_data[ssm], f"{stage.name} and {ssm.name} differ in their data section"


# ---------------------------------------------------------------------------- checkpoints, Ctrl-C, overrides
ROTATION = """\
seed_everything: 0
trainer:
  max_epochs: 4
  accelerator: cpu
  check_val_every_n_epoch: 10     # validates rarely: checkpoints must not wait for it
  enable_progress_bar: false
  enable_model_summary: false
  num_sanity_val_steps: 0
  deterministic: true
  logger:
    class_path: lightning.pytorch.loggers.TensorBoardLogger
    init_args: {{save_dir: {root}/runs, name: rot}}
model:
  class_path: ssm_ms.module.MultipleShootingModule
  init_args:
    state_dim: 2
    n_nodes: 3
    lr: 0.01
    schedule:
      class_path: ssm_ms.schedule.ShootingSchedule
      init_args: {{alpha: 50.0, alpha_epoch: 2, lr_milestones: [2], lr_factor: 0.1}}
    f:
      class_path: ssm_ms.nets.LocallyLinearTransition
      init_args: {{state_dim: "${{model.init_args.state_dim}}", n_matrices: 4, hidden: 16}}
    g:
      class_path: ssm_ms.nets.Projection
      init_args: {{indices: [0]}}
data:
  class_path: tests.conftest.RotationDataModule
  init_args: {{data_dir: {root}/data, batch_size: 3, val_trajectories: 2}}
"""


class StopAt(Callback):
    """Ctrl-C (KeyboardInterrupt, as SIGINT raises it), a real SIGTERM to this process, or a diverging f (NaN
    parameters) in the middle of an epoch."""

    def __init__(self, epoch: int, how: str = "interrupt"):
        self.epoch, self.how = epoch, how

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if trainer.current_epoch == self.epoch and batch_idx == 1:
            if self.how == "interrupt":
                raise KeyboardInterrupt
            if self.how == "sigterm":  # what `kill <pid>` sends; Lightning's handler stops after this batch
                os.kill(os.getpid(), signal.SIGTERM)
                return
            with torch.no_grad():
                for p in pl_module.f.parameters():
                    p.fill_(float("nan"))


class Saves(Callback):
    """The epoch of last.ckpt as it is on disk at the start of every epoch."""

    def __init__(self):
        self.seen = {}

    def on_train_epoch_start(self, trainer, pl_module):
        path = Path(trainer.log_dir) / "checkpoints" / "last.ckpt"
        self.seen[trainer.current_epoch] = torch.load(path, weights_only=True)["epoch"] if path.is_file() else None


@pytest.fixture
def rotation(tmp_path):
    (tmp_path / "rot.yaml").write_text(ROTATION.format(root=tmp_path))
    return tmp_path, ["fit", "--config", str(tmp_path / "rot.yaml")]


def last_ckpt(root: Path, version: str) -> Path:
    return root / "runs" / "rot" / version / "checkpoints" / "last.ckpt"


def test_checkpoint_every_epoch_with_rare_validation(rotation):
    root, fit = rotation
    cli = main([*fit, "--trainer.logger.init_args.version", "a", "--trainer.callbacks+=tests.test_cli.Saves"])
    saves = next(c for c in cli.trainer.callbacks if isinstance(c, Saves))
    assert saves.seen == {0: None, 1: 0, 2: 1, 3: 2}  # last.ckpt holds the previous epoch at every epoch start
    assert torch.load(last_ckpt(root, "a"), weights_only=True)["epoch"] == 3


def test_a_fit_checkpoints_every_epoch_unless_told_otherwise(rotation):
    """The rotation config names no EpochCheckpoint: the CLI adds one to a fit (a crash loses at most the epoch under
    way; the test above sees it write every epoch); a config's own is kept with its options, not doubled;
    ``enable_checkpointing: false`` writes none."""
    from ssm_ms.checkpointing import EpochCheckpoint

    root, fit = rotation

    def savers(version: str, *extra: str) -> list:
        cli = main([*fit, "--trainer.max_epochs", "1", "--trainer.logger.init_args.version", version, *extra])
        return [c for c in cli.trainer.callbacks if isinstance(c, ModelCheckpoint)]

    (added,) = savers("added")
    assert type(added) is EpochCheckpoint and added.every_n_epochs == 1
    assert torch.load(last_ckpt(root, "added"), weights_only=True)["epoch"] == 0
    (own,) = savers(
        "own", "--trainer.callbacks+=ssm_ms.checkpointing.EpochCheckpoint", "--trainer.callbacks.every_n_epochs=3"
    )
    assert own.every_n_epochs == 3
    assert savers("none", "--trainer.enable_checkpointing", "false") == []
    assert not (root / "runs" / "rot" / "none" / "checkpoints").exists()


def test_a_second_model_checkpoint_keeps_its_epochs_beside_the_house_one(rotation):
    """A ModelCheckpoint keeping every epoch beside the house's EpochCheckpoint (whose top-1 file is replaced every
    epoch) loses none of them, under Lightning's default name too (where the names meet, the second writer's file
    gets Lightning's ``-v1``), and under a name of its own they are told apart at a glance (docs/cli.md)."""
    root, fit = rotation
    keep = [
        "--trainer.callbacks+=lightning.pytorch.callbacks.ModelCheckpoint",
        "--trainer.callbacks.save_top_k=-1",
        "--trainer.callbacks.save_on_train_epoch_end=true",  # this config validates every 10 epochs
    ]
    for version, name in (("default", []), ("own", ["--trainer.callbacks.filename=keep-{epoch}"])):
        main([*fit, "--trainer.max_epochs", "3", "--trainer.logger.init_args.version", version, *keep, *name])
        files = sorted(p.name for p in (root / "runs" / "rot" / version / "checkpoints").iterdir())
        epochs = sorted(int(re.match(r"(?:keep-)?epoch=(\d+)", f)[1]) for f in files if f != "last.ckpt")
        assert epochs == [0, 1, 2, 2], files  # the kept three and the house's last epoch
        assert "last.ckpt" in files
    assert [f for f in files if f.startswith("keep-")] == [
        "keep-epoch=0.ckpt",
        "keep-epoch=1.ckpt",
        "keep-epoch=2.ckpt",
    ]


def test_configs_state_the_schedule_on_the_model_and_twins_change_only_what_differs():
    """The CPU twin of the pendulum states its two milestones and keeps the paper config's alpha and factor (that no
    config lists the schedule among the trainer's callbacks: tests/test_configs.py)."""
    paper = load_config(ROOT / "configs/pendulum.yaml")["model"]["init_args"]["schedule"]["init_args"]
    twin = load_config(ROOT / "configs/cpu/pendulum.yaml")["model"]["init_args"]["schedule"]["init_args"]
    assert (paper["alpha_epoch"], paper["lr_milestones"]) == (200, [200, 600])
    assert (twin["alpha_epoch"], twin["lr_milestones"]) == (110, [110, 150])
    assert twin["alpha"] == paper["alpha"] == 1000.0 and twin["lr_factor"] == paper["lr_factor"] == 0.1
    # the callbacks too come from the paper config, one list (their cadence follows the run's length)
    for twin_file in sorted((ROOT / "configs/cpu").glob("*.yaml")):
        assert "ReconstructionLogger" not in twin_file.read_text(), twin_file
    assert load_config(ROOT / "configs/cpu/pendulum.yaml")["trainer"]["callbacks"] == [
        {
            "class_path": "ssm_ms.viz.ReconstructionLogger",
            "init_args": {"every_n_epochs": None, "max_trajectories": 4, "max_frames": 10},
        }
    ]


def test_a_section_file_changed_by_dotted_keys_in_the_same_file_is_refused(tmp_path, capsys):
    """jsonargparse would drop ``model: parts/amortised.yaml`` for the base's model with the dotted key applied (an
    SSM-LL of 8 nodes in place of the amortised model); one message names the fix instead, and the same key one
    include later composes the part's model."""
    bench = ROOT / "configs" / "benchmarks"
    bad = tmp_path / "bad.yaml"
    bad.write_text(
        f"config: {bench / 'cascaded_tanks.yaml'}\nmodel: {bench / 'parts' / 'amortised.yaml'}\nmodel.init_args.lr: 0.001\n"
    )
    with pytest.raises(SystemExit) as stop:
        main(["fit", "--config", str(bad), "--print_config"])
    err = capsys.readouterr().err
    assert stop.value.code != 0 and "Traceback" not in err
    assert "model.init_args.lr" in err and "config that includes this one" in err
    with pytest.raises(ValueError, match="in one file"):
        load_config(bad)
    good = tmp_path / "good.yaml"
    good.write_text(f"config: {bench / 'cascaded_tanks_amortised.yaml'}\nmodel.init_args.lr: 0.001\n")
    model = load_config(good)["model"]["init_args"]
    assert (model["lr"], model["n_nodes"], model["state_dim"]) == (0.001, 1, 10) and model["node_encoder"]


def test_nan_stop_names_the_last_good_epoch(rotation, capsys):
    root, fit = rotation
    with pytest.raises(SystemExit) as stop:
        main(
            [
                *fit,
                "--trainer.logger.init_args.version",
                "n",
                "--trainer.callbacks+=tests.test_cli.StopAt",
                "--trainer.callbacks.epoch=2",
                "--trainer.callbacks.how=nan",
            ]
        )
    err = capsys.readouterr().err
    assert stop.value.code == 1 and "Traceback" not in err
    assert "not finite at epoch 2" in err and f"the last good checkpoint is {last_ckpt(root, 'n')}" in err
    saved = torch.load(last_ckpt(root, "n"), weights_only=True)
    assert saved["epoch"] == 1 and all(torch.isfinite(v).all() for v in saved["state_dict"].values())


@pytest.mark.parametrize("how", ["interrupt", "sigterm"])
def test_ctrl_c_or_sigterm_then_resume_equals_an_uninterrupted_run(rotation, capsys, how):
    root, fit = rotation
    sigterm = signal.getsignal(signal.SIGTERM)
    main([*fit, "--trainer.logger.init_args.version", "full"])
    interrupted = [
        *fit,
        "--trainer.logger.init_args.version",
        "cut",
        "--trainer.callbacks+=tests.test_cli.StopAt",
        "--trainer.callbacks.epoch=2",
        f"--trainer.callbacks.how={how}",
    ]
    with pytest.raises(SystemExit) as stop:
        main(interrupted)
    err = capsys.readouterr().err
    assert stop.value.code == 130 and "Traceback" not in err
    ckpt = last_ckpt(root, "cut")
    assert torch.load(ckpt, weights_only=True)["epoch"] == 1  # the last completed epoch, not the half one
    command = err.split("Resume with:")[1].strip()
    assert command == "python cli.py " + " ".join(interrupted) + f" --ckpt_path {ckpt}"
    assert signal.getsignal(signal.SIGTERM) == sigterm  # the process's own SIGTERM handling is back
    main([*fit, "--trainer.logger.init_args.version", "cut", "--ckpt_path", str(ckpt)])  # the command, less the Ctrl-C
    full = torch.load(last_ckpt(root, "full"), weights_only=True)
    resumed = torch.load(ckpt, weights_only=True)
    assert resumed["epoch"] == full["epoch"] == 3 and resumed["global_step"] == full["global_step"]
    for key, value in full["state_dict"].items():
        torch.testing.assert_close(resumed["state_dict"][key], value, rtol=0, atol=0)


def test_state_dim_override_reaches_f_and_print_config(rotation, capsys):
    root, fit = rotation
    with pytest.raises(SystemExit):
        main([*fit, "--model.init_args.state_dim", "5", "--print_config"])
    printed = OmegaConf.create(capsys.readouterr().out).model.init_args
    assert printed.state_dim == 5 and printed.f.init_args.state_dim == 5
    cli = main(
        [
            *fit,
            "--model.init_args.state_dim",
            "5",
            "--trainer.max_epochs",
            "1",
            "--trainer.logger.init_args.version",
            "d5",
        ]
    )
    assert cli.model.f.matrices.shape[-1] == 5 and cli.model.nodes.weight.shape[1] == 3 * 5
    # that in every shipped config the command line's state_dim reaches f and g: tests/test_configs.py


def test_cli_model_reloads_in_python_with_its_config(rotation):
    root, fit = rotation
    cli = main([*fit, "--trainer.max_epochs", "1", "--trainer.logger.init_args.version", "r"])
    model = MultipleShootingModule.load_from_checkpoint(last_ckpt(root, "r"))
    assert model.hparams["f"] == {
        "class_path": "ssm_ms.nets.LocallyLinearTransition",
        "init_args": {"state_dim": 2, "n_matrices": 4, "hidden": 16, "input_dim": 0},
    }
    assert model.hparams["g"]["class_path"] == "ssm_ms.nets.Projection"
    x0 = torch.randn(5, 2)
    trained = cli.model.cpu().eval()
    with torch.no_grad():
        for a, b in zip(model(x0, 7), trained(x0, 7)):
            torch.testing.assert_close(a, b, rtol=0, atol=0)
    # saved again, it still describes f and g by their config (no pickled networks)
    trainer = pl.Trainer(logger=False, enable_checkpointing=False, enable_progress_bar=False)
    trainer.strategy.connect(model)
    trainer.save_checkpoint(root / "again.ckpt")
    again = torch.load(root / "again.ckpt", weights_only=True)
    assert "networks" not in again and again["hyper_parameters"]["f"] == model.hparams["f"]


EXAMPLE_CONFIGS = sorted((ROOT / "configs" / "examples").glob("*.yaml"))


@pytest.mark.parametrize("config", EXAMPLE_CONFIGS, ids=[p.stem for p in EXAMPLE_CONFIGS])
def test_example_configs_layer_on_an_ssm_config(tmp_path, config):
    """configs/examples/*.yaml, added after a CPU config as the README shows, parse and set what they say."""
    cli = main(
        [
            "--config",
            str(CPU / "pendulum.yaml"),
            "--config",
            str(config),
            "--trainer.accelerator",
            "cpu",
            "--trainer.logger.init_args.save_dir",
            str(tmp_path),
        ],
        run=False,
    )  # ddp.yaml asks for GPUs
    wanted = OmegaConf.to_container(OmegaConf.load(config)).get("model", {}).get("init_args", {})
    assert wanted
    for key, value in wanted.items():
        assert cli.model.hparams[key] == value, key


def test_the_package_log_goes_to_the_stderr_of_the_moment(monkeypatch):
    """Lines logged after stderr was redirected (and the first one closed: pytest's capture of an earlier test) go
    to the new stderr, not to the closed stream with a 'Logging error' traceback."""
    log = logging.getLogger("ssm_ms")
    monkeypatch.setattr(log, "handlers", [])
    first, second = io.StringIO(), io.StringIO()
    monkeypatch.setattr(sys, "stderr", first)
    show_package_log()
    log.info("one")
    first.close()
    monkeypatch.setattr(sys, "stderr", second)
    log.info("two")
    assert second.getvalue() == "two\n"


def test_a_fit_shows_the_epochs_and_time_to_go(tmp_path):
    """The bar in place of Lightning's (none named, bar not disabled) says ``Epoch e/max``, then from the second
    epoch on the time left at the pace of the last epochs, their median: a clock advancing 60 s per epoch but 480 s
    across epoch 2 (the process paused), 6 epochs, a window of three."""
    from ssm_ms.progress import RunProgressBar, duration

    bar = RunProgressBar(window=3, mode="bar")  # pytest captures stdout: "auto" would write lines
    ticks = iter([0, 60, 120, 600, 660, 720])  # each epoch's start: epoch 2 took 480 s
    bar._clock = lambda: next(ticks)
    seen = []

    class Read(pl.Callback):
        def on_train_epoch_start(self, trainer, pl_module):
            seen.append(bar.train_progress_bar.desc)

    fast_trainer(tmp_path, max_epochs=6, callbacks=[bar, Read()], enable_progress_bar=True).fit(
        rotation_model(), RotationDataModule(data_dir=str(tmp_path / "data"), batch_size=4, val_trajectories=2)
    )
    # durations: 60, 60, 480, 60, 60; the pace at each start is the median of the last three of those known
    assert [d.rstrip(": ") for d in seen] == [
        "Epoch 0/6",
        "Epoch 1/6, ~5 min to go",  # 60 s x 5
        "Epoch 2/6, ~4 min to go",  # median(60, 60) x 4
        "Epoch 3/6, ~3 min to go",  # median(60, 60, 480) x 3 (a mean: 200 s x 3 = 10 min)
        "Epoch 4/6, ~2 min to go",  # median(60, 480, 60) x 2
        "Epoch 5/6, ~60 s to go",  # median(480, 60, 60) x 1
    ]
    assert [duration(s) for s in (1.4, 45, 720, 14040, 216000)] == ["1.4 s", "45 s", "12 min", "3.9 h", "2.5 days"]
    cli = main(["--config", str(ROOT / "configs" / "cpu" / "pendulum.yaml"), "--trainer.logger", "false"], run=False)
    assert sum(isinstance(c, RunProgressBar) for c in cli.trainer.callbacks) == 1
    quiet = ["--trainer.enable_progress_bar", "false"]
    cli = main(
        ["--config", str(ROOT / "configs" / "cpu" / "pendulum.yaml"), "--trainer.logger", "false", *quiet], run=False
    )
    assert cli.trainer.progress_bar_callback is None


def test_a_batch_limit_given_as_an_int_counts_batches(tmp_path, monkeypatch):
    """``--trainer.limit_train_batches 1`` trains one batch an epoch and ``1.0`` all of them (Lightning: an int counts,
    a float is a fraction). The parser of ``python cli.py`` once read the int 1 as 1.0 (a union's order, set by what
    the process imported first: in this test process it came out right, so the int runs as a user runs it, in a
    process of its own; the float in this one). Steps read from the int's checkpoint and the float's trainer; the
    epoch's batches from the data loader itself: 4 trajectories of 10,000 steps in pieces of 100, 40 a batch."""
    import subprocess

    config = CPU / "lorenz_T100.yaml"
    common = [*TINY["lorenz"], "--data.init_args.batch_size", "40", "--data.init_args.data_dir", str(tmp_path / "data")]
    common += [
        "--trainer.enable_progress_bar",
        "false",
        "--trainer.max_epochs",
        "1",
        "--trainer.limit_val_batches",
        "0",
    ]
    steps = {}
    command = [sys.executable, str(ROOT / "cli.py"), "fit", "--config", str(config), *common]
    command += ["--trainer.logger.init_args.save_dir", str(tmp_path / "1"), "--trainer.limit_train_batches", "1"]
    proc = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    (ckpt,) = (tmp_path / "1").glob("*/*/checkpoints/last.ckpt")
    steps["1"] = torch.load(ckpt, map_location="cpu", weights_only=False)["global_step"]
    monkeypatch.chdir(tmp_path)  # the fit's config.yaml is written where it runs
    cli = main(["fit", "--config", str(config), *common, "--trainer.logger", "false", "--trainer.limit_train_batches",
                "1.0", "--trainer.enable_checkpointing", "false"])  # fmt: skip
    steps["1.0"] = cli.trainer.global_step
    whole = len(cli.datamodule.train_dataloader())
    assert whole > 1
    assert steps == {"1": 1, "1.0": whole}
