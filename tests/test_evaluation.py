"""The forecasting protocol: metrics against hand computations, frame bookkeeping with an exact model,
the encoder stage on a tiny trained checkpoint, the UKF stage, results files and bad input."""

import json
import math

import lightning.pytorch as pl
import numpy as np
import pytest
import torch
from lightning.pytorch.callbacks import ModelCheckpoint

from ssm_ms.forecasting.protocol import (
    ValidTimeAccumulator,
    bce_per_sequence,
    mse_per_sequence,
    mse_sum_per_sequence,
    sequence_metrics,
    sequence_summary,
    split_sequence,
    ssim_per_sequence,
)
from ssm_ms.inference.encoder_module import StateEncoderModule
from ssm_ms.inference.filter_module import FilterForecaster
from ssm_ms.inference.ssm_forecaster import SSMForecaster
from ssm_ms.module import MultipleShootingModule
from ssm_ms.nets import Projection
from tests.conftest import ExactRotation, RotationDataModule, fast_trainer


# ---------------------------------------------------------------------------- metrics
def test_mse_and_bce_against_hand_computation():
    torch.manual_seed(0)
    pred = torch.rand(3, 4, 1, 2, 2, dtype=torch.float64) * 0.98 + 0.01
    target = torch.rand(3, 4, 1, 2, 2, dtype=torch.float64)
    for b in range(3):
        se, bce_mean, bce_sum = 0.0, 0.0, 0.0
        for t in range(4):
            frame_bce = 0.0
            for i in range(2):
                for j in range(2):
                    p, q = pred[b, t, 0, i, j].item(), target[b, t, 0, i, j].item()
                    se += (p - q) ** 2
                    frame_bce += -(q * math.log(p + 1e-12) + (1 - q) * math.log(1 - p + 1e-12))
            bce_mean += frame_bce / 4
            bce_sum += frame_bce
        assert mse_per_sequence(pred, target)[b].item() == pytest.approx(se / 16)
        assert bce_per_sequence(pred, target, "mean")[b].item() == pytest.approx(bce_mean / 4)
        assert bce_per_sequence(pred, target, "sum")[b].item() == pytest.approx(bce_sum / 4)


def test_mse_summed_over_a_frame_against_hand_computation():
    torch.manual_seed(1)
    pred, target = torch.rand(2, 3, 1, 2, 3, dtype=torch.float64), torch.rand(2, 3, 1, 2, 3, dtype=torch.float64)
    for b in range(2):
        frames = [sum((pred[b, t, 0, i, j].item() - target[b, t, 0, i, j].item()) ** 2 for i in range(2) for j in range(3))
                  for t in range(3)]
        assert mse_sum_per_sequence(pred, target)[b].item() == pytest.approx(sum(frames) / 3)


def naive_ssim(a: list, b: list, k: int = 11, sigma: float = 1.5) -> float:
    """Wang et al.'s SSIM of two grey frames by loops: Gaussian-weighted means, variances and covariance over every
    window position that lies inside the frame, ``C1 = 0.01^2``, ``C2 = 0.03^2`` (data range 1), averaged."""
    r = k // 2
    g = [math.exp(-((i - r) ** 2) / (2 * sigma**2)) for i in range(k)]
    g = [v / sum(g) for v in g]
    h, w = len(a), len(a[0])
    values = []
    for i in range(r, h - r):
        for j in range(r, w - r):
            m = {"a": 0.0, "b": 0.0, "aa": 0.0, "bb": 0.0, "ab": 0.0}
            for u in range(k):
                for v in range(k):
                    wt, pa, pb = g[u] * g[v], a[i - r + u][j - r + v], b[i - r + u][j - r + v]
                    m["a"] += wt * pa
                    m["b"] += wt * pb
                    m["aa"] += wt * pa * pa
                    m["bb"] += wt * pb * pb
                    m["ab"] += wt * pa * pb
            va, vb, cab = m["aa"] - m["a"] ** 2, m["bb"] - m["b"] ** 2, m["ab"] - m["a"] * m["b"]
            values.append((2 * m["a"] * m["b"] + 1e-4) * (2 * cab + 9e-4)
                          / ((m["a"] ** 2 + m["b"] ** 2 + 1e-4) * (va + vb + 9e-4)))
    return sum(values) / len(values)


def test_ssim_against_a_loop_over_windows():
    torch.manual_seed(2)
    target = torch.rand(2, 2, 1, 13, 14, dtype=torch.float64)
    pred = (target + 0.3 * torch.randn_like(target)).clamp(0, 1)
    got = ssim_per_sequence(pred, target)
    for b in range(2):
        frames = [naive_ssim(pred[b, t, 0].tolist(), target[b, t, 0].tolist()) for t in range(2)]
        assert got[b].item() == pytest.approx(sum(frames) / 2, rel=1e-9)
    assert 0.2 < got.min() < got.max() < 0.95  # a noisy copy: neither identical nor unrelated
    assert ssim_per_sequence(target, target).tolist() == pytest.approx([1.0, 1.0])
    assert sequence_metrics(pred, target, ["ssim", "mse_sum"], "mean")["ssim"].tolist() == got.tolist()


def test_ssim_refuses_frames_it_cannot_score():
    with pytest.raises(ValueError, match="metric 'ssim' needs image frames .* at least 11 x 11 pixels, got \\[2, 5, 3\\]"):
        ssim_per_sequence(torch.zeros(2, 5, 3), torch.zeros(2, 5, 3))


def test_bce_of_saturated_predictions_is_finite():
    pred = torch.tensor([[[0.0, 1.0]]])
    target = torch.tensor([[[1.0, 0.0]]])
    assert bce_per_sequence(pred, target).item() == pytest.approx(-math.log(1e-12))


def test_valid_time_of_images_scales_by_the_mean_per_pixel_variance():
    """Images pool their pixels: mean squared error over the mean per-pixel variance of the truth, so a
    forecast as bad as the mean frame has normalised error 1; constant background pixels divide nothing."""
    torch.manual_seed(0)
    truth = torch.rand(2, 3, 6, 1, 2, 2, dtype=torch.float64)  # two batches of 3 sequences, 6 steps
    truth[..., 0, 0] = 0.0  # a background pixel
    growth = torch.linspace(0.0, 1.0, 6, dtype=torch.float64).view(1, 1, 6, 1, 1, 1)  # errors grow over time,
    size = torch.tensor([0.02, 0.1, 0.2, 0.3, 0.4, 0.6], dtype=torch.float64).view(2, 3, 1, 1, 1, 1)  # more or less
    pred = truth + torch.randn_like(truth) * growth * size
    acc = ValidTimeAccumulator()
    for b in range(2):
        acc.update(pred[b], truth[b])
    steps, horizon = acc.steps(0.5)
    all_truth = truth.reshape(6, 6, 4)  # [sequence, step, pixel]
    pixel_var = all_truth.reshape(-1, 4).var(0, unbiased=False).mean()
    expected = []
    for seq_pred, seq_truth in zip(pred.reshape(6, 6, 4), all_truth):
        err = ((seq_pred - seq_truth) ** 2).mean(1) / pixel_var
        expected.append(next((t for t in range(6) if err[t].sqrt() > 0.5), math.inf))
    assert horizon == 6 and steps.tolist() == expected
    curve = torch.stack([(((sp - st) ** 2).mean(1) / pixel_var).sqrt() for sp, st in zip(pred.reshape(6, 6, 4), all_truth)])
    assert acc.growth() == pytest.approx({"1": 0.0, "3": curve[:, 2].mean().item(), "6": curve[:, 5].mean().item()})
    assert 0 < sum(e != math.inf for e in expected) < 6  # the case is not trivial


def test_error_growth_leaves_out_a_diverged_forecast():
    """A forecast that turned NaN (a filter that diverged) is left out of the mean error curve, as out of the
    scores; the others' curve is their plain mean of |error| / std (vectors: per component, then averaged)."""
    torch.manual_seed(1)
    truth = torch.randn(4, 8, 2, dtype=torch.float64)
    pred = truth + 0.1 * torch.randn_like(truth) * torch.arange(1, 9, dtype=torch.float64).view(1, 8, 1)
    pred[2, 5:] = math.nan
    acc = ValidTimeAccumulator()
    acc.update(pred[:2], truth[:2])
    acc.update(pred[2:], truth[2:])
    std = truth.reshape(-1, 2).std(0, unbiased=False)
    kept = [0, 1, 3]
    curve = [sum(((pred[i, t] - truth[i, t]) ** 2 / std**2).mean().sqrt().item() for i in kept) / 3 for t in range(8)]
    assert acc.growth() == pytest.approx({"1": curve[0], "2": curve[1], "4": curve[3], "8": curve[7]})
    assert acc.steps(10.0)[0].tolist() == [math.inf, math.inf, 5, math.inf]  # still counted, invalid from its NaN


def test_filter_lengths_longer_than_the_sequences_are_refused():
    y = torch.zeros(2, 20, 1)
    assert [t.shape[1] for t in split_sequence(y, 15)] == [15, 5]
    assert [t.shape[1] for t in split_sequence(y, 10, 4)] == [10, 4]
    with pytest.raises(ValueError, match="cannot filter 20 and predict 0 frames of sequences of length 20"):
        split_sequence(y, 20)
    with pytest.raises(ValueError, match="cannot filter 15 and predict 10 frames of sequences of length 20"):
        split_sequence(y, 15, 10)


# ---------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def exact_ssm(tmp_path_factory):
    """An SSM whose f is the data's true rotation (trained briefly: nodes only matter for the encoder)."""
    tmp = tmp_path_factory.mktemp("exact")
    dm = RotationDataModule(data_dir=str(tmp / "data"), seq_len=12, batch_size=4, val_trajectories=2)
    model = MultipleShootingModule(ExactRotation(0.3, learnable=False), Projection([0]), state_dim=2, n_nodes=3, lr=0.05)
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

    def infer(self, y_filter):
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
    report = (tmp / "results" / "rot.md").read_text()
    assert "| SSM (ExactRotation) + oracle |" in report and "| last (reference, with SSM (ExactRotation) + oracle) |" in report


def test_sequence_summary_leaves_diverged_sequences_out_and_counts_them():
    scores = [0.5, float("nan"), 1.5, float("inf"), 4.0]
    finite = [0.5, 1.5, 4.0]
    mean = sum(finite) / 3
    got = sequence_summary(torch.tensor(scores))
    assert (got["n"], got["non_finite"]) == (5, 2)
    assert got["mean"] == pytest.approx(mean)
    assert got["std"] == pytest.approx(math.sqrt(sum((v - mean) ** 2 for v in finite) / 3))
    none = sequence_summary(torch.full((3,), float("nan")))
    assert (none["n"], none["non_finite"]) == (3, 3) and math.isnan(none["mean"])


class DivergingOracle(Oracle):
    """The true states, except for the test sequences whose index is in ``diverged``: NaN (a filter that blew up)."""

    def __init__(self, *args, diverged=(), **kwargs):
        super().__init__(*args, **kwargs)
        self.diverged = set(diverged)

    def infer(self, y_filter):
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
    oracle = DivergingOracle(str(ckpt), n_filter=8, metrics=["mse"], results_dir=str(tmp / "results"), experiment=name,
                             diverged=diverged, analysis={"valid_time": {}})
    fast_trainer(tmp, max_epochs=1).test(oracle, rotation_dm(tmp))
    saved = json.loads((tmp / "results" / f"{name}.json").read_text())["runs"]["oracle"]["summary"]
    entry = saved["oracle/clean/mse"]
    assert (entry["n"], entry["non_finite"]) == (4, len(diverged))
    assert saved["last/clean/mse"]["non_finite"] == len(diverged)  # the reference uses the method's last estimate
    assert saved["mean/clean/mse"]["non_finite"] == 0
    report = (tmp / "results" / f"{name}.md").read_text()
    if len(diverged) == 4:
        assert "non-finite on all 4 sequences" in report
    else:
        assert entry["mean"] < 1e-10  # the two others are exact
        assert f"(non-finite on {len(diverged)} of 4 sequences, left out)" in report


def test_analysis_of_the_exact_model(exact_ssm):
    """The exact rotation as f: forecasts from exact states never leave the truth (valid time infinite: censored
    at the horizon), f is neither expanding nor contracting (exponents 0), and its free runs decoded have the
    data's distribution (x = cos of a uniform phase)."""
    tmp, ckpt = exact_ssm
    dm = rotation_dm(tmp)
    analysis = {"valid_time": {"n_filter": 4, "horizon": 8}, "dt": 0.1,
                "dynamics": {"runs": 4, "free_runs": 6, "lyapunov_steps": 300, "transient": 10, "align": 10,
                             "free_steps": 2000}}
    oracle = Oracle(str(ckpt), n_filter=8, metrics=["mse"], results_dir=str(tmp / "results"), experiment="rot_an",
                    analysis=analysis)
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
    assert "## Analysis" in (tmp / "results" / "rot_an.md").read_text()
    with pytest.raises(ValueError, match=r"analysis.valid_time takes \['horizon', 'n_filter', 'threshold'\], got \['steps'\]"):
        Oracle(str(ckpt), n_filter=8, analysis={"valid_time": {"steps": 3}})
    with pytest.raises(ValueError, match="unknown analysis section 'chaos'"):
        Oracle(str(ckpt), n_filter=8, analysis={"chaos": {}})


def test_encoder_stage_on_a_tiny_trained_checkpoint(exact_ssm):
    tmp, ckpt = exact_ssm
    dm = rotation_dm(tmp)
    enc = StateEncoderModule(str(ckpt), n_filter=8, encoder={"preset": "vector", "hidden": 32}, lr=1e-2,
                             metrics=["mse"], results_dir=str(tmp / "results"), experiment="rot_enc")
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


def test_ssim_on_vector_data_is_refused_before_any_sequence_is_scored(exact_ssm):
    tmp, ckpt = exact_ssm
    ukf = FilterForecaster(str(ckpt), n_filter=8, method="ukf", metrics=["mse", "ssim"],
                           results_dir=str(tmp / "results"), experiment="rot_ssim")
    ukf.test_step = lambda *a, **k: pytest.fail("a sequence was scored")
    with pytest.raises(ValueError, match="metric 'ssim' needs image frames"):
        fast_trainer(tmp, max_epochs=1).test(ukf, rotation_dm(tmp))
    assert not (tmp / "results" / "rot_ssim.json").exists()


def test_ukf_stage_tracks_the_exact_model(exact_ssm):
    tmp, ckpt = exact_ssm
    dm = rotation_dm(tmp)
    ukf = FilterForecaster(str(ckpt), n_filter=8, method="ukf", measurement_var=0.05**2, init_var=1.0,
                           metrics=["mse"], results_dir=str(tmp / "results"), experiment="rot_ukf")
    fast_trainer(tmp, max_epochs=1).test(ukf, dm)
    saved = json.loads((tmp / "results" / "rot_ukf.json").read_text())["runs"]["ukf"]["summary"]
    # noise std 0.05 on a unit circle: the filtered phase is accurate, the forecast too
    assert saved["ukf/clean/mse"]["mean"] < 0.01
    assert saved["ukf/clean/mse"]["mean"] < 0.1 * saved["mean/clean/mse"]["mean"]
    # f and g in bfloat16 and the cubature rule, labelled as another method of the same experiment:
    # as accurate, and the results say how the states were inferred
    fast = FilterForecaster(str(ckpt), n_filter=8, method="ukf", measurement_var=0.05**2, init_var=1.0,
                            autocast="bfloat16", unscented={"beta": 0.0}, method_name="ukf_fast", metrics=["mse"],
                            results_dir=str(tmp / "results"), experiment="rot_ukf")
    assert fast.filter.beta == 0.0
    fast_trainer(tmp, max_epochs=1).test(fast, dm)
    runs = json.loads((tmp / "results" / "rot_ukf.json").read_text())["runs"]
    assert set(runs) == {"ukf", "ukf_fast"}
    assert runs["ukf_fast"]["summary"]["ukf_fast/clean/mse"]["mean"] < 0.01
    assert runs["ukf"]["info"]["inference_settings"].endswith("alpha=1, beta=2, kappa=0; full precision")
    assert runs["ukf_fast"]["info"]["inference_settings"].endswith("alpha=1, beta=0, kappa=0; f and g under autocast(bfloat16)")
    assert "f and g under autocast(bfloat16)" in (tmp / "results" / "rot_ukf.md").read_text()
    with pytest.raises(ValueError, match=r"unscented takes alpha, beta and kappa, got \['gamma'\]"):
        FilterForecaster(str(ckpt), n_filter=8, unscented={"gamma": 1.0})
    with pytest.raises(ValueError, match="no effect with method 'pf'"):
        FilterForecaster(str(ckpt), n_filter=8, method="pf", unscented={"beta": 0.0})


# ---------------------------------------------------------------------------- bad input
def test_missing_checkpoint_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"the SSM checkpoint .*nope.ckpt does not exist: train the model first"):
        StateEncoderModule(str(tmp_path / "nope.ckpt"), n_filter=5)


def test_checkpoint_of_another_data_set_is_refused(exact_ssm):
    tmp, ckpt = exact_ssm
    other = RotationDataModule(data_dir=str(tmp / "data"), seq_len=12, omega=0.5, batch_size=4)
    trainer = fast_trainer(tmp, max_epochs=1)
    with pytest.raises(ValueError, match=r"trained on other data: data parameters differ .*'omega': \(0.3, 0.5\)"):
        trainer.fit(StateEncoderModule(str(ckpt), n_filter=8, encoder={"preset": "vector", "hidden": 8}), other)


def test_fewer_test_sequences_are_tested_and_said(exact_ssm):
    """The test split's size does not determine the training data: an encoder trains and tests with n_test 2 (the
    SSM's data had 4), reads only the test split when it tests, and the results file says how many it scored and
    that the test data differ from the SSM's."""
    tmp, ckpt = exact_ssm
    fit_dm = RotationDataModule(data_dir=str(tmp / "data"), seq_len=12, n_test=2, batch_size=4, val_trajectories=2)
    enc = StateEncoderModule(str(ckpt), n_filter=8, encoder={"preset": "vector", "hidden": 8}, metrics=["mse"],
                             results_dir=str(tmp / "results"), experiment="rot_fewer")
    fast_trainer(tmp, max_epochs=1).fit(enc, fit_dm)
    test_dm = RotationDataModule(data_dir=str(tmp / "fresh"), seq_len=12, n_test=2, batch_size=4)
    fast_trainer(tmp, max_epochs=1).test(enc, test_dm)
    assert test_dm.is_cached("test") and not test_dm.is_cached("train")  # the test read its own split only
    assert "train" not in test_dm.datasets
    text = (tmp / "results" / "rot_fewer.md").read_text()
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
    pf = FilterForecaster(str(ckpt), n_filter=8, method="pf", n_particles=2000, measurement_var=0.05**2,
                          init_var=1.0, metrics=["mse"], results_dir=str(tmp / "results"), experiment="rot_pf")
    fast_trainer(tmp, max_epochs=1).test(pf, dm)
    saved = json.loads((tmp / "results" / "rot_pf.json").read_text())["runs"]["pf"]["summary"]
    assert saved["pf/clean/mse"]["mean"] < 0.1 * saved["mean/clean/mse"]["mean"]


def test_valid_time_of_images_counts_the_error_above_the_reconstruction_floor():
    """A forecaster whose decoder blurs every frame by the same amount (its reconstruction of the given frames
    included) and loses the object after s steps: valid for exactly s steps, counted by hand above its floor;
    without the given frames the blur alone reads as invalid from the first step."""
    torch.manual_seed(1)
    n, h, m = 5, 12, 4
    truth = (torch.rand(n, m + h, 1, 6, 6, dtype=torch.float64) > 0.7).double()  # sparse "lit" pixels
    blur = 0.4 * torch.randn(n, 1, 1, 6, 6, dtype=torch.float64)  # the decoder's error, the same on every frame
    lost = torch.tensor([0, 3, 7, 11, 12])  # step at which each sequence's forecast loses the object
    est = truth + blur
    for i, s in enumerate(lost.tolist()):
        est[i, m + s :] = truth[i, m + s :].roll(3, dims=-1) + blur[i]  # drawn elsewhere, same blur
    acc = ValidTimeAccumulator()
    acc.update(est[:, m:], truth[:, m:], given=(est[:, :m], truth[:, :m]))
    steps, horizon = acc.steps(0.5)
    # by hand: pooled variance, per-sequence floor from the given frames, error above it, first step over 0.5
    values = truth[:, m:].reshape(-1, 36)
    var = values.var(0, unbiased=False).mean()
    expected = []
    for i in range(n):
        floor = ((est[i, :m] - truth[i, :m]) ** 2).mean()
        err = [(((est[i, m + t] - truth[i, m + t]) ** 2).mean() - floor).clamp_min(0).div(var).sqrt() for t in range(h)]
        expected.append(next((t for t in range(h) if err[t] > 0.5), math.inf))
    assert horizon == h and steps.tolist() == expected
    assert expected[1:] == [3.0, 7.0, 11.0, math.inf] and expected[0] == 0.0  # as constructed
    assert acc.floor() == pytest.approx(float(((est[:, :m] - truth[:, :m]) ** 2).flatten(1).mean(1).div(var).sqrt().mean()))
    assert acc.floor() > 0.5  # the blur alone is over the threshold:
    plain = ValidTimeAccumulator()
    plain.update(est[:, m:], truth[:, m:])
    assert plain.steps(0.5)[0].tolist() == [0.0] * n and plain.floor() == 0.0
