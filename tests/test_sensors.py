"""Several sensors at once (ssm_ms.nets.sensors): the packed layout, the weighted and masked fit against a naive
loop, the UKF's update without a missing sample against a filter that never had that sensor, and the data modules
serving camera and joint angle (pendulum) or several keys (files), one at a lower rate."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from datamodules.files import FileDataModule
from datamodules.pendulum import PendulumDataModule
from ssm_ms.inference.filter_module import FilterForecaster
from ssm_ms.inference.optimise import OptimisationForecaster
from ssm_ms.inference.ukf import UnscentedKalmanFilter
from ssm_ms.module import MultipleShootingModule
from ssm_ms.nets import ConvDecoder, LinearReadout, LocallyLinearTransition
from ssm_ms.nets.sensors import SensorHeads, SensorLayout, Stream
from ssm_ms.training.shooting import weighted_fit
from tests.conftest import fast_trainer


def test_layout_packs_splits_and_weighs_by_the_inverse_noise_variance():
    layout = SensorLayout([Stream("image", (1, 2, 2), 0.2), Stream("angle", (1,), 0.05)])
    assert layout.size == 5 and layout.names == ["image", "angle"]
    parts = {"image": torch.arange(8.0).view(2, 1, 2, 2), "angle": torch.tensor([[9.0], [10.0]])}
    packed = layout.pack(parts)
    assert packed.tolist() == [[0, 1, 2, 3, 9], [4, 5, 6, 7, 10]]
    back = layout.split(packed)
    assert torch.equal(back["image"], parts["image"]) and torch.equal(back["angle"], parts["angle"])
    raw = torch.tensor([1 / 0.04] * 4 + [1 / 0.0025])
    torch.testing.assert_close(layout.weights(), raw / raw.mean())
    torch.testing.assert_close(layout.variances(), torch.tensor([0.04] * 4 + [0.0025]))
    torch.testing.assert_close(layout.variances({"image": 0.1}), torch.tensor([0.1] * 4 + [0.0025]))
    with pytest.raises(ValueError, match=r"variances name streams \['camera'\]"):
        layout.variances({"camera": 0.1})
    assert SensorLayout.from_state_dict(layout.state_dict()) == layout


def test_stream_weights_scale_a_streams_inverse_variance_before_the_average():
    layout = SensorLayout([Stream("image", (1, 2, 2), 0.2), Stream("angle", (1,), 0.05)])
    # by hand: image 1 / 0.04 = 25 per pixel, angle 0.1 / 0.0025 = 40; their mean over 5 components (4 * 25 + 40) / 5
    torch.testing.assert_close(layout.weights({"angle": 0.1}), torch.tensor([25.0] * 4 + [40.0]) / 28.0)
    with pytest.raises(ValueError, match=r"stream_weights name streams \['joint'\]; the streams are"):
        layout.weights({"joint": 0.1})
    with pytest.raises(ValueError, match="stream_weights must be > 0"):
        layout.weights({"angle": 0.0})
    g = SensorHeads(4, {"image": ConvDecoder(4, preset="pendulum"), "angle": LinearReadout(4, 2)})
    model = MultipleShootingModule(
        LocallyLinearTransition(4, 2, 8, input_dim=1), g, state_dim=4, stream_weights={"angle": 0.1}
    )
    model.adopt_sensors(SensorLayout([Stream("image", (1, 24, 24), 0.2), Stream("angle", (2,), 0.05)]))
    raw = torch.tensor([25.0] * 576 + [40.0] * 2)
    torch.testing.assert_close(model.measurement_weights, raw / raw.mean())
    with pytest.raises(ValueError, match="these data have one: remove model.init_args.stream_weights"):
        model.adopt_sensors(None)


def test_weighted_fit_with_missing_samples_against_a_naive_loop():
    torch.manual_seed(0)
    y_hat, y = torch.rand(2, 3, 4), torch.rand(2, 3, 4)
    y[0, 1, 3] = y[1, 2, 3] = float("nan")
    w = torch.tensor([1.0, 1.0, 2.0, 0.5])
    totals, counts = [0.0, 0.0], [0, 0]
    for b in range(2):
        for t in range(3):
            for c in range(4):
                if torch.isfinite(y[b, t, c]):
                    totals[b] += w[c] * (y_hat[b, t, c] - y[b, t, c]) ** 2
                    counts[b] += 1
    torch.testing.assert_close(weighted_fit("mse", y_hat, y, w, missing=True), sum(totals) / sum(counts))
    per_sequence = torch.stack([torch.as_tensor(t / c) for t, c in zip(totals, counts)])
    torch.testing.assert_close(weighted_fit("mse", y_hat, y, w, missing=True, per_sequence=True), per_sequence)
    clean = torch.nan_to_num(y)
    torch.testing.assert_close(weighted_fit("mse", y_hat, clean), torch.nn.functional.mse_loss(y_hat, clean))


def test_ukf_update_skips_a_missing_sensor_exactly():
    """Linear g of two sensors; with the second's sample NaN, the update equals that of a filter whose g is the first
    sensor alone."""
    torch.manual_seed(0)
    h = torch.randn(3, 2, dtype=torch.float64)

    def g(x):
        return x @ h.T

    def g_first(x):
        return x @ h[:2].T

    mean, cov = torch.randn(4, 2, dtype=torch.float64), torch.eye(2, dtype=torch.float64).expand(4, 2, 2) * 0.5
    y = torch.randn(4, 3, dtype=torch.float64)
    y[:, 2] = float("nan")
    both = UnscentedKalmanFilter(lambda x: x, g, measurement_var=[0.1, 0.2, 0.3], state_dim=2, innovation="low_rank")
    first = UnscentedKalmanFilter(lambda x: x, g_first, measurement_var=[0.1, 0.2], state_dim=2, innovation="low_rank")
    m1, c1 = both.update(mean, cov, y)
    m2, c2 = first.update(mean, cov, y[:, :2])
    torch.testing.assert_close(m1, m2)
    torch.testing.assert_close(c1, c2)


@pytest.fixture(scope="module")
def camera_and_angle(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("sensors")
    kw = dict(n_train=6, n_test=2, data_dir=str(tmp), workers=1, batch_size=3, val_trajectories=2, torque_limit=2.0)
    both = PendulumDataModule(sensors=["image", "angle"], angle_noise_std=0.05, angle_every=2, **kw)
    both.prepare_data()
    both.setup("fit")
    camera = PendulumDataModule(**kw)
    camera.prepare_data()
    camera.setup("fit")
    return both, camera


def test_pendulum_serves_camera_and_angle_packed(camera_and_angle):
    both, camera = camera_and_angle
    assert both.sensor_layout == [
        {"name": "image", "shape": [1, 24, 24], "noise_std": 0.2},
        {"name": "angle", "shape": [2], "noise_std": 0.05},
    ]
    item, alone = both.train_split()[2], camera.train_split()[2]
    assert item["y"].shape == (100, 578)
    # the camera's frames are the single-sensor data's (the angle's noise is drawn after the image's)
    torch.testing.assert_close(item["y"][:, :576].view(100, 1, 24, 24), alone["y"])
    reading, truth = item["y"][:, 576:], item["state"][:, 0].double()
    assert torch.isnan(reading[1::2]).all() and torch.isfinite(reading[::2]).all()  # every second frame
    # the encoder reports the sine and cosine of the angle it measures with noise
    measured = torch.atan2(reading[::2, 0], reading[::2, 1]).double()
    error = torch.remainder(measured - truth[::2] + torch.pi, 2 * torch.pi) - torch.pi
    assert error.std() == pytest.approx(0.05, rel=0.35) and error.abs().max() < 0.3
    assert reading[::2].norm(dim=1).sub(1).abs().max() < 1e-5
    torch.testing.assert_close(item["y_clean"][:, 576:].double(), torch.stack([truth.sin(), truth.cos()], 1))
    assert both.obs_shape == (578,)


def test_a_model_of_camera_and_angle_trains_with_the_weighted_masked_fit(camera_and_angle, tmp_path):
    both, _ = camera_and_angle
    torch.manual_seed(0)
    g = SensorHeads(4, {"image": ConvDecoder(4, preset="pendulum"), "angle": LinearReadout(4, 2)})
    model = MultipleShootingModule(LocallyLinearTransition(4, 2, 8, input_dim=1), g, state_dim=4, n_nodes=4)
    trainer = fast_trainer(tmp_path, max_epochs=1, limit_val_batches=1)
    trainer.fit(model, both)
    batch = next(iter(both.train_dataloader()))
    fit, _ = model.shooting_loss(batch)
    nodes = model.node_states(batch["index"])
    from ssm_ms.training.shooting import rollout

    states = rollout(model.f, nodes.reshape(-1, 4), 26, batch["u"].reshape(-1, 25, 1))[:, :25]
    y_hat = g(states.reshape(-1, 4)).view(batch["y"].shape)
    layout = SensorLayout.from_state_dict(both.sensor_layout)
    torch.testing.assert_close(fit, weighted_fit("mse", y_hat, batch["y"], layout.weights(), missing=True))
    # the UKF of the test protocol weighs each stream by its own noise unless told otherwise
    trainer.save_checkpoint(tmp_path / "ssm.ckpt")
    for given, expected in ((None, [0.2**2] * 576 + [0.05**2] * 2), (0.3, 0.3)):
        ukf = FilterForecaster(
            str(tmp_path / "ssm.ckpt"), n_filter=50, measurement_var=given, results_dir=str(tmp_path), experiment="s"
        )
        fast_trainer(tmp_path, max_epochs=1).test(ukf, both)
        torch.testing.assert_close(ukf.filter.measurement_var.double(), torch.tensor(expected, dtype=torch.float64))
    bad = SensorHeads(4, {"angle": LinearReadout(4, 2), "image": ConvDecoder(4, preset="pendulum")})
    with pytest.raises(ValueError, match="one head per sensor, in the data's order"):
        fast_trainer(tmp_path, max_epochs=1).fit(
            MultipleShootingModule(LocallyLinearTransition(4, 2, 8, input_dim=1), bad, state_dim=4, n_nodes=4), both
        )


def test_files_with_several_keys(tmp_path):
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(8, 12, 2)).astype(np.float32), rng.normal(size=(8, 12, 1)).astype(np.float32)
    b[:, 1::3] = np.nan  # sampled every third step
    np.savez(tmp_path / "rec.npz", pos=a, enc=b)
    dm = FileDataModule(str(tmp_path / "rec.npz"), key=["pos", "enc"], noise_std={"enc": 0.5}, batch_size=4)
    assert dm.sensor_layout == [
        {"name": "pos", "shape": [2], "noise_std": 1.0},
        {"name": "enc", "shape": [1], "noise_std": 0.5},
    ]
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    expected = np.concatenate([a, b], -1)[batch["index"].numpy()]
    np.testing.assert_array_equal(batch["y"].numpy(), expected)
    np.savez(tmp_path / "short.npz", pos=a, enc=b[:, :6])
    with pytest.raises(ValueError, match=r"every sensor of a trajectory has a sample slot per step"):
        FileDataModule(str(tmp_path / "short.npz"), key=["pos", "enc"])
    b[0, 0, 0] = np.inf
    np.savez(tmp_path / "inf.npz", pos=a, enc=b)
    with pytest.raises(ValueError, match="non-finite"):
        FileDataModule(str(tmp_path / "inf.npz"), key=["pos", "enc"]).setup("fit")


def two_sensor_ssm(
    tmp_path, seed: int, every: int, **data
) -> tuple[np.ndarray, np.ndarray, FileDataModule, SensorHeads]:
    """Recordings of two sensors, ``pos`` [2] every step and ``enc`` [1] missing one step in ``every`` (NaN), in
    ``rec.npz`` (and their first 3 sequences' first 12 steps in ``new.npz``); their data module (``data``: more
    arguments) and an SSM of one head per sensor fitted one epoch, saved as ``ssm.ckpt``. Returns the recordings,
    the data module and ``g``."""
    rng = np.random.default_rng(seed)
    pos, enc = rng.normal(size=(8, 30, 2)).astype(np.float32), rng.normal(size=(8, 30, 1)).astype(np.float32)
    enc[:, 1::every] = np.nan
    np.savez(tmp_path / "rec.npz", pos=pos, enc=enc)
    np.savez(tmp_path / "new.npz", pos=pos[:3, :12], enc=enc[:3, :12])
    kwargs = {"batch_size": 4, **data}
    dm = FileDataModule(
        str(tmp_path / "rec.npz"), key=["pos", "enc"], noise_std={"pos": 0.1, "enc": 0.2}, normalize=False, **kwargs
    )
    torch.manual_seed(0)
    g = SensorHeads(3, {"pos": LinearReadout(3, 2), "enc": LinearReadout(3, 1)})
    model = MultipleShootingModule(LocallyLinearTransition(3, 2, 8), g, state_dim=3, n_nodes=3)
    trainer = fast_trainer(tmp_path, max_epochs=1, limit_val_batches=1)
    trainer.fit(model, dm)
    trainer.save_checkpoint(tmp_path / "ssm.ckpt")
    return pos, enc, dm, g


def test_predict_writes_each_sensor_in_its_own_shape(tmp_path):
    """``cli.py predict`` of a two-sensor model: each stream read by its name, forecast, written in its own shape."""
    from ssm_ms.forecasting.writer import ForecastWriter

    pos, enc, dm, g = two_sensor_ssm(tmp_path, seed=0, every=2, predict_path=str(tmp_path / "new.npz"), predict_steps=5)
    ukf = FilterForecaster(str(tmp_path / "ssm.ckpt"), n_filter=10, results_dir=str(tmp_path), experiment="s")
    out = tmp_path / "forecast.npz"
    fast_trainer(tmp_path, max_epochs=1, callbacks=[ForecastWriter(str(out), figures=1)]).predict(ukf, dm)
    got = np.load(out)
    assert "filtered" not in got and "predicted" not in got
    assert got["filtered_pos"].shape == (3, 12, 2) and got["filtered_enc"].shape == (3, 12, 1)
    assert got["predicted_pos"].shape == (3, 5, 2) and got["predicted_enc"].shape == (3, 5, 1)
    with torch.no_grad():  # each stream is its own head of g on the forecast's states, not a slice of a packed vector
        states = torch.from_numpy(got["predicted_states"]).reshape(-1, 3)
        for name in ("pos", "enc"):
            head = g.heads[name](states).reshape(got[f"predicted_{name}"].shape).numpy()
            np.testing.assert_allclose(got[f"predicted_{name}"], head, rtol=1e-4, atol=1e-5)
    assert {p.name for p in (tmp_path / "forecast_figures").iterdir()} == {
        "sequence_00000_pos.png",
        "sequence_00000_enc.png",
    }
    np.savez(tmp_path / "one.npz", pos=pos[:3, :12])  # a sensor missing from the file: one message
    dm.predict_path, dm.datasets = [str(tmp_path / "one.npz")], {}
    with pytest.raises(ValueError, match="stream 'enc'"):
        dm.load_predict()


def test_states_fitted_through_two_sensors_weigh_them_and_skip_missing_samples(tmp_path):
    """The fit of several sensors is the SSM's own: each stream weighted by its noise, the samples a sensor did not take
    left out; the objective of the fitted nodes against a naive loop over sequences, steps and components."""
    pos, enc, dm, g = two_sensor_ssm(tmp_path, seed=2, every=2, test_path=str(tmp_path / "rec.npz"))
    fitted = OptimisationForecaster(
        str(tmp_path / "ssm.ckpt"), n_filter=10, n_nodes=2, steps=50, n_candidates=8, results_dir=str(tmp_path)
    )
    fast_trainer(tmp_path, max_epochs=1).test(fitted, dm)  # its setup adopts the data's sensors
    y = torch.from_numpy(np.concatenate([pos, enc], -1)[:3, :10])
    nodes, objective = fitted.fit_states(y)
    weights = SensorLayout.from_state_dict(dm.sensor_layout).weights().double()
    f, heads, alpha = fitted.ssm.f, fitted.ssm.g.heads, fitted.alpha
    with torch.no_grad():
        for b in range(3):
            total, count, states, ends = 0.0, 0, [], []
            for piece in range(2):  # two pieces of 5 steps, each rolled out from its node
                x = nodes[b : b + 1, piece]
                for _ in range(5):
                    states.append(x)
                    x = f(x)
                ends.append(x)
            for t, x in enumerate(states):
                y_hat = torch.cat([heads["pos"](x), heads["enc"](x)], -1)[0].double()
                for c in range(3):
                    if torch.isfinite(y[b, t, c]):
                        total += weights[c].item() * (y_hat[c].item() - y[b, t, c].item()) ** 2
                        count += 1
            gap = ((nodes[b, 1] - ends[0][0]) ** 2).mean().item()
            assert objective[b].item() == pytest.approx(total / count + alpha * gap, rel=1e-4)
    assert count < 30  # the loop left samples out


def test_the_test_protocol_scores_each_sensor_over_the_frames_it_sampled(tmp_path):
    """Several sensors are scored stream by stream, a frame a sensor did not sample (NaN) left out: against a naive
    loop over the sequences and frames of the UKF's own forecasts."""
    import json

    pos, enc, dm, _ = two_sensor_ssm(tmp_path, seed=1, every=3, test_path=str(tmp_path / "rec.npz"), batch_size=8)
    ukf = FilterForecaster(
        str(tmp_path / "ssm.ckpt"),
        n_filter=10,
        metrics=["mse", "bce"],
        results_dir=str(tmp_path),
        figures_dir=str(tmp_path / "figures"),
        experiment="s",
    )
    fast_trainer(tmp_path, max_epochs=1).test(ukf, dm)
    drawn = {p.name for p in (tmp_path / "figures").iterdir()}
    assert {"s_ukf_prediction_pos.png", "s_ukf_lorenz_prediction_enc.png"} <= drawn  # each stream its own figure
    summary = json.loads((tmp_path / "s.json").read_text())["runs"]["ukf"]["summary"]
    assert "ukf/noisy/enc/bce" not in summary and "ukf/noisy/mse" not in summary  # no bce of a vector, no packed score
    y = torch.from_numpy(np.concatenate([pos, enc], -1))
    with torch.no_grad():
        predicted = ukf.forecast(y[:, :10], 20).predicted.double().numpy()
    for name, cols in (("pos", slice(0, 2)), ("enc", slice(2, 3))):
        per_sequence = []
        for b in range(8):
            frames = [
                np.mean((predicted[b, j, cols] - y[b, 10 + j, cols].double().numpy()) ** 2)
                for j in range(20)
                if np.isfinite(y[b, 10 + j, cols].numpy()).all()
            ]
            per_sequence.append(np.mean(frames))
        assert summary[f"ukf/noisy/{name}/mse"]["mean"] == pytest.approx(np.mean(per_sequence), rel=1e-4)
        assert summary[f"ukf/noisy/{name}/mse"]["non_finite"] == 0


def test_reconstruction_logger_draws_each_sensor_in_its_own_shape():
    """The camera's frames as an image grid, the joint reading as a series: one TensorBoard picture per stream."""
    from types import SimpleNamespace

    from ssm_ms.viz import ReconstructionLogger

    class Writer:
        def __init__(self):
            self.images, self.figures = {}, {}

        def add_image(self, tag, image, step):
            self.images[tag] = image

        def add_figure(self, tag, figure, step):
            self.figures[tag] = figure

    writer = Writer()
    layout = [
        {"name": "image", "shape": [1, 24, 24], "noise_std": 0.2},
        {"name": "angle", "shape": [2], "noise_std": 0.05},
    ]
    trainer = SimpleNamespace(
        sanity_checking=False,
        loggers=[SimpleNamespace(experiment=writer)],
        datamodule=SimpleNamespace(sensor_layout=layout),
        global_step=0,
        current_epoch=0,
        max_epochs=1,
    )
    y = torch.rand(2, 10, 578)
    ReconstructionLogger().on_validation_batch_end(trainer, None, {"y": y, "y_hat": y}, None, 0)
    assert set(writer.images) == {"val/reconstruction/image"} and set(writer.figures) == {"val/reconstruction/angle"}
    assert writer.images["val/reconstruction/image"].shape[-1] > 24  # a grid of frames, not a strip of numbers


def test_streams_encoder_reads_each_sensor_by_itself_and_flags_missing_samples():
    """An image stream and a vector stream packed side by side, the vector missing at some steps: against a naive
    loop over the steps (the image's CNN alone on the image, the vector as it is or zeros, a flag per stream)."""
    from ssm_ms.nets.encoder import StreamsEncoder

    torch.manual_seed(0)
    enc = StreamsEncoder({"image": (1, 12, 12), "angle": (2,)}, conv_channels=[4], final_channels=3)
    y = torch.rand(2, 5, 144 + 2)
    y[0, 1, 144:] = float("nan")
    y[1, 3, 145] = float("nan")  # one component missing: the sample is missing
    out = enc(y)
    cnn = enc.streams[0]
    assert out.shape == (2, 5, cnn.out_features + 1 + 2 + 1) == (2, 5, enc.out_features)
    for b in range(2):
        for t in range(5):
            image, angle = y[b, t, :144].view(1, 1, 12, 12), y[b, t, 144:]
            sampled = bool(torch.isfinite(angle).all())
            expected = torch.cat(
                [cnn(image)[0], torch.ones(1), angle if sampled else torch.zeros(2), torch.tensor([float(sampled)])]
            )
            torch.testing.assert_close(out[b, t], expected)
    with pytest.raises(ValueError, match="packed into 146 values"):
        enc(torch.rand(3, 150))


def test_encoder_of_two_sensors_trains_and_filters_through_missing_samples(tmp_path):
    """The forecasting stage on an SSM of one head per sensor, one sensor missing one step in three: its encoder
    reads the streams by themselves and its latent estimates stay finite where a sample is missing."""
    from ssm_ms.inference import StateEncoderModule
    from ssm_ms.nets.encoder import StreamsEncoder

    pos, enc, dm, _ = two_sensor_ssm(tmp_path, seed=2, every=3)
    module = StateEncoderModule(
        str(tmp_path / "ssm.ckpt"), n_filter=10, encoder={"hidden": 16}, metrics=["mse"], results_dir=str(tmp_path)
    )
    assert isinstance(module.encoder.frames, StreamsEncoder) and module.encoder.frames.names == ["pos", "enc"]
    fast_trainer(tmp_path, max_epochs=1).fit(module, dm)
    y = torch.from_numpy(np.concatenate([pos, enc], -1))
    assert torch.isnan(y).any()
    with torch.no_grad():
        z = module.encoder(y)
    assert z.shape == (8, 30, 3) and torch.isfinite(z).all()


def test_the_angle_readout_draws_each_joints_sine_and_cosine_on_the_unit_circle():
    """AngleReadout against its formula written out per joint: the linear map's (a_j, b_j) over their norm, in the
    encoders' order (sines, then cosines); bounded for states far outside any data."""
    from ssm_ms.nets import AngleReadout

    torch.manual_seed(0)
    g = AngleReadout(state_dim=5, joints=2)
    x = torch.randn(7, 5) * torch.tensor([[1.0]] * 6 + [[1e6]])  # the last state far out
    out = g(x)
    lin = x @ g.linear.weight.T + g.linear.bias
    for j in range(2):
        a, b = lin[:, j], lin[:, 2 + j]
        norm = (a**2 + b**2).sqrt()
        torch.testing.assert_close(out[:, j], a / norm)
        torch.testing.assert_close(out[:, 2 + j], b / norm)
    torch.testing.assert_close(out[:, :2] ** 2 + out[:, 2:] ** 2, torch.ones(7, 2))
    with pytest.raises(ValueError, match="at least one joint"):
        AngleReadout(state_dim=5, joints=0)
