"""The Python API (``from ssm_ms import Recordings, SSM, fit``): arrays in the user's units in and out, checked against
computations by hand (a naive loop over f and g, the statistics computed with numpy), the same weights as ``cli.py``
for the same fit, the paper's schedule when none is given, one message for each mistake."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import yaml
from lightning.pytorch.callbacks import Callback

import ssm_ms
from ssm_ms import SSM, Recordings, fit
from ssm_ms.cli import main as cli_main
from ssm_ms.inference import FilterForecaster, UnscentedKalmanFilter
from ssm_ms.module import MultipleShootingModule

SMALL_F = {"n_matrices": 2, "hidden": 8}


def driven_recordings(n: int = 6, t: int = 40, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` recordings of a damped oscillator driven by a random input, seen through its position, in units far
    from 0 and 1 (so that a forgotten normalisation shows)."""
    rng = np.random.default_rng(seed)
    u = rng.normal(2.0, 0.5, size=(n, t, 1)).astype(np.float32)
    x = np.zeros((n, 2))
    y = np.zeros((n, t, 1), dtype=np.float32)
    for k in range(t):
        y[:, k, 0] = 100.0 + 30.0 * x[:, 0] + rng.normal(0, 0.3, n)
        x = np.stack([x[:, 0] + 0.1 * x[:, 1], x[:, 1] - 0.1 * x[:, 0] - 0.02 * x[:, 1] + 0.1 * (u[:, k, 0] - 2)], 1)
    return y, u


@pytest.fixture(scope="module")
def driven():
    y, u = driven_recordings()
    data = Recordings(y=y, u=u, dt=0.1, batch_size=3)
    return y, u, data, SSM(data, state_dim=2, f_options=SMALL_F)


def test_import_ssm_ms_exports_the_api():
    assert set(ssm_ms.__all__) == {"SSM", "Recordings", "fit"}
    assert ssm_ms.SSM is SSM and ssm_ms.fit is fit


def test_the_model_sizes_itself_from_the_data(driven):
    y, u, data, model = driven
    assert model.state_dim == 2 and model.input_dim == 1
    assert model.module.n_nodes == 2  # 40 samples: the fewest pieces of at most 25 samples
    assert tuple(model.module.obs_shape()) == (1,)
    assert model.module.nodes.num_embeddings == data.num_train_trajectories == 6


def test_simulate_is_a_loop_over_f_and_g_in_the_user_units(driven, tmp_path):
    y, u, data, model = driven
    fit(model, data, epochs=1, save_dir=tmp_path, enable_progress_bar=False, logger=False)
    # the statistics by hand: per component over every training sample
    y_mean, y_std = y.reshape(-1, 1).astype(np.float64).mean(0), y.reshape(-1, 1).astype(np.float64).std(0)
    u_mean, u_std = u.reshape(-1, 1).astype(np.float64).mean(0), u.reshape(-1, 1).astype(np.float64).std(0)
    u_new = np.random.default_rng(5).normal(2.0, 0.5, size=(30, 1)).astype(np.float32)
    x0 = np.array([0.3, -0.2], dtype=np.float32)
    got = model.simulate(u_new, x0=x0, chunk=7)  # chunks that do not divide the length
    assert isinstance(got, np.ndarray) and got.shape == (30, 1)
    expected, x = [], torch.tensor(x0)[None]
    with torch.no_grad():
        for t in range(30):
            expected.append(model.g(x)[0].double().numpy() * y_std + y_mean)
            x = model.f(x, torch.tensor((u_new[t] - u_mean) / u_std, dtype=torch.float32)[None])
    np.testing.assert_allclose(got, np.stack(expected), rtol=1e-4, atol=1e-3)
    # a batch of two is the two simulations; a tensor in gives a tensor out
    batch = model.simulate(torch.tensor(np.stack([u_new, u_new])), x0=torch.tensor(np.stack([x0, x0])))
    assert isinstance(batch, torch.Tensor) and batch.shape == (2, 30, 1)
    np.testing.assert_allclose(batch[1].numpy(), got, rtol=1e-5, atol=1e-4)


def test_the_state_from_the_first_samples_is_the_ukf_s_and_the_simulation_goes_on_from_it(driven, tmp_path):
    y, u, data, model = driven
    y_init, u_init, u_next = y[0, :20], u[0, :20], u[0, 20:]
    got = model.simulate(u_next, y_init=y_init, u_init=u_init, measurement_var=0.09, process_var=1e-4)
    # by hand: the UKF on f and g in the model's units, the measurement noise scaled by the data's variance
    units = model.units
    y_n = units.y_to_model(torch.tensor(y_init)[None])
    u_n = units.u_to_model(torch.tensor(u[0])[None])
    std = float(y[..., 0].astype(np.float64).std())
    ukf = UnscentedKalmanFilter(model.f, model.g, process_var=1e-4, measurement_var=0.09 / std**2, init_var=0.1)
    prior = model.module.nodes.weight.detach().view(-1, 2).mean(0)
    with torch.no_grad():
        means = ukf.filter(y_n, prior[None], u=u_n[:, :19]).means
        x = model.f(means[:, -1], u_n[:, 19])
        expected = []
        for t in range(20):
            expected.append(units.y_to_user(model.g(x))[0].numpy())
            x = model.f(x, u_n[:, 20 + t])
    np.testing.assert_allclose(got, np.stack(expected), rtol=1e-4, atol=1e-3)
    # forecast() is the same thing, given the whole inputs
    np.testing.assert_allclose(
        model.forecast(y_init, 20, u=u[0], measurement_var=0.09, process_var=1e-4), got, rtol=1e-5, atol=1e-4
    )
    x_f, p_f = model.filter(y_init, u=u_init, measurement_var=0.09, process_var=1e-4)
    assert x_f.shape == (20, 2) and p_f.shape == (20, 2, 2)
    np.testing.assert_allclose(x_f, means[0].numpy(), rtol=1e-5, atol=1e-5)


def test_a_filter_built_on_the_model_works_in_the_user_units(driven):
    """``UnscentedKalmanFilter(*model.in_units())`` on raw measurements is the filter on normalised ones."""
    y, u, data, model = driven
    std = float(y[..., 0].astype(np.float64).std())
    y_raw = torch.tensor(y[:2])
    in_units = UnscentedKalmanFilter(*model.in_units(), measurement_var=0.09, process_var=1e-4, init_var=0.1)
    normalised = UnscentedKalmanFilter(model.f, model.g, measurement_var=0.09 / std**2, process_var=1e-4, init_var=0.1)
    with torch.no_grad():
        a = in_units.filter(y_raw, u=torch.tensor(u[:2, :-1])).means
        b = normalised.filter(model.units.y_to_model(y_raw), u=model.units.u_to_model(torch.tensor(u[:2, :-1]))).means
    torch.testing.assert_close(a, b, rtol=1e-3, atol=1e-4)
    # and a forecaster takes the model object as well as a checkpoint path
    forecaster = FilterForecaster(model, n_filter=20, method="ukf")
    assert forecaster.ssm is model.module and forecaster.hparams["ssm_checkpoint"] is None


class Probe(Callback):
    """Alpha and lr at each epoch's first batch (the schedule has set them by then)."""

    def __init__(self):
        self.seen = {}

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        self.seen.setdefault(
            trainer.current_epoch, (float(pl_module.alpha), trainer.optimizers[0].param_groups[0]["lr"])
        )


def test_a_fit_without_a_schedule_runs_the_paper_s_scaled_to_its_epochs(tmp_path):
    y, u = driven_recordings()
    data = Recordings(y=y, u=u, batch_size=6)
    model = SSM(data, state_dim=2, f_options=SMALL_F, lr=1e-3)
    probe = Probe()
    fit(model, data, epochs=10, save_dir=tmp_path, callbacks=[probe], enable_progress_bar=False, logger=False)
    # the paper: alpha 1 -> 1000 with lr / 10 at epoch 200 of 1000, lr / 10 again at 600: here 2 and 6 of 10
    assert [probe.seen[e][0] for e in range(10)] == [1.0, 1.0] + [1000.0] * 8
    lrs = [probe.seen[e][1] for e in range(10)]
    assert lrs == pytest.approx([1e-3] * 2 + [1e-4] * 4 + [1e-5] * 4)


def test_save_and_load_keep_the_units_and_the_weights(driven, tmp_path):
    y, u, data, model = driven
    path = model.save(tmp_path / "model.ckpt")
    back = SSM.load(path)
    assert isinstance(back.module, MultipleShootingModule)
    x0 = np.array([0.1, 0.2], dtype=np.float32)
    np.testing.assert_allclose(back.simulate(u[0], x0=x0), model.simulate(u[0], x0=x0), rtol=1e-6)
    y_mean = y.reshape(-1).astype(np.float64).mean()
    np.testing.assert_allclose(back.units.y_to_user(torch.zeros(1, 1)).item(), y_mean, rtol=1e-5)


def test_mistakes_get_one_message(driven):
    y, u, data, model = driven
    with pytest.raises(ValueError, match="give state_dim"):
        SSM(data)
    with pytest.raises(ValueError, match="f must be one of"):
        SSM(data, state_dim=2, f="rnn")
    with pytest.raises(ValueError, match="give a training budget"):
        fit(model, data)
    with pytest.raises(ValueError, match="time must be"):
        fit(model, data, time="soon")
    with pytest.raises(ValueError, match=r"u must be \[T, 1\]"):
        model.simulate(np.zeros((10, 3)), x0=np.zeros(2))
    with pytest.raises(ValueError, match="driven by 1 inputs per step: give u"):
        model.simulate(steps=10)
    with pytest.raises(ValueError, match="NaN or inf"):
        model.simulate(np.full((10, 1), np.nan), x0=np.zeros(2))
    with pytest.raises(ValueError, match="u_init holds 5 inputs per sequence, the measurements need 10"):
        model.simulate(u[0], y_init=y[0, :10], u_init=u[0, :5])
    with pytest.raises(ValueError, match="method must be one of"):
        model.filter(y[0], u=u[0], method="magic")
    with pytest.raises(ValueError, match="needs a trained encoder"):
        model.filter(y[0], u=u[0], method="encoder")


def test_a_fit_through_the_api_and_through_cli_py_give_the_same_weights(tmp_path):
    """The same data (a file for cli.py, arrays for the API), the same seed and settings: the same weights after two
    epochs (the paper's schedule added to both, as neither names one)."""
    y, u = driven_recordings(n=4, t=20)
    np.savez(tmp_path / "rec.npz", y=y, u=u)
    config = {
        "seed_everything": 0,
        "trainer": {"max_epochs": 2, "logger": False, "enable_progress_bar": False, "default_root_dir": str(tmp_path)},
        "model": {
            "class_path": "ssm_ms.module.MultipleShootingModule",
            "init_args": {
                "n_nodes": 2,
                "f": {
                    "class_path": "ssm_ms.nets.LocallyLinearTransition",
                    "init_args": {"state_dim": 2, "input_dim": 1, **SMALL_F},
                },
                "g": {"class_path": "ssm_ms.nets.LinearReadout", "init_args": {"state_dim": 2, "out_features": 1}},
            },
        },
        "data": {
            "class_path": "datamodules.files.FileDataModule",
            "init_args": {
                "train_path": str(tmp_path / "rec.npz"),
                "input_key": "u",
                "normalize": True,
                "batch_size": 2,
            },
        },
    }
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(config))
    cli = cli_main(["fit", "--config", str(tmp_path / "config.yaml")])
    data = Recordings(y=y, u=u, batch_size=2)
    model = SSM(data, state_dim=2, f_options=SMALL_F, n_nodes=2, seed=0)
    fit(model, data, epochs=2, logger=False, enable_progress_bar=False, save_dir=tmp_path / "api")
    ours, theirs = model.module.state_dict(), cli.model.state_dict()
    assert set(ours) == set(theirs)
    for key in ours:
        torch.testing.assert_close(ours[key], theirs[key], rtol=0, atol=0, msg=key)
    assert cli.model.data_state["normalizer"]["mean"].tolist() == pytest.approx(
        model.module.data_state["normalizer"]["mean"].tolist()
    )


def test_images_and_several_sensors_go_through_the_same_calls(tmp_path):
    """Grey frames ``[N, T, H, W]``: g is the paper's decoder; a dict of a camera and an angle sensor (the angle at
    every other sample, NaN between): g one head per stream, simulate returns a dict; both against the loop."""
    rng = np.random.default_rng(0)
    frames = rng.random((4, 20, 24, 24)).astype(np.float32)
    data = Recordings(y=frames, batch_size=2)
    model = SSM(data, state_dim=3, f_options=SMALL_F, loss="bce")
    assert type(model.g).__name__ == "ConvDecoder" and model.units.is_identity  # images: not normalised
    fit(model, data, epochs=1, save_dir=tmp_path, logger=False, enable_progress_bar=False)
    x0 = np.zeros(3, dtype=np.float32)
    got = model.simulate(steps=5, x0=x0)
    assert got.shape == (5, 1, 24, 24)
    with torch.no_grad():
        x, expected = torch.zeros(1, 3), []
        for _ in range(5):
            expected.append(model.g(x)[0].numpy())
            x = model.f(x)
    np.testing.assert_allclose(got, np.stack(expected), rtol=1e-5, atol=1e-6)
    x_f, _ = model.filter(frames[0, :6])  # grey frames without their channel axis, as given
    assert x_f.shape == (6, 3)

    angle = rng.normal(size=(4, 20, 1)).astype(np.float32)
    angle[:, 1::2] = np.nan
    sensors = Recordings(y={"camera": frames, "angle": angle}, noise_std={"camera": 0.1, "angle": 0.05}, batch_size=2)
    both = SSM(sensors, state_dim=3, f_options=SMALL_F)
    assert type(both.g).__name__ == "SensorHeads" and list(both.streams) == ["camera", "angle"]
    fit(both, sensors, epochs=1, save_dir=tmp_path, logger=False, enable_progress_bar=False)
    sim = both.simulate(steps=4, x0=x0)
    assert set(sim) == {"camera", "angle"} and sim["camera"].shape == (4, 1, 24, 24) and sim["angle"].shape == (4, 1)
    with torch.no_grad():
        packed = both.g(torch.zeros(1, 3))[0].numpy()
    np.testing.assert_allclose(sim["angle"][0], packed[-1:], rtol=1e-5, atol=1e-6)
    x_f, p_f = both.filter({"camera": frames[0, :6], "angle": angle[0, :6]})  # NaN angles: not sampled
    assert x_f.shape == (6, 3) and np.isfinite(x_f).all()
    with pytest.raises(ValueError, match=r"reads the sensors \['camera', 'angle'\]: give a dict"):
        both.filter(frames[0, :6])
