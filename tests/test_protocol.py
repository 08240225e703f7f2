"""The forecasting protocol (``ssm_ms.forecasting.protocol``): frame bookkeeping and references with an exact model,
a forecast that diverges, the analysis of the exact model, the encoder stage on a tiny trained checkpoint, the UKF
and particle filter stages, and bad input. The metrics: tests/test_metrics.py; the valid time:
tests/test_valid_time.py; the analysis options: tests/test_analysis_settings.py."""

import json
import math
from pathlib import Path

import lightning.pytorch as pl
import numpy as np
import pytest
import torch
from lightning.pytorch.callbacks import ModelCheckpoint

from experiments.results import render_file
from ssm_ms.inference.encoder_module import StateEncoderModule
from ssm_ms.inference.filter_module import FilterForecaster
from ssm_ms.inference.optimise import OptimisationForecaster
from ssm_ms.inference.ssm_forecaster import SSMForecaster
from ssm_ms.module import MultipleShootingModule
from ssm_ms.nets import Projection
from ssm_ms.runtime import memory
from tests.conftest import ExactRotation, RotationDataModule, fast_trainer


# ---------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def exact_ssm(tmp_path_factory):
    """An SSM whose f is the data's true rotation (trained briefly: nodes only matter for the encoder)."""
    tmp = tmp_path_factory.mktemp("exact")
    dm = RotationDataModule(data_dir=str(tmp / "data"), seq_len=12, batch_size=4, val_trajectories=2)
    model = MultipleShootingModule(
        ExactRotation(0.3, learnable=False), Projection([0]), state_dim=2, n_nodes=3, lr=0.05
    )
    ckpt = ModelCheckpoint(dirpath=tmp / "ckpt", save_last=True)
    fast_trainer(tmp, max_epochs=40, callbacks=[ckpt]).fit(model, dm)
    return tmp, tmp / "ckpt" / "last.ckpt"


def rotation_dm(tmp):
    return RotationDataModule(data_dir=str(tmp / "data"), seq_len=12, batch_size=4, val_trajectories=2)


class Oracle(SSMForecaster):
    """Infers the true states (read from the batch), and records what it was given."""

    method_kind = "oracle"

    def on_test_batch_start(self, batch, batch_idx, dataloader_idx=0):
        self.batch = batch

    def infer(self, y_filter, u=None):
        k = y_filter.shape[1]
        assert torch.equal(y_filter, self.batch["y"][:, :k])  # exactly the first k measurements
        return self.batch["state"][:, :k]


# ---------------------------------------------------------------------------- the protocol
def test_protocol_bookkeeping_with_the_exact_model(exact_ssm):
    tmp, ckpt = exact_ssm
    dm = rotation_dm(tmp)
    oracle = Oracle(str(ckpt), n_filter=8, metrics=["mse"], results_dir=str(tmp / "results"), experiment="rot")
    fast_trainer(tmp, max_epochs=1).test(oracle, dm)
    saved = json.loads((tmp / "results" / "rot.json").read_text())["runs"]["oracle"]["summary"]
    # exact f from the true state at k-1: frames k..T-1 are predicted exactly (no off-by-one)
    assert saved["oracle/clean/mse"]["mean"] < 1e-10
    # references, recomputed here: the last inferred frame and the mean training frame, held constant
    test = dm.load_arrays("test")
    clean = torch.from_numpy(test["y_clean"].copy()).double()  # [4, 12, 1]
    last = clean[:, 7:8]  # g(x[k-1]) = the clean frame at k-1 since the states are exact
    expected_last = (clean[:, 8:] - last).pow(2).mean((1, 2))
    train_y = torch.from_numpy(dm.load_arrays("train")["y"].copy()).double()
    expected_mean = (clean[:, 8:] - train_y.mean((0, 1))).pow(2).mean((1, 2))
    assert saved["last/clean/mse"]["mean"] == pytest.approx(expected_last.mean().item(), rel=1e-5)
    assert saved["last/clean/mse"]["std"] == pytest.approx(expected_last.std(unbiased=False).item(), rel=1e-4)
    assert saved["mean/clean/mse"]["mean"] == pytest.approx(expected_mean.mean().item(), rel=1e-5)
    noisy = torch.from_numpy(test["y"].copy()).double()
    expected_noisy = (noisy[:, 8:] - clean[:, 8:]).pow(2).mean((1, 2))
    assert saved["oracle/noisy/mse"]["mean"] == pytest.approx(expected_noisy.mean().item(), rel=1e-4)
    report = render_file(tmp / "results" / "rot.json").read_text()
    assert (
        "| SSM (ExactRotation) + oracle |" in report
        and "| last (reference, with SSM (ExactRotation) + oracle) |" in report
    )


def test_results_go_to_the_run_folder_unless_a_results_dir_is_given(exact_ssm):
    """The library writes the results file (JSON only) into the run's own folder by default (the trainer's log_dir;
    here, without a logger, its default_root_dir), never into the repository's results/."""
    tmp, ckpt = exact_ssm
    oracle = Oracle(str(ckpt), n_filter=8, metrics=["mse"], experiment="rot_here")
    trainer = fast_trainer(tmp / "run", max_epochs=1)
    trainer.test(oracle, rotation_dm(tmp))
    assert Path(trainer.log_dir) == tmp / "run"
    assert sorted(p.name for p in (tmp / "run").glob("rot_here.*")) == ["rot_here.json"]
    assert not (tmp / "results" / "rot_here.json").exists()


class DivergingOracle(Oracle):
    """The true states, except for the test sequences whose index is in ``diverged``: NaN (a filter that blew up)."""

    def __init__(self, *args, diverged=(), **kwargs):
        super().__init__(*args, **kwargs)
        self.diverged = set(diverged)

    def infer(self, y_filter, u=None):
        states = super().infer(y_filter).clone()
        for row, index in enumerate(self.batch["index"].tolist()):
            if index in self.diverged:
                states[row] = float("nan")
        return states


@pytest.mark.parametrize("diverged", [(1, 3), (0, 1, 2, 3)], ids=["some", "all"])
def test_a_forecast_that_diverges_is_reported_not_averaged(exact_ssm, diverged):
    """A test run whose forecasts are NaN on some sequences (or all) still writes its results: the scores of the
    others, and how many diverged."""
    tmp, ckpt = exact_ssm
    name = f"rot_nan{len(diverged)}"
    oracle = DivergingOracle(
        str(ckpt),
        n_filter=8,
        metrics=["mse"],
        results_dir=str(tmp / "results"),
        experiment=name,
        diverged=diverged,
        analysis={"valid_time": {}},
    )
    fast_trainer(tmp, max_epochs=1).test(oracle, rotation_dm(tmp))
    saved = json.loads((tmp / "results" / f"{name}.json").read_text())["runs"]["oracle"]["summary"]
    entry = saved["oracle/clean/mse"]
    assert (entry["n"], entry["non_finite"]) == (4, len(diverged))
    assert saved["last/clean/mse"]["non_finite"] == len(diverged)  # the reference uses the method's last estimate
    assert saved["mean/clean/mse"]["non_finite"] == 0
    report = render_file(tmp / "results" / f"{name}.json").read_text()
    if len(diverged) == 4:
        assert "non-finite on all 4" in report
    else:
        assert entry["mean"] < 1e-10  # the two others are exact
        assert f"({len(diverged)} of 4 non-finite, left out)" in report


def test_analysis_of_the_exact_model(exact_ssm):
    """The exact rotation as f: forecasts from exact states never leave the truth (valid time infinite: censored
    at the horizon), f is neither expanding nor contracting (exponents 0), and its free runs decoded have the
    data's distribution (x = cos of a uniform phase)."""
    tmp, ckpt = exact_ssm
    dm = rotation_dm(tmp)
    analysis = {
        "valid_time": {"n_filter": 4, "horizon": 8},
        "dt": 0.1,
        "dynamics": {
            "runs": 4,
            "free_runs": 6,
            "lyapunov_steps": 300,
            "transient": 10,
            "align": 10,
            "free_steps": 2000,
        },
    }
    oracle = Oracle(
        str(ckpt), n_filter=8, metrics=["mse"], results_dir=str(tmp / "results"), experiment="rot_an", analysis=analysis
    )
    fast_trainer(tmp, max_epochs=1).test(oracle, dm)
    run = json.loads((tmp / "results" / "rot_an.json").read_text())["runs"]["oracle"]
    vt = run["analysis"]["valid_time"]
    assert vt["censored_share"] == 1.0 and vt["mean_steps"] == 8 and vt["mean_seconds"] == pytest.approx(0.8)
    assert vt["mean_lyapunov_times"] is None  # no true exponent known for this data set
    dyn = run["analysis"]["dynamics"]
    assert dyn["lyapunov"]["exponents"] == pytest.approx([0.0, 0.0], abs=1e-6)
    free = dyn["free_run"]
    assert dyn["lyapunov"]["runs"] == 4 and free["runs"] == 6
    assert free["model_std"][0] == pytest.approx(math.sqrt(0.5), rel=0.05)  # nodes trained briefly: radius ~1
    assert free["reference_std"][0] == pytest.approx(math.sqrt(0.5), rel=0.1)
    assert "## Analysis" in render_file(tmp / "results" / "rot_an.json").read_text()


def test_encoder_stage_on_a_tiny_trained_checkpoint(exact_ssm):
    tmp, ckpt = exact_ssm
    dm = rotation_dm(tmp)
    enc = StateEncoderModule(
        str(ckpt),
        n_filter=8,
        encoder={"preset": "vector", "hidden": 32},
        lr=1e-2,
        metrics=["mse"],
        results_dir=str(tmp / "results"),
        experiment="rot_enc",
    )
    trainer = fast_trainer(tmp, max_epochs=30)
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    trainer.fit(enc, dm)
    # latent statistics over all training trajectories, recomputed by a naive loop over nodes and steps
    ssm = enc.ssm
    zs = []
    for j in range(8):
        for i in range(3):
            x = ssm.node_states(torch.tensor([j]))[0, i : i + 1]
            for _ in range(4):
                zs.append(x[0])
                x = ssm.f(x)
    zs = torch.stack(zs)
    torch.testing.assert_close(enc.latent_mean, zs.mean(0), rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(enc.latent_std, zs.std(0, unbiased=False), rtol=1e-4, atol=1e-5)
    # the encoder learned the regression: far better than predicting the mean latent (loss 1)
    with torch.no_grad():
        assert enc._regression(batch).item() < 0.3
    fast_trainer(tmp, max_epochs=1).test(enc, dm)
    saved = json.loads((tmp / "results" / "rot_enc.json").read_text())["runs"]["encoder"]["summary"]
    assert saved["encoder/clean/mse"]["mean"] < saved["mean/clean/mse"]["mean"]


def test_an_encoder_that_cannot_train_in_memory_is_refused_before_its_first_step(exact_ssm, monkeypatch):
    """The encoder's LSTM (32 units) on batches of 4 sequences of 12 steps needs at least 60 x 4 x 12 x 32 bytes
    (92 kB): with 50 kB available, fit stops before any step, naming a batch that fits (0.8 x 50 kB / 23 kB: 1)."""
    tmp, ckpt = exact_ssm
    enc = StateEncoderModule(str(ckpt), n_filter=8, encoder={"preset": "vector", "hidden": 32}, metrics=["mse"])
    trainer = fast_trainer(tmp, max_epochs=1)
    monkeypatch.setattr(memory, "available_memory", lambda: 50_000)
    with pytest.raises(ValueError, match=r"the encoder needs at least 92 kB .* 4 sequences of 12 steps .* at most 1 "):
        trainer.fit(enc, rotation_dm(tmp))
    assert trainer.global_step == 0


def test_ssim_on_vector_data_is_refused_before_any_sequence_is_scored(exact_ssm):
    tmp, ckpt = exact_ssm
    ukf = FilterForecaster(
        str(ckpt),
        n_filter=8,
        method="ukf",
        metrics=["mse", "ssim"],
        results_dir=str(tmp / "results"),
        experiment="rot_ssim",
    )
    ukf.test_step = lambda *a, **k: pytest.fail("a sequence was scored")
    with pytest.raises(ValueError, match="metric 'ssim' needs image frames"):
        fast_trainer(tmp, max_epochs=1).test(ukf, rotation_dm(tmp))
    assert not (tmp / "results" / "rot_ssim.json").exists()


def test_ukf_stage_tracks_the_exact_model(exact_ssm):
    tmp, ckpt = exact_ssm
    dm = rotation_dm(tmp)
    ukf = FilterForecaster(
        str(ckpt),
        n_filter=8,
        method="ukf",
        measurement_var=0.05**2,
        init_var=1.0,
        metrics=["mse"],
        results_dir=str(tmp / "results"),
        experiment="rot_ukf",
    )
    fast_trainer(tmp, max_epochs=1).test(ukf, dm)
    saved = json.loads((tmp / "results" / "rot_ukf.json").read_text())["runs"]["ukf"]["summary"]
    # noise std 0.05 on a unit circle: the filtered phase is accurate, the forecast too
    assert saved["ukf/clean/mse"]["mean"] < 0.01
    assert saved["ukf/clean/mse"]["mean"] < 0.1 * saved["mean/clean/mse"]["mean"]
    # f and g in bfloat16 and the cubature rule, labelled as another method of the same experiment:
    # as accurate, and the results say how the states were inferred
    fast = FilterForecaster(
        str(ckpt),
        n_filter=8,
        method="ukf",
        measurement_var=0.05**2,
        init_var=1.0,
        autocast="bfloat16",
        unscented={"beta": 0.0},
        method_name="ukf_fast",
        metrics=["mse"],
        results_dir=str(tmp / "results"),
        experiment="rot_ukf",
    )
    assert fast.filter.beta == 0.0
    fast_trainer(tmp, max_epochs=1).test(fast, dm)
    runs = json.loads((tmp / "results" / "rot_ukf.json").read_text())["runs"]
    assert set(runs) == {"ukf", "ukf_fast"}
    assert runs["ukf_fast"]["summary"]["ukf_fast/clean/mse"]["mean"] < 0.01
    assert runs["ukf"]["info"]["inference_settings"].endswith("alpha=1, beta=2, kappa=0; full precision")
    assert runs["ukf_fast"]["info"]["inference_settings"].endswith(
        "alpha=1, beta=0, kappa=0; f and g under autocast(bfloat16)"
    )
    assert "f and g under autocast(bfloat16)" in render_file(tmp / "results" / "rot_ukf.json").read_text()
    with pytest.raises(ValueError, match=r"unscented takes alpha, beta, kappa and iterations, got \['gamma'\]"):
        FilterForecaster(str(ckpt), n_filter=8, unscented={"gamma": 1.0})
    with pytest.raises(ValueError, match="no effect with method 'pf'"):
        FilterForecaster(str(ckpt), n_filter=8, method="pf", unscented={"beta": 0.0})


def test_ukf_prior_mean_is_the_mean_node_or_zero(exact_ssm):
    tmp, ckpt = exact_ssm
    y = torch.randn(3, 8, 2)
    nodes = FilterForecaster(str(ckpt), n_filter=8)
    zero = FilterForecaster(str(ckpt), n_filter=8, init_mean="zero")
    ssm = nodes.ssm
    mean_node = ssm.nodes.weight.detach().view(-1, ssm.state_dim).mean(0)
    mapping = {int(k): int(v) for k, v in (ssm.hparams.get("node_init_map") or {}).items()}
    expect_nodes, expect_zero = mean_node.expand(3, -1).clone(), torch.zeros(3, ssm.state_dim)
    for state_i, obs_i in mapping.items():
        expect_nodes[:, state_i] = expect_zero[:, state_i] = y[:, 0, obs_i]
    torch.testing.assert_close(nodes.prior_mean(y), expect_nodes)
    torch.testing.assert_close(zero.prior_mean(y), expect_zero)
    assert zero.inference_settings().endswith("init_mean=zero; full precision")
    with pytest.raises(ValueError, match="init_mean must be 'nodes'"):
        FilterForecaster(str(ckpt), n_filter=8, init_mean="mean")


def test_states_fitted_by_optimisation_track_the_exact_model(exact_ssm):
    tmp, ckpt = exact_ssm
    dm = rotation_dm(tmp)
    results = tmp / "results" / "rot_optimise.json"
    for nodes in (1, 4):  # single shooting, and four pieces of two steps joined by the SSM's own alpha
        fitted = OptimisationForecaster(
            str(ckpt),
            n_filter=8,
            n_nodes=nodes,
            method_name=f"optimise{nodes}",
            results_dir=str(tmp / "results"),
            experiment="rot_optimise",
        )
        fast_trainer(tmp, max_epochs=1).test(fitted, dm)
        run = json.loads(results.read_text())["runs"][f"optimise{nodes}"]
        # noise std 0.05 on a unit circle, 8 samples: the phase is well determined, the forecast too
        assert run["summary"][f"optimise{nodes}/clean/mse"]["mean"] < 0.01
        assert run["summary"][f"optimise{nodes}/clean/mse"]["mean"] < 0.1 * run["summary"]["mean/clean/mse"]["mean"]
        settings = run["info"]["inference_settings"]
        assert settings.startswith(f"Adam on the shooting objective of the frozen f and g: n_nodes={nodes}, alpha=")
    assert fitted.alpha == float(fitted.ssm.alpha)  # unset: the SSM's own, as its training ended


@pytest.mark.parametrize("per_call", [None, 8])  # all candidates in one call, or in calls of a few
def test_the_best_node_start_is_the_candidate_that_fits_each_piece_best(exact_ssm, monkeypatch, per_call):
    tmp, ckpt = exact_ssm
    if per_call is not None:  # 8 states per call: one candidate at a time over 2 sequences x 2 pieces of 2 steps
        monkeypatch.setattr("ssm_ms.inference.optimise.SEARCH_STATES", per_call)
    fitted = OptimisationForecaster(str(ckpt), n_filter=4, n_nodes=2, n_candidates=5)
    candidates = fitted.candidates.double().numpy()
    assert len(candidates) == 5
    y = torch.randn(2, 4, 1, generator=torch.Generator().manual_seed(1))
    c, s = math.cos(0.3), math.sin(0.3)
    rotation = np.array([[c, -s], [s, c]])
    expected = np.zeros((2, 2, 2))
    for b in range(2):
        for piece in range(2):
            fits = []
            for x in candidates:  # the rollout's first component against the piece's 2 measurements
                states = [x, rotation @ x]
                fits.append(np.mean([(states[j][0] - y[b, 2 * piece + j, 0].item()) ** 2 for j in range(2)]))
            expected[b, piece] = candidates[int(np.argmin(fits))]
    np.testing.assert_allclose(fitted.initial_nodes(y).double().numpy(), expected, rtol=1e-6)


def test_optimisation_settings_are_checked_before_any_sequence(exact_ssm):
    tmp, ckpt = exact_ssm
    with pytest.raises(ValueError, match=r"n_filter: 8 measurements, which n_nodes=3 .* among \[1, 2, 4, 8\]"):
        OptimisationForecaster(str(ckpt), n_filter=8, n_nodes=3)
    with pytest.raises(ValueError, match="start must be 'best_node' .*'nodes' .*or 'zero', got 'mean'"):
        OptimisationForecaster(str(ckpt), n_filter=8, start="mean")
    with pytest.raises(ValueError, match="lr must be > 0"):
        OptimisationForecaster(str(ckpt), n_filter=8, lr=0)
    with pytest.raises(ValueError, match="alpha must be >= 0"):
        OptimisationForecaster(str(ckpt), n_filter=8, alpha=-1.0)
    with pytest.raises(ValueError, match="n_nodes must be >= 1"):
        OptimisationForecaster(str(ckpt), n_filter=8, n_nodes=0)
    with pytest.raises(ValueError, match="n_candidates must be >= 1"):
        OptimisationForecaster(str(ckpt), n_filter=8, n_candidates=0)
    fitted = OptimisationForecaster(
        str(ckpt), n_filter=8, n_nodes=4, analysis={"valid_time": {"n_filter": 6, "horizon": 4}}
    )
    with pytest.raises(ValueError, match="valid_time's n_filter: 6 measurements, which n_nodes=4 does not cut"):
        fast_trainer(tmp, max_epochs=1).test(fitted, rotation_dm(tmp))


def test_the_ssm_training_figure_comes_only_from_the_ssm_run_itself(exact_ssm, tmp_path):
    """A checkpoint in its training run's ``checkpoints/`` folder draws that run's curves; a copy elsewhere (a
    ``pretrained/`` file) draws none, though the folder above it holds another run's event files."""
    from torch.utils.tensorboard import SummaryWriter

    _, ckpt = exact_ssm
    for run in (tmp_path / "run", tmp_path / "other"):
        with SummaryWriter(str(run)) as writer:
            writer.add_scalar("train/fit", 1.0, 0)
    (tmp_path / "run" / "checkpoints").mkdir()
    (tmp_path / "pretrained").mkdir()
    first = {"y": torch.zeros(1, 12, 1), "y_model": torch.zeros(1, 12, 1), "states": torch.zeros(1, 12, 2)}
    drawn = {}
    for where in ("run/checkpoints", "pretrained"):
        copy = tmp_path / where / "ssm.ckpt"
        copy.write_bytes(ckpt.read_bytes())
        drawn[where] = FilterForecaster(str(copy), n_filter=8).forecast_figures(first)
    assert "ssm_training" in drawn["run/checkpoints"]
    assert "ssm_training" not in drawn["pretrained"]


# ---------------------------------------------------------------------------- bad input
def test_missing_checkpoint_is_named(tmp_path):
    with pytest.raises(
        FileNotFoundError, match=r"the SSM checkpoint .*nope.ckpt does not exist: train the model first"
    ):
        StateEncoderModule(str(tmp_path / "nope.ckpt"), n_filter=5)


def test_checkpoint_of_another_data_set_is_refused(exact_ssm):
    tmp, ckpt = exact_ssm
    other = RotationDataModule(data_dir=str(tmp / "data"), seq_len=12, omega=0.5, batch_size=4)
    trainer = fast_trainer(tmp, max_epochs=1)
    with pytest.raises(ValueError, match=r"trained on other data: data parameters differ .*'omega': \(0.3, 0.5\)"):
        trainer.fit(StateEncoderModule(str(ckpt), n_filter=8, encoder={"preset": "vector", "hidden": 8}), other)


@pytest.mark.parametrize("kind", ["encoder", "lstm"])
def test_a_forecaster_validated_on_held_out_trajectories_never_trains_on_them(exact_ssm, kind):
    """validate_held_out (an encoder's, a baseline's): the training batches hold every training trajectory but the
    evenly spaced validation ones (first and last of 8 for val_trajectories 2), validation holds exactly those;
    without trajectories to hold out (val_trajectories 0), or holding out all 8, the fit is refused before any step,
    naming the setting."""
    from lightning.pytorch.callbacks import Callback

    from ssm_ms.baselines import LSTMBaseline

    tmp, ckpt = exact_ssm

    class Seen(Callback):
        def __init__(self):
            self.train, self.val = set(), set()

        def on_train_batch_start(self, trainer, module, batch, batch_idx):
            self.train.update(batch["index"].tolist())

        def on_validation_batch_start(self, trainer, module, batch, batch_idx, dataloader_idx=0):
            self.val.update(batch["index"].tolist())

    def encoder():
        if kind == "lstm":
            return LSTMBaseline(n_filter=8, network={"hidden": 8}, metrics=["mse"], validate_held_out=True)
        return StateEncoderModule(
            str(ckpt), n_filter=8, encoder={"preset": "vector", "hidden": 8}, metrics=["mse"], validate_held_out=True
        )

    seen = Seen()
    fast_trainer(tmp, max_epochs=2, callbacks=[seen]).fit(encoder(), rotation_dm(tmp))
    assert seen.val == {0, 7} and seen.train == {1, 2, 3, 4, 5, 6}
    none = RotationDataModule(data_dir=str(tmp / "data"), seq_len=12, batch_size=4, val_trajectories=0)
    steps = Seen()
    with pytest.raises(ValueError, match=r"validate_held_out .* set data.init_args.val_trajectories > 0"):
        fast_trainer(tmp, max_epochs=1, callbacks=[steps]).fit(encoder(), none)
    assert not steps.train
    every = RotationDataModule(data_dir=str(tmp / "data"), seq_len=12, batch_size=4, val_trajectories=8)
    with pytest.raises(ValueError, match=r"holds out all 8 training trajectories .* below 8"):
        fast_trainer(tmp, max_epochs=1, callbacks=[steps]).fit(encoder(), every)
    assert not steps.train


def test_fewer_test_sequences_are_tested_and_said(exact_ssm):
    """The test split's size does not determine the training data: an encoder trains and tests with n_test 2 (the
    SSM's data had 4), reads only the test split when it tests, and the results file says how many it scored and
    that the test data differ from the SSM's."""
    tmp, ckpt = exact_ssm
    fit_dm = RotationDataModule(data_dir=str(tmp / "data"), seq_len=12, n_test=2, batch_size=4, val_trajectories=2)
    enc = StateEncoderModule(
        str(ckpt),
        n_filter=8,
        encoder={"preset": "vector", "hidden": 8},
        metrics=["mse"],
        results_dir=str(tmp / "results"),
        experiment="rot_fewer",
    )
    fast_trainer(tmp, max_epochs=1).fit(enc, fit_dm)
    test_dm = RotationDataModule(data_dir=str(tmp / "fresh"), seq_len=12, n_test=2, batch_size=4)
    fast_trainer(tmp, max_epochs=1).test(enc, test_dm)
    assert test_dm.is_cached("test") and not test_dm.is_cached("train")  # the test read its own split only
    assert "train" not in test_dm.datasets
    text = render_file(tmp / "results" / "rot_fewer.json").read_text()
    assert "test_sequences: 2" in text
    assert "'n_test': (4, 2)" in text


def test_a_test_stage_generates_only_the_test_split(tmp_path):
    """Under a trainer testing, prepare_data generates the test split alone; what the test needs from the training
    data (normalisation, mean measurement, shape) comes from a checkpoint's DataModule state."""
    from lightning.pytorch.trainer.states import TrainerFn

    trained = RotationDataModule(data_dir=str(tmp_path / "a"), normalize=True, seq_len=12)
    trained.prepare_data()
    trained.setup("fit")
    state = trained.state_dict()
    y = np.load(trained.split_file("train", "y")).astype(np.float64)
    np.testing.assert_allclose(state["mean_measurement"].numpy(), y.mean(axis=(0, 1)), rtol=1e-5)  # all 8 < 1000

    fresh = RotationDataModule(data_dir=str(tmp_path / "b"), normalize=True, seq_len=12)
    trainer = pl.Trainer(logger=False, enable_progress_bar=False)
    trainer.state.fn = TrainerFn.TESTING
    fresh.trainer = trainer
    fresh.prepare_data()
    assert fresh.is_cached("test") and not fresh.is_cached("train")
    fresh.setup("test")
    fresh.load_state_dict(state)
    batch = next(iter(fresh.test_dataloader()))
    raw = np.load(fresh.split_file("test", "y"))[:4]
    mean, std = state["normalizer"]["mean"].numpy(), state["normalizer"]["std"].numpy()
    np.testing.assert_allclose(batch["y"].numpy(), (raw - mean) / std, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(fresh.mean_measurement(), state["mean_measurement"])
    assert not fresh.is_cached("train") and "train" not in fresh.datasets


def test_encoder_refuses_measurements_of_another_shape(exact_ssm):
    tmp, ckpt = exact_ssm
    enc = StateEncoderModule(str(ckpt), n_filter=8, encoder={"preset": "vector", "hidden": 8})
    with pytest.raises(ValueError, match=r"built for measurements of shape \[1\], got \[3\]"):
        enc.encoder(torch.zeros(2, 5, 3))


def test_particle_filter_stage_tracks_the_exact_model(exact_ssm):
    tmp, ckpt = exact_ssm
    dm = rotation_dm(tmp)
    pf = FilterForecaster(
        str(ckpt),
        n_filter=8,
        method="pf",
        n_particles=2000,
        measurement_var=0.05**2,
        init_var=1.0,
        metrics=["mse"],
        results_dir=str(tmp / "results"),
        experiment="rot_pf",
    )
    fast_trainer(tmp, max_epochs=1).test(pf, dm)
    saved = json.loads((tmp / "results" / "rot_pf.json").read_text())["runs"]["pf"]["summary"]
    assert saved["pf/clean/mse"]["mean"] < 0.1 * saved["mean/clean/mse"]["mean"]
