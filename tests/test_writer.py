"""``python cli.py predict`` on a user's own sequences: the same forecasts as the test protocol, in original
units; the filters' covariances; defaults, figures and the user's mistakes.

One tiny oscillator SSM (configs/oscillator.yaml, the README's example) is trained once for the module; the
stages run through the real command line, in-process."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from ssm_ms.cli import main
from ssm_ms.module import MultipleShootingModule

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
K, P = 20, 10  # samples given, steps forecast (the test protocol's n_filter, n_predict here)


def cli(tmp: Path, subcommand: str, config: str, *extra: str):
    return main(
        [
            subcommand,
            "--config",
            str(CONFIGS / config),
            "--trainer.logger.init_args.save_dir",
            str(tmp / "runs"),
            "--trainer.logger.init_args.version",
            "t",
            "--trainer.enable_progress_bar",
            "false",
            "--trainer.enable_model_summary",
            "false",
            "--data.init_args.train_path",
            str(tmp / "osc.npz"),
            *extra,
        ]
    )


@pytest.fixture(scope="module")
def oscillator(tmp_path_factory):
    """``(folder, SSM checkpoint, test sequences y, y_clean)``: 20 recordings of 40 samples, the last 4 the test split."""
    tmp = tmp_path_factory.mktemp("predict")
    spec = importlib.util.spec_from_file_location("make_osc", ROOT / "examples" / "make_oscillator_data.py")
    make_osc = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(make_osc)
    make_osc.main(["--out", str(tmp / "osc.npz"), "--n", "20", "--steps", "40"])
    cli(tmp, "fit", "oscillator.yaml", "--trainer.max_epochs", "3", "--trainer.check_val_every_n_epoch", "3")
    data = np.load(tmp / "osc.npz")
    return tmp, tmp / "runs" / "oscillator" / "t" / "checkpoints" / "last.ckpt", data["y"][16:], data["y_clean"][16:]


def stage_args(tmp: Path, ckpt: Path) -> list[str]:
    return [
        "--model.init_args.ssm_checkpoint",
        str(ckpt),
        "--model.init_args.results_dir",
        str(tmp / "results"),
        "--model.init_args.figures_dir",
        "null",
        "--model.init_args.n_filter",
        str(K),
        "--model.init_args.n_predict",
        str(P),
        "--model.init_args.analysis",
        "null",
    ]


def writer(output: Path, figures: int = 0) -> list[str]:
    return [
        "--trainer.callbacks+=ssm_ms.forecasting.ForecastWriter",
        "--trainer.callbacks.output",
        str(output),
        "--trainer.callbacks.figures",
        str(figures),
    ]


def predict_file(tmp: Path, y: np.ndarray, name: str = "new.npz") -> Path:
    path = tmp / name
    np.savez(path, y=y)
    return path


def per_sequence_mse(pred: np.ndarray, target: np.ndarray) -> np.ndarray:
    return ((pred.astype(np.float64) - target) ** 2).reshape(len(pred), -1).mean(1)


def assert_protocol_scores(out, summary: dict, method: str, y: np.ndarray, y_clean: np.ndarray) -> None:
    """The test stage's scores (mean and population std over sequences), recomputed from predict's output."""
    last = np.repeat(out["filtered"][:, -1:], P, axis=1)
    for name, pred in ((method, out["predicted"]), ("last", last)):
        for target_name, target in (("noisy", y[:, K : K + P]), ("clean", y_clean[:, K : K + P])):
            mse = per_sequence_mse(pred, target)
            score = summary[f"{name}/{target_name}/mse"]
            assert score["n"] == len(mse)
            assert mse.mean() == pytest.approx(score["mean"], rel=1e-5)
            assert mse.std() == pytest.approx(score["std"], rel=1e-4, abs=1e-9)


def ssm_and_units(ckpt: Path):
    """The SSM and the measurement statistics, read from the checkpoint directly."""
    model = MultipleShootingModule.load_from_checkpoint(ckpt).double().eval()
    saved = torch.load(ckpt, weights_only=False)
    norm = next(v["normalizer"] for v in saved.values() if isinstance(v, dict) and "normalizer" in v)
    return model, norm["mean"].double(), norm["std"].double()


def assert_forecast_by_hand(out, ckpt: Path):
    """``predict``'s forecast is ``f`` iterated from the last inferred state, decoded by ``g`` with the normalisation
    undone, and its estimate of the given samples ``g`` of the inferred states; returns ``(model, mean, std)``."""
    model, mean, std = ssm_and_units(ckpt)
    x = torch.from_numpy(out["states"][:, -1]).double()
    with torch.no_grad():
        for j in range(P):
            x = model.f(x)
            torch.testing.assert_close(
                x, torch.from_numpy(out["predicted_states"][:, j]).double(), rtol=1e-4, atol=1e-5
            )
            y_j = model.g(x) * std + mean
            torch.testing.assert_close(y_j, torch.from_numpy(out["predicted"][:, j]).double(), rtol=1e-4, atol=1e-5)
        filtered = model.g(torch.from_numpy(out["states"]).double()) * std + mean
    torch.testing.assert_close(filtered, torch.from_numpy(out["filtered"]).double(), rtol=1e-4, atol=1e-5)
    return model, mean, std


def scores_and_predictions(tmp: Path, config: str, method: str, args: list[str], y: np.ndarray):
    """``(summary, out)``: the test stage's scores of ``method`` (``config`` with ``args``), and ``predict``'s output
    (the same ``args``) on the same test sequences ``y`` as a user's file, in original units, ``K`` given, ``P``
    forecast."""
    cli(tmp, "test", config, *args)
    summary = json.loads((tmp / "results" / "oscillator.json").read_text())["runs"][method]["summary"]
    given = ["--data.init_args.predict_given", str(K), "--data.init_args.predict_steps", str(P)]
    source = ["--data.init_args.predict_path", str(predict_file(tmp, y))]
    cli(tmp, "predict", config, *args, *source, *given, *writer(tmp / f"{method}.npz"))
    return summary, np.load(tmp / f"{method}.npz")


def test_ukf_predict_gives_the_test_protocol_forecasts_in_original_units(oscillator):
    tmp, ckpt, y, y_clean = oscillator
    summary, out = scores_and_predictions(tmp, "oscillator_ukf.yaml", "ukf", stage_args(tmp, ckpt), y)
    d = 4
    assert out["filtered"].shape == (4, K, 2) and out["predicted"].shape == (4, P, 2)
    assert out["states"].shape == (4, K, d) and out["predicted_states"].shape == (4, P, d)
    assert (int(out["k"]), int(out["p"]), str(out["method"])) == (K, P, "ukf")
    assert out["index"].tolist() == [0, 1, 2, 3]
    assert_protocol_scores(out, summary, "ukf", y, y_clean)
    model, _, _ = assert_forecast_by_hand(out, ckpt)

    # covariances: symmetric positive semi-definite; the first forecast one is the unscented transform of
    # the last posterior through f (alpha 1, beta 2, kappa 0: centre weights 0 and 2, the others 1 / 2d)
    # plus the process noise 1e-4 I of configs/oscillator_ukf.yaml
    posterior, ahead = (
        torch.from_numpy(out["state_cov"]).double(),
        torch.from_numpy(out["predicted_state_cov"]).double(),
    )
    assert posterior.shape == (4, K, d, d) and ahead.shape == (4, P, d, d)
    for cov in (posterior, ahead):
        torch.testing.assert_close(cov, cov.transpose(-1, -2))
        eig = torch.linalg.eigvalsh(cov)
        assert (eig >= -1e-6 * eig.abs().amax(-1, keepdim=True)).all()
    m, chol = torch.from_numpy(out["states"][:, -1]).double(), torch.linalg.cholesky(posterior[:, -1])
    offsets = d**0.5 * chol.transpose(-1, -2)  # rows: columns of the Cholesky factor
    sigma = torch.cat([m[:, None], m[:, None] + offsets, m[:, None] - offsets], 1)  # [4, 2d + 1, d]
    with torch.no_grad():
        fs = model.f(sigma.reshape(-1, d)).reshape(4, 2 * d + 1, d)
    w_mean = torch.full((2 * d + 1,), 1 / (2 * d), dtype=torch.float64)
    w_mean[0] = 0.0
    w_cov = w_mean.clone()
    w_cov[0] = 2.0
    centred = fs - (w_mean[:, None] * fs).sum(1, keepdim=True)
    expected = torch.einsum("n,bni,bnj->bij", w_cov, centred, centred) + 1e-4 * torch.eye(d, dtype=torch.float64)
    torch.testing.assert_close(ahead[:, 0], expected, rtol=1e-3, atol=1e-6)


def test_encoder_predict_gives_the_test_protocol_forecasts(oscillator):
    tmp, ckpt, y, y_clean = oscillator
    args = stage_args(tmp, ckpt)
    cli(
        tmp,
        "fit",
        "oscillator_encoder.yaml",
        *args,
        "--trainer.max_epochs",
        "1",
        "--trainer.check_val_every_n_epoch",
        "1",
        "--model.init_args.encoder",
        '{"preset": "vector", "hidden": 16}',
    )
    enc = tmp / "runs" / "oscillator_encoder" / "t" / "checkpoints" / "last.ckpt"
    summary, out = scores_and_predictions(
        tmp, "oscillator_encoder.yaml", "encoder", [*args, "--ckpt_path", str(enc)], y
    )
    assert str(out["method"]) == "encoder" and "state_cov" not in out.files and out["states"].shape == (4, K, 4)
    assert_protocol_scores(out, summary, "encoder", y, y_clean)


def test_optimisation_predict_gives_the_test_protocol_forecasts(oscillator, capsys):
    """States fitted through f and g: the same forecasts from ``predict`` as from ``test`` (each sequence's fit is its
    own, whatever the batch), states that are the rollouts of the fitted nodes, no covariances."""
    tmp, ckpt, y, y_clean = oscillator
    args = [*stage_args(tmp, ckpt), "--model.init_args.n_nodes", "2", "--model.init_args.steps", "100"]
    summary, out = scores_and_predictions(tmp, "oscillator_optimise.yaml", "optimise", args, y)
    assert str(out["method"]) == "optimise" and "state_cov" not in out.files and out["states"].shape == (4, K, 4)
    assert_protocol_scores(out, summary, "optimise", y, y_clean)
    model, _, _ = assert_forecast_by_hand(out, ckpt)
    states = torch.from_numpy(out["states"]).double()  # two pieces of K / 2: each a rollout of f from its node
    with torch.no_grad():
        for t in [*range(K // 2 - 1), *range(K // 2, K - 1)]:
            torch.testing.assert_close(model.f(states[:, t]), states[:, t + 1], rtol=1e-4, atol=1e-5)
    # given samples the pieces do not cut evenly: refused before predicting, or when the file is read (given whole)
    source, short = predict_file(tmp, y), predict_file(tmp, y[:, :25], "odd.npz")
    for extra, words in (
        (["--data.init_args.predict_path", str(source), "--data.init_args.predict_given", "7"], "predict_given: 7"),
        (
            ["--data.init_args.predict_path", str(short), "--model.init_args.n_predict", "5"],
            "(predict_given unset): 25",
        ),
    ):
        err = predict_error(tmp, ckpt, capsys, *args[-4:], *extra, config="oscillator_optimise.yaml")
        assert f"{words} measurements, which n_nodes=2 does not cut into equal pieces" in err, err


def test_predict_defaults_figures_and_the_particle_filter(oscillator, monkeypatch):
    tmp, ckpt, y, _ = oscillator
    source = predict_file(tmp, y[:, :25], "recording.npz")
    work = tmp / "cwd"
    work.mkdir()
    monkeypatch.chdir(work)
    # no ForecastWriter configured: predictions/<experiment>_<method>.npz; k: the whole recording; p: n_predict
    cli(tmp, "predict", "oscillator_ukf.yaml", *stage_args(tmp, ckpt), "--data.init_args.predict_path", str(source))
    out = np.load(work / "predictions" / "oscillator_ukf.npz")
    assert out["filtered"].shape == (4, 25, 2) and out["predicted"].shape == (4, P, 2)
    # the particle filter: weighted covariances, figures of the first two sequences
    cli(
        tmp,
        "predict",
        "oscillator_ukf.yaml",
        *stage_args(tmp, ckpt),
        "--model.init_args.method",
        "pf",
        "--model.init_args.n_particles",
        "64",
        "--model.init_args.unscented",
        "null",
        "--data.init_args.predict_path",
        str(source),
        "--data.init_args.predict_steps",
        "5",
        *writer(tmp / "pf.npz", figures=2),
    )
    out = np.load(tmp / "pf.npz")
    assert str(out["method"]) == "pf" and out["predicted"].shape == (4, 5, 2)
    for key, steps in (("state_cov", 25), ("predicted_state_cov", 5)):
        cov = torch.from_numpy(out[key]).double()
        assert cov.shape == (4, steps, 4, 4)
        torch.testing.assert_close(cov, cov.transpose(-1, -2))
        assert (torch.linalg.eigvalsh(cov) >= -1e-6).all()
    assert sorted(p.name for p in (tmp / "pf_figures").iterdir()) == ["sequence_00000.png", "sequence_00001.png"]


def predict_error(tmp: Path, ckpt: Path, capsys, *extra: str, config: str = "oscillator_ukf.yaml") -> str:
    with pytest.raises(SystemExit) as exit_info:
        cli(tmp, "predict", config, *stage_args(tmp, ckpt), *extra, *writer(tmp / "never.npz"))
    err = capsys.readouterr().err
    assert exit_info.value.code not in (0, None) and "Traceback" not in err, err
    assert not (tmp / "never.npz").exists()
    return err


def test_predict_refuses_bad_inputs_with_one_message(oscillator, capsys):
    tmp, ckpt, y, _ = oscillator
    good = predict_file(tmp, y, "good.npz")
    np.save(tmp / "flat.npy", y[..., 0])
    np.save(tmp / "three.npy", np.concatenate([y, y[..., :1]], -1))
    nan = y.copy()
    nan[1, 3, 0] = np.nan
    np.save(tmp / "nan.npy", nan)
    cases = [
        ([], "nothing to predict"),
        (["--data.init_args.predict_path", str(tmp / "missing.npz")], "does not exist"),
        (["--data.init_args.predict_path", str(tmp / "flat.npy")], "add a trailing axis"),
        (["--data.init_args.predict_path", str(tmp / "three.npy")], "the model was trained on (2,)"),
        (["--data.init_args.predict_path", str(good), "--data.init_args.predict_key", "x"], "holds no array 'x'"),
        (
            ["--data.init_args.predict_path", str(good), "--data.init_args.predict_given", "41"],
            "predict_given=41 but the sequences of predict_path have T=40",
        ),
        (
            ["--data.init_args.predict_path", str(good), "--data.init_args.predict_given", "0"],
            "predict_given must be >= 1",
        ),
        (["--data.init_args.predict_path", str(good), "--model.init_args.n_predict", "null"], "predict_steps"),
        (["--data.init_args.predict_path", str(tmp / "nan.npy")], "non-finite"),
    ]
    for extra, words in cases:
        assert words in predict_error(tmp, ckpt, capsys, *extra), extra


def test_forecasts_that_diverge_are_named_with_their_step():
    """A forecast that leaves the finite range, or 100 training stds (here: std 2, so 200 from the mean 1), is named
    with its first such step; one within the bound is not."""
    from types import SimpleNamespace

    from datamodules.normalizer import Normalizer
    from ssm_ms.forecasting.writer import ForecastWriter

    predicted = np.ones((3, 6, 1))
    predicted[1, 4, 0] = 1 + 2 * 101.0  # 101 stds away
    predicted[2, 2, 0] = np.inf
    predicted[0, 5, 0] = 1 + 2 * 99.0  # within
    module = SimpleNamespace(normalizer=lambda: Normalizer(torch.tensor([1.0]), torch.tensor([2.0]), 1))
    assert ForecastWriter._diverged({"predicted": predicted}, module) == [(1, 4), (2, 2)]
