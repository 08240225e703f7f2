"""A user's mistakes through the real command line (``ssm_ms.cli.main``, in-process): each one exits
non-zero with one short message on stderr naming the problem and the fix, and no traceback. A bug
(an error raised outside the project's validation) still propagates with its traceback, and
``SSM_MS_TRACEBACK=1`` shows the traceback of anything."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from lightning.pytorch.callbacks import Callback

from ssm_ms.cli import TRACEBACK_ENV, main

ROOT = Path(__file__).resolve().parents[1]

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
  class_path: ssm_ms.module.MultipleShootingModule
  init_args:
    state_dim: 3
    n_nodes: 3
    lr: 0.01
    f:
      class_path: ssm_ms.nets.LocallyLinearTransition
      init_args: {{state_dim: "${{model.init_args.state_dim}}", n_matrices: 2, hidden: 8}}
    g:
      class_path: torch.nn.Linear
      init_args: {{in_features: "${{model.init_args.state_dim}}", out_features: 2}}
data:
  class_path: datamodules.files.FileDataModule
  init_args: {{train_path: {root}/good.npz, key: y, batch_size: 4, val_trajectories: 2}}
"""


def trajectories(n: int = 8, t: int = 12, d: int = 2, seed: int = 0) -> np.ndarray:
    """Noisy circles: values in about [-1.1, 1.1]."""
    rng = np.random.default_rng(seed)
    phase = rng.uniform(0, 6.28, (n, 1)) + 0.3 * np.arange(t)
    y = np.stack([np.cos(phase), np.sin(phase)][:d], -1)
    return (y + 0.05 * rng.standard_normal(y.shape)).astype(np.float32)


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """The config, its data files, and a checkpoint of one epoch."""
    root = tmp_path_factory.mktemp("bad")
    y = trajectories()
    np.savez(root / "good.npz", y=y, y_clean=y)
    (root / "config.yaml").write_text(CONFIG.format(root=root))
    main(["fit", "--config", str(root / "config.yaml")])
    (ckpt,) = (root / "runs").glob("**/last.ckpt")
    return root, ckpt


def fails(capsys, args: list[str], status: int, *words: str) -> str:
    """Run the command line; check the exit status, that no traceback was printed, and the message."""
    with pytest.raises(SystemExit) as exit_info:
        main(args)
    out, err = capsys.readouterr()
    assert exit_info.value.code == status, err
    assert "Traceback" not in out + err
    message = err.strip().splitlines()
    assert message and message[0].startswith("error: "), err
    assert len(message) <= 2, err  # the message, and the hint that names the traceback switch
    for word in words:
        assert word in err, err
    assert "weights_only=False" not in err
    return err


def fit(root: Path, *extra: str) -> list[str]:
    return ["fit", "--config", str(root / "config.yaml"), *extra]


def save(root: Path, name: str, **arrays) -> str:
    path = root / name
    if name.endswith(".npy"):
        np.save(path, arrays["y"])
    else:
        np.savez(path, **arrays)
    return str(path)


# ---------------------------------------------------------------------------- data
def test_missing_data_file(setup, capsys):
    root, _ = setup
    fails(
        capsys,
        fit(root, "--data.init_args.train_path", str(root / "nope.npz")),
        1,
        "nope.npz does not exist",
        "expected a .npy or .npz file",
    )


def test_wrong_key(setup, capsys):
    root, _ = setup
    fails(capsys, fit(root, "--data.init_args.key", "z"), 1, "holds no array 'z'", "set the key argument")


def test_empty_array(setup, capsys):
    root, _ = setup
    path = save(root, "empty.npz", y=np.zeros((0, 12, 2), np.float32))
    fails(capsys, fit(root, "--data.init_args.train_path", path), 1, "is empty", "at least one trajectory")


def test_nan_in_data(setup, capsys):
    root, _ = setup
    y = trajectories()
    y[2, 5, 1] = np.nan
    path = save(root, "nan.npz", y=y)
    fails(
        capsys,
        fit(root, "--data.init_args.train_path", path, "--data.init_args.key", "y"),
        1,
        "non-finite value",
        "(2, 5, 1)",
        "remove or interpolate",
    )


def test_wrong_rank(setup, capsys):
    root, _ = setup
    path = save(root, "rank6.npy", y=np.zeros((1, 2, 3, 4, 5, 6), np.float32))
    fails(capsys, fit(root, "--data.init_args.train_path", path), 1, "rank 6", "accepted layouts")


def test_ragged_trajectories(setup, capsys):
    root, _ = setup
    ragged = np.empty(2, dtype=object)
    ragged[0], ragged[1] = np.zeros((12, 2)), np.zeros((10, 2))
    path = root / "ragged.npy"
    np.save(path, ragged, allow_pickle=True)
    fails(capsys, fit(root, "--data.init_args.train_path", str(path)), 1, "object array", "in its own file")


def test_not_a_numpy_file(setup, capsys):
    root, _ = setup
    (root / "data.csv").write_text("1,2,3\n")
    fails(capsys, fit(root, "--data.init_args.train_path", str(root / "data.csv")), 1, "neither .npy nor .npz")


def test_val_file_of_other_measurements(setup, capsys):
    root, _ = setup
    path = save(root, "val3.npz", y=np.zeros((2, 12, 3), np.float32))
    fails(capsys, fit(root, "--data.init_args.val_path", path), 1, "val_path", "do not match the training observations")


def test_test_fraction_out_of_range(setup, capsys):
    root, _ = setup
    fails(capsys, fit(root, "--data.init_args.test_fraction", "1.5"), 1, "test_fraction must be in [0, 1)")


def test_batch_size_zero(setup, capsys):
    root, _ = setup
    fails(capsys, fit(root, "--data.init_args.batch_size", "0"), 1, "batch_size must be >= 1")


def test_constant_channel_with_normalisation(setup, capsys):
    root, _ = setup
    y = trajectories()
    y[..., 1] = 0.5
    path = save(root, "const.npz", y=y)
    fails(
        capsys,
        fit(root, "--data.init_args.train_path", path, "--data.init_args.normalize", "true"),
        1,
        "constant",
        "normalize: false",
    )


# ---------------------------------------------------------------------------- model
def test_length_not_divisible_by_nodes(setup, capsys):
    root, _ = setup
    fails(
        capsys,
        fit(root, "--model.init_args.n_nodes", "5"),
        1,
        "T=12 is not divisible by model.n_nodes=5",
        "choose n_nodes among [1, 2, 3, 4, 6, 12]",
    )


def test_zero_nodes(setup, capsys):
    root, _ = setup
    fails(capsys, fit(root, "--model.init_args.n_nodes", "0"), 1, "n_nodes must be >= 1", "a divisor")


def test_unknown_loss(setup, capsys):
    root, _ = setup
    fails(capsys, fit(root, "--model.init_args.loss", "l1"), 1, "l1", "mse")


def test_negative_learning_rate(setup, capsys):
    root, _ = setup
    fails(capsys, fit(root, "--model.init_args.lr", "-0.001"), 1, "learning rate must be > 0", "model.init_args.lr")


def test_zero_learning_rate(setup, capsys):
    root, _ = setup
    fails(capsys, fit(root, "--model.init_args.lr", "0"), 1, "learning rate must be > 0")


def test_bce_with_data_outside_unit_interval(setup, capsys):
    root, _ = setup
    fails(
        capsys,
        fit(root, "--model.init_args.loss", "bce"),
        1,
        "loss: bce needs measurements in [0.0, 1.0]",
        "range from -1.",
        "use loss: mse",
    )


def test_bce_with_normalised_data(setup, capsys):
    root, _ = setup
    fails(
        capsys,
        fit(root, "--model.init_args.loss", "bce", "--data.init_args.normalize", "true"),
        1,
        "data.normalize is on",
        "normalize to false",
    )


def test_f_of_another_state_size(setup, capsys):
    root, _ = setup
    fails(
        capsys,
        fit(root, "--model.init_args.f.init_args.state_dim", "4"),
        1,
        "f has state_dim 4 but the model was given state_dim 3",
        "give it once",
    )


def test_g_of_another_measurement_size(setup, capsys):
    root, _ = setup
    fails(
        capsys,
        fit(root, "--model.init_args.g.init_args.out_features", "3"),
        1,
        "outputs measurements of shape (3,)",
        "data have shape (2,)",
    )


def test_node_init_map_outside_the_state(setup, capsys):
    root, _ = setup
    fails(capsys, fit(root, "--model.init_args.node_init_map", "{7: 0}"), 1, "node_init_map names state components [7]")


# ---------------------------------------------------------------------------- command line and config
def test_unknown_option(setup, capsys):
    root, _ = setup
    fails(capsys, fit(root, "--model.init_args.bogus", "1"), 2, "model", "'bogus' is not accepted", "--help")


def test_wrong_type(setup, capsys):
    root, _ = setup
    err = fails(capsys, fit(root, "--model.init_args.lr", "fast"), 2, "model.init_args.lr", "float", "fast")
    assert "Union subtypes" not in err and "NoneType" not in err


def test_misspelt_trainer_option(setup, capsys):
    root, _ = setup
    fails(capsys, fit(root, "--trainer.max_epochz", "3"), 2, "unrecognized arguments", "max_epochz")


def test_missing_config_file(setup, capsys):
    root, _ = setup
    fails(capsys, ["fit", "--config", str(root / "nope.yaml")], 2, "nope.yaml")


def test_unknown_class(setup, capsys):
    root, _ = setup
    fails(capsys, fit(root, "--model.init_args.f.class_path", "ssm_ms.nets.NoSuchNet"), 2, "NoSuchNet")


def test_unknown_subcommand(setup, capsys):
    fails(capsys, ["fitt"], 2, "fitt")


@pytest.mark.parametrize("form", [["--config", "configs/nope.yaml"], ["--config=configs/nope.yaml"]])
def test_missing_config_is_refused_before_lightning_is_imported(form):
    """``python cli.py`` checks its ``--config`` files before the ~10 s import of Lightning: one line, status 2, and
    Lightning never loaded (read from ``sys.modules`` of the script's own process)."""
    code = (
        "import runpy, sys\n"
        f"sys.argv = ['cli.py', 'fit', *{form!r}]\n"
        "try:\n    runpy.run_path('cli.py', run_name='__main__')\n"
        "except SystemExit as exc:\n    print(exc.code, 'lightning' in sys.modules, 'torch' in sys.modules)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert done.stdout.split() == ["2", "False", "False"], done.stdout + done.stderr
    assert (
        done.stderr.strip()
        == "error: --config configs/nope.yaml: no such file (the shipped configs are under configs/)"
    )


@pytest.mark.parametrize("program", [["ssm-ms"], ["python", "-m", "ssm_ms"]], ids=["console script", "module"])
def test_the_console_script_is_cli_py(program):
    """``ssm-ms`` (pyproject's console script) and ``python -m ssm_ms`` are ``python cli.py``: the same refusal of a
    missing config, before Lightning is imported."""
    bin_dir = Path(sys.executable).parent
    command = [str(bin_dir / "ssm-ms")] if program == ["ssm-ms"] else [sys.executable, "-m", "ssm_ms"]
    done = subprocess.run(
        [*command, "fit", "--config", "configs/nope.yaml"], cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 2
    assert (
        done.stderr.strip()
        == "error: --config configs/nope.yaml: no such file (the shipped configs are under configs/)"
    )


# ---------------------------------------------------------------------------- checkpoints
def test_missing_checkpoint(setup, capsys):
    root, _ = setup
    fails(capsys, fit(root, "--ckpt_path", str(root / "nope.ckpt")), 1, "nope.ckpt does not exist", "last.ckpt")


def test_truncated_checkpoint(setup, capsys):
    root, ckpt = setup
    data = ckpt.read_bytes()
    (root / "truncated.ckpt").write_bytes(data[: len(data) // 2])
    fails(capsys, fit(root, "--ckpt_path", str(root / "truncated.ckpt")), 1, "is not a readable checkpoint")


def test_foreign_checkpoint(setup, capsys):
    root, _ = setup
    (root / "notes.ckpt").write_text("not a checkpoint\n")
    err = fails(
        capsys, fit(root, "--ckpt_path", str(root / "notes.ckpt")), 1, "notes.ckpt is not a readable checkpoint"
    )
    assert "weights_only" not in err and "unpickl" not in err.lower()


def test_pickle_that_would_run_code_is_refused(setup, capsys):
    root, _ = setup
    torch.save({"state_dict": {}, "anything": Path("x")}, root / "pickled.ckpt")  # needs unsafe loading
    fails(capsys, fit(root, "--ckpt_path", str(root / "pickled.ckpt")), 1, "is not a readable checkpoint")


def test_checkpoint_of_another_model_class(setup, capsys):
    root, _ = setup
    torch.save(
        {"state_dict": {}, "hyper_parameters": {"_class_path": "ssm_ms.baselines.LSTMBaseline"}}, root / "lstm.ckpt"
    )
    fails(
        capsys,
        fit(root, "--ckpt_path", str(root / "lstm.ckpt")),
        1,
        "checkpoint of a ssm_ms.baselines.LSTMBaseline",
        "builds a ssm_ms.module.MultipleShootingModule",
    )


def test_checkpoint_of_other_data(setup, capsys):
    """The checkpoint's node table holds 8 trajectories, the data given now hold 6."""
    root, ckpt = setup
    path = save(root, "six.npz", y=trajectories(6))
    fails(
        capsys,
        fit(root, "--ckpt_path", str(ckpt), "--data.init_args.train_path", path),
        1,
        "shooting nodes for 8 trajectories",
        "training set has 6",
    )


def test_stage_given_a_checkpoint_that_is_not_an_ssm(setup, capsys):
    root, _ = setup
    torch.save({"state_dict": {"encoder.weight": torch.zeros(1)}, "forecaster": "LSTMBaseline"}, root / "base.ckpt")
    fails(
        capsys,
        [
            "test",
            "--config",
            str(ROOT / "configs" / "oscillator_encoder.yaml"),
            "--model.init_args.ssm_checkpoint",
            str(root / "base.ckpt"),
            "--data.init_args.train_path",
            str(root / "good.npz"),
        ],
        1,
        "not of an SSM",
        "last.ckpt of an SSM run",
    )


def test_stage_without_its_ssm(setup, capsys):
    """ssm_checkpoint may be left out only where a --ckpt_path supplies it: else one message naming both ways."""
    root, _ = setup
    fails(
        capsys,
        [
            "test",
            "--config",
            str(ROOT / "configs" / "oscillator_encoder.yaml"),
            "--data.init_args.train_path",
            str(root / "good.npz"),
        ],
        1,
        "model.init_args.ssm_checkpoint is not set",
        "--ckpt_path",
    )


# ---------------------------------------------------------------------------- bugs keep their traceback
class Buggy(Callback):
    """Raises from code that is not the project's validation (a stand-in for a bug)."""

    def __init__(self, kind: str = "runtime"):
        self.kind = kind

    def on_train_start(self, trainer, pl_module):
        raise (ValueError if self.kind == "value" else RuntimeError)("a bug")


@pytest.mark.parametrize("kind", ["runtime", "value"])
def test_a_bug_shows_its_traceback(setup, kind):
    root, _ = setup
    with pytest.raises((RuntimeError, ValueError), match="a bug"):
        main(fit(root, "--trainer.callbacks+=tests.test_bad_input.Buggy", f"--trainer.callbacks.kind={kind}"))


def test_traceback_switch_shows_user_errors_too(setup, monkeypatch):
    root, _ = setup
    monkeypatch.setenv(TRACEBACK_ENV, "1")
    with pytest.raises(ValueError, match="not divisible by model.n_nodes=5"):
        main(fit(root, "--model.init_args.n_nodes", "5"))


def test_the_real_command_prints_no_traceback(setup):
    root, _ = setup
    done = subprocess.run(
        [sys.executable, "cli.py", *fit(root, "--model.init_args.n_nodes", "0")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 1
    assert "Traceback" not in done.stderr and "error: state_dim and n_nodes must be >= 1" in done.stderr


# ---------------------------------------------------------------------------- resuming
def test_invalid_trainer_value_is_one_error_line(setup, capsys):
    root, _ = setup
    fails(capsys, fit(root, "--trainer.max_epochs", "-5"), 1, "trainer:", "max_epochs", "-5")


def test_checkpoint_of_another_model_names_the_checkpoint_first(setup, capsys):
    """A checkpoint trained with a g of 3 outputs on 3-channel data, given to this config (2 channels): the error
    says the checkpoint belongs to another model or data before the shape detail, in one line."""
    root, _ = setup
    path = save(root, "three.npz", y=trajectories(d=2).repeat(2, axis=-1)[..., :3])
    main(
        fit(
            root,
            "--data.init_args.train_path",
            path,
            "--model.init_args.g.init_args.out_features",
            "3",
            "--trainer.default_root_dir",
            str(root / "three"),
        )
    )
    (other,) = (root / "three").glob("**/last.ckpt")
    capsys.readouterr()
    with pytest.raises(SystemExit) as stop:
        main(fit(root, "--ckpt_path", str(other)))
    err = capsys.readouterr().err
    assert stop.value.code == 1 and "Traceback" not in err
    lines = err.strip().splitlines()
    # the note that the checkpoint's g (3 outputs) replaced the config's (2), then the error
    assert lines[0].startswith("note: --ckpt_path") and "g.init_args.out_features = 3 from the checkpoint" in lines[0]
    error = lines[1]
    assert error.startswith(f"error: the checkpoint {other} (trained on the ")
    assert error.index("was trained for another model or other data") < error.index(
        "outputs measurements of shape (3,)"
    )
    assert "data have shape (2,)" in error and "config.yaml" in error and len(lines) == 3, err


def test_ckpt_path_says_which_model_values_it_replaced(setup, capsys):
    """Lightning rebuilds the model with the checkpoint's hyperparameters: a value given that differs is named, with
    the winner; values that agree, and trainer values (which are not replaced), are not."""
    root, ckpt = setup
    saved = torch.load(ckpt, weights_only=True)["hyper_parameters"]
    assert saved["lr"] == 0.01 and saved["f"]["init_args"]["hidden"] == 8
    cli = main(
        fit(
            root,
            "--ckpt_path",
            str(ckpt),
            "--model.init_args.lr",
            "0.5",
            "--model.init_args.n_nodes",
            "3",
            "--model.init_args.f.init_args.hidden",
            "16",
            "--trainer.max_epochs",
            "2",
        )
    )
    err = capsys.readouterr().err
    notes = [line for line in err.splitlines() if line.startswith("note:")]
    assert len(notes) == 1, err
    note = notes[0]
    assert "model.init_args.lr = 0.01 from the checkpoint, not 0.5 as given" in note
    assert "model.init_args.f.init_args.hidden = 8 from the checkpoint, not 16 as given" in note
    assert "n_nodes" not in note and "max_epochs" not in note and "without --ckpt_path" in note
    assert cli.model.hparams.lr == 0.01 and cli.trainer.max_epochs == 2  # the note tells the truth
    capsys.readouterr()
    main(fit(root, "--ckpt_path", str(ckpt), "--trainer.max_epochs", "2"))  # nothing replaced: nothing said
    assert "note:" not in capsys.readouterr().err
