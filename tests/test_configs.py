"""The shipped configs, read as ``cli.py`` reads them (:func:`ssm_ms.cli.config_parser`, which
:func:`experiments.configs.load_config` uses): every one parses and checks, overlays compose as docs/cli.md says, and what
``make reproduce`` reads of them (where a stage logs, its experiment, its results folder) is what the parser gives."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from experiments.configs import config_value, experiment_name, load_config, logger_dir
from experiments.registry import read_registry
from ssm_ms.cli import config_parser, main

ROOT = Path(__file__).resolve().parents[1]
# every runnable config: not the shared sections (configs/data/, configs/cpu/data/, configs/benchmarks/parts/), not
# the examples added after one, not the experiment registry (configs/experiments.yaml)
CONFIGS = sorted(
    p
    for p in (ROOT / "configs").rglob("*.yaml")
    if p.parent.name not in ("data", "examples", "parts") and p != ROOT / "configs" / "experiments.yaml"
)


# the stages the registry runs on a trained SSM's checkpoint (an encoder, the UKF, fitted states), read once: a read
# of the registry costs ~0.1 s, once per config it was ~20 s of the suite
STAGES = {
    stages[kind]
    for sizes in read_registry()["experiments"].values()
    for stages in sizes.values()
    for kind in ("encoder", "ukf", "optimise")
    if kind in stages
}


def is_stage(config: Path) -> bool:
    """A stage config (:data:`STAGES`); a test's own config, outside the repository, is not."""
    return config.is_relative_to(ROOT) and str(config.relative_to(ROOT)) in STAGES


@pytest.fixture(scope="module")
def resolve():
    """``config -> dict``: the config as ``python cli.py fit --config <config> --print_config`` prints it, checked
    (a stage config gets the SSM checkpoint it needs, not read)."""
    parser = config_parser()

    def parse(config: Path) -> dict:
        extra = ["--model.init_args.ssm_checkpoint", "x.ckpt"] if is_stage(config) else []
        namespace = parser.parse_args(["--config", str(config), *extra])
        return yaml.safe_load(parser.dump(namespace, skip_unset=False))  # as --print_config dumps it

    return parse


@pytest.mark.parametrize("config", CONFIGS, ids=lambda p: str(p.relative_to(ROOT / "configs")))
def test_every_config_parses_and_reproduce_reads_its_folders(config, resolve):
    """Each shipped config parses and checks; what ``make reproduce`` reads of it is what the parser gives; its
    trainer's callbacks and its ``state_dim`` are as the house wants them. (Every check of every config is here: a
    config read costs ~0.3 s on these CPUs, so the suite reads each file as few times as it can.)"""
    resolved = resolve(config)  # parses and checks (the parser's error names the problem otherwise)
    loaded = load_config(config)  # as make reproduce reads it
    assert {"trainer", "model", "data"} <= set(loaded) and "config" not in loaded
    # what make reproduce reads: where the stage logs, and the experiment and folder its results go to
    logger = resolved["trainer"]["logger"]["init_args"]
    assert logger_dir(loaded) == Path(logger["save_dir"]) / logger["name"]  # (given the file: this same read)
    model = resolved["model"]["init_args"]
    assert experiment_name(config, loaded) == (model.get("experiment") or config.stem)
    assert config_value(loaded, "model.init_args.results_dir", default="results") == model.get("results_dir", "results")
    for c in loaded["trainer"].get("callbacks") or []:
        # the schedule is the model's argument: a callbacks list would replace the base's whole
        assert c["class_path"] != "ssm_ms.schedule.ShootingSchedule"
        if c["class_path"] == "lightning.pytorch.callbacks.ModelCheckpoint":  # a best epoch beside the house's last
            assert c["init_args"].get("monitor") and c["init_args"].get("filename") == "best"
            assert not c["init_args"].get("save_last")
    if "state_dim" in (loaded["model"].get("init_args") or {}):
        # f's and g's state sizes follow model.init_args.state_dim (interpolated, through includes and overlays): the
        # command line's value reaches both
        args = ["--config", str(config), "--model.init_args.state_dim", "7"]
        changed = config_parser().parse_args(args, _skip_validation=True).as_dict()["model"]["init_args"]
        for network in ("f", "g"):
            sizes = (changed.get(network) or {}).get("init_args") or {}
            for key in ("state_dim", "in_features"):
                if key in sizes:
                    assert sizes[key] == 7, (network, sizes)


def test_overlay_semantics(tmp_path, resolve):
    """What docs/cli.md says of overlays: ``config:`` includes a file (relative to the overlay), a dotted key changes
    one value, a nested section replaces the base's whole section, lists are replaced whole, and a section may be the
    path of a file; a path is relative to the file that states it."""
    (tmp_path / "data").mkdir()
    (tmp_path / "cpu").mkdir()
    (tmp_path / "data" / "lorenz.yaml").write_text(
        "class_path: datamodules.lorenz.LorenzDataModule\ninit_args: {piece_length: 100, n_train: 20, batch_size: 8}\n"
    )
    base = (ROOT / "configs" / "lorenz_T1000.yaml").read_text().split("\ndata:")[0] + "\ndata: data/lorenz.yaml\n"
    (tmp_path / "base.yaml").write_text(base)
    (tmp_path / "cpu" / "overlay.yaml").write_text(
        "config: ../base.yaml\n"
        "trainer.max_epochs: 7\n"
        "trainer.callbacks:\n  - class_path: ssm_ms.checkpointing.EpochCheckpoint\n"
        "model.init_args.f.init_args.hidden: 64\n"
        "data.init_args.n_train: 10\n"
        "seed_everything: 3\n"
    )
    (tmp_path / "cpu" / "replace.yaml").write_text(
        "config: overlay.yaml\n"
        "trainer:\n  logger:\n    class_path: lightning.pytorch.loggers.TensorBoardLogger\n"
        "    init_args: {save_dir: elsewhere, name: replaced}\n"
    )
    overlay = resolve(tmp_path / "cpu" / "overlay.yaml")
    assert overlay["seed_everything"] == 3 and overlay["trainer"]["max_epochs"] == 7
    assert overlay["trainer"]["log_every_n_steps"] == 1  # the base's, kept
    assert [c["class_path"] for c in overlay["trainer"]["callbacks"]] == ["ssm_ms.checkpointing.EpochCheckpoint"]
    f = overlay["model"]["init_args"]["f"]["init_args"]
    assert (f["hidden"], f["n_matrices"], f["state_dim"]) == (64, 32, 3)  # one value changed, the interpolation kept
    data = overlay["data"]["init_args"]  # the base's file (data/, relative to the base), one value changed
    assert (data["piece_length"], data["n_train"], data["batch_size"]) == (100, 10, 8)
    replaced = resolve(tmp_path / "cpu" / "replace.yaml")
    assert replaced["trainer"]["logger"]["init_args"]["name"] == "replaced"
    assert replaced["trainer"]["max_epochs"] is None and replaced["trainer"]["callbacks"] is None  # section replaced
    assert load_config(tmp_path / "cpu" / "replace.yaml")["trainer"]["logger"]["init_args"]["name"] == "replaced"


def test_an_include_loop_is_named(tmp_path):
    (tmp_path / "a.yaml").write_text("config: b.yaml\n")
    (tmp_path / "b.yaml").write_text("config: a.yaml\n")
    with pytest.raises(ValueError, match="loop detected"):
        load_config(tmp_path / "a.yaml")


def test_the_two_sensor_pendulum_sees_the_camera_pendulums_data():
    """configs/data/pendulum_sensors.yaml is configs/data/pendulum_torque.yaml's system and excitation with a joint
    encoder beside the camera: every setting of the torque pendulum's data is the same there (the control rows
    compare the two on the same data), only the sensors' own settings are added."""
    torque = yaml.safe_load((ROOT / "configs/data/pendulum_torque.yaml").read_text())["init_args"]
    sensors = yaml.safe_load((ROOT / "configs/data/pendulum_sensors.yaml").read_text())["init_args"]
    added = {"sensors", "angle_noise_std", "angle_every"}
    assert {k: v for k, v in sensors.items() if k not in added} == torque


def test_an_interpolation_under_a_dotted_key_is_one_line_naming_the_fix(tmp_path, capsys):
    """jsonargparse rewrites an interpolation's path from the YAML nesting, which a dotted key hides (docs/cli.md):
    the CLI says so in one line, with the key, instead of omegaconf's traceback."""
    (tmp_path / "bad.yaml").write_text(
        f"config: {ROOT / 'configs' / 'lorenz_T1000.yaml'}\n"
        "model.init_args.f:\n  class_path: ssm_ms.nets.FullyConnectedTransition\n"
        "  init_args:\n    state_dim: ${model.init_args.state_dim}\n"
    )
    with pytest.raises(SystemExit) as stop:
        main(["fit", "--config", str(tmp_path / "bad.yaml"), "--trainer.max_epochs", "0"])
    err = capsys.readouterr().err
    assert stop.value.code == 1 and "Traceback" not in err
    assert err.startswith("error: a config interpolation cannot be resolved (at model.init_args.f.init_args.state_dim)")
    assert "not under a dotted key" in err


@pytest.mark.parametrize("config", ["configs/cpu/lorenz_T1000.yaml", "configs/cpu/data/lorenz_T1000.yaml"])
def test_build_datamodule_takes_a_whole_config_or_a_data_config_with_overrides(config):
    """build_datamodule (the benchmarks' data from a config): a whole config's data section (given as a file there) or
    a data config, each argument as the data config's YAML states it, overrides replacing theirs."""
    from datamodules.lorenz import LorenzDataModule
    from experiments.configs import build_datamodule

    stated = yaml.safe_load((ROOT / "configs/cpu/data/lorenz_T1000.yaml").read_text())["init_args"]
    dm = build_datamodule(ROOT / config, n_test=3, data_dir="elsewhere")
    assert type(dm) is LorenzDataModule
    assert (dm.n_train, dm.train_steps, dm.piece_length) == (
        stated["n_train"],
        stated["train_steps"],
        stated["piece_length"],
    )
    assert dm.noise_std == stated["noise_std"] and dm.n_test == 3 and str(dm.data_dir) == "elsewhere"
    assert build_datamodule(load_config(ROOT / config)).n_test == stated["n_test"]  # the composed dict, as given


def test_build_datamodule_names_a_config_without_data_and_an_argument_refused(tmp_path):
    from experiments.configs import build_datamodule

    (tmp_path / "trainer.yaml").write_text("trainer:\n  max_epochs: 3\n")
    (tmp_path / "nowhere.yaml").write_text("class_path: datamodules.nowhere.Nothing\n")
    with pytest.raises(ValueError, match="trainer.yaml describes no data module"):
        build_datamodule(tmp_path / "trainer.yaml")
    with pytest.raises(ValueError, match="no data module datamodules.nowhere.Nothing"):
        build_datamodule(tmp_path / "nowhere.yaml")
    with pytest.raises(ValueError, match="refuses its arguments .*colour"):
        build_datamodule(ROOT / "configs/cpu/data/lorenz_T1000.yaml", colour="red")


def test_the_batch400_ablation_takes_t10000s_steps_with_t1000s_pieces():
    """configs/lorenz_T1000_batch400.yaml's premise, from the three configs' values: per epoch as many Adam steps, of
    as many sub-trajectories, as T = 10,000, with T = 1000's pieces and nodes (its continuity links)."""

    def per_epoch(name: str) -> tuple[int, int, int, int]:
        config = load_config(ROOT / "configs" / f"{name}.yaml")
        data, nodes = config["data"]["init_args"], config["model"]["init_args"]["n_nodes"]
        pieces = data["n_train"] * data["train_steps"] // data["piece_length"]
        steps, short = divmod(pieces, data["batch_size"])
        assert short == 0, f"{name}: its last batch is short"
        return steps, data["batch_size"] * nodes, data["piece_length"], nodes

    ablation, t1000, t10000 = (per_epoch(n) for n in ("lorenz_T1000_batch400", "lorenz_T1000", "lorenz_T10000"))
    assert ablation[:2] == t10000[:2] == (25, 8000)
    assert t1000[:2] == (250, 800)
    assert ablation[2:] == t1000[2:] == (1000, 20)
