"""The baselines (sequence-to-sequence CNN-LSTM, RKN) as forecasters: what the LSTM sees while predicting,
training on a DataModule, the shared protocol's numbers against a hand computation, checkpoints, bad input."""

from __future__ import annotations

import json

import pytest
import torch
from lightning.pytorch.callbacks import ModelCheckpoint

from experiments.results import render_file
from ssm_ms import pretrained
from ssm_ms.baselines import LSTMBaseline, RKNBaseline, Seq2SeqLSTM
from ssm_ms.baselines.rkn import RecurrentKalmanNetwork
from ssm_ms.inference.encoder_module import StateEncoderModule
from ssm_ms.module import MultipleShootingModule
from ssm_ms.nets import Projection
from ssm_ms.runtime import memory
from tests.conftest import ExactRotation, RotationDataModule, fast_trainer

LSTM_NET = {"hidden": 16}
RKN_NET = {"latent_state_dim": 4, "n_basis": 3, "bandwidth": 1, "decoder_hidden": [16]}


def rotation(tmp, **kwargs):
    return RotationDataModule(data_dir=str(tmp / "data"), seq_len=12, batch_size=4, val_trajectories=2, **kwargs)


# ---------------------------------------------------------------------------- the LSTM's inputs
def test_lstm_reads_zeros_and_the_flag_while_predicting():
    torch.manual_seed(0)
    net = Seq2SeqLSTM([1, 24, 24], hidden=8)
    y = torch.rand(2, 6, 1, 24, 24)
    observed = torch.tensor([[True] * 4 + [False] * 2] * 2)
    seen = []
    net.lstm.register_forward_hook(lambda module, args, out: seen.append(args[0].detach().clone()))
    out = net(y, observed).mean
    lstm_in = seen[-1]  # [B, T, features + 1]
    zero_frame = net.frames(torch.zeros(1, 1, 24, 24))[0]
    for t in range(6):
        expected = net.frames(y[:, t]) if t < 4 else zero_frame.expand(2, -1)
        torch.testing.assert_close(lstm_in[:, t, :-1], expected)
        assert (lstm_in[:, t, -1] == (1.0 if t < 4 else 0.0)).all()
    # whatever the frames to predict hold, the outputs are the same: the network does not see them
    y2 = y.clone()
    y2[:, 4:] = torch.rand(2, 2, 1, 24, 24)
    torch.testing.assert_close(net(y2, observed).mean, out)
    # and they do matter where observed (the check above could not pass by ignoring every frame)
    y3 = y.clone()
    y3[:, 1] = torch.rand(2, 1, 24, 24)
    assert not torch.allclose(net(y3, observed).mean[:, 4:], out[:, 4:])
    assert out.shape == y.shape and 0 <= out.min() and out.max() <= 1


def test_lstm_decoder_draws_the_data_image_size():
    # a named preset keeps its layers (quad: 4 transposed convolutions) and draws the data's size
    net = Seq2SeqLSTM([1, 24, 24], hidden=8, decoder_preset="quad")
    assert sum(isinstance(m, torch.nn.ConvTranspose2d) for m in net.decoder.deconv) == 4
    # a size of none of the paper's experiments: the nearest one's presets (30 -> pendulum), drawn at 30
    net = Seq2SeqLSTM([1, 30, 30], hidden=8)
    assert sum(isinstance(m, torch.nn.ConvTranspose2d) for m in net.decoder.deconv) == 3
    y = torch.rand(2, 3, 1, 30, 30)
    assert net(y, torch.ones(2, 3, dtype=torch.bool)).mean.shape == y.shape
    with pytest.raises(ValueError, match=r"no default encoder_preset for non-square images of shape \[1, 24, 30\]"):
        Seq2SeqLSTM([1, 24, 30], hidden=8)


@pytest.mark.parametrize("cls", [Seq2SeqLSTM, RecurrentKalmanNetwork], ids=["lstm", "rkn"])
def test_baseline_layers_given_as_mappings_instead_of_presets(cls):
    """A narrower CNN and decoder than the presets (a CPU-sized run): the layers are the ones asked for."""
    small = {"hidden": 8} if cls is Seq2SeqLSTM else {"latent_state_dim": 4, "n_basis": 2}
    net = cls(
        [1, 64, 64],
        **small,
        encoder_preset={"conv_channels": [4, 8], "final_channels": 3, "final_relu": True},
        decoder_preset={"stem_channels": 6, "layers": [[5, 3, 2], [1, 4, 2]]},
    )
    frames = net.frames if cls is Seq2SeqLSTM else net.encoder
    convs = [m for m in frames.modules() if isinstance(m, torch.nn.Conv2d)]
    assert [c.out_channels for c in convs] == [4, 8, 3]
    deconvs = [m for m in net.decoder.deconv if isinstance(m, torch.nn.ConvTranspose2d)]
    assert [(d.in_channels, d.out_channels, d.kernel_size[0], d.stride[0]) for d in deconvs] == [
        (6, 5, 3, 2),
        (5, 1, 4, 2),
    ]
    y = torch.rand(2, 3, 1, 64, 64)
    assert net(y, torch.ones(2, 3, dtype=torch.bool)).mean.shape == y.shape
    with pytest.raises(ValueError, match=r"encoder_preset as a mapping takes .* unknown: \['channels'\]"):
        cls([1, 64, 64], **small, encoder_preset={"channels": [4]})
    with pytest.raises(ValueError, match="decoder_preset as a mapping takes 'layers'"):
        cls([1, 64, 64], **small, decoder_preset={"stem_channels": 6})


# ---------------------------------------------------------------------------- training and the protocol
@pytest.fixture(scope="module", params=["lstm", "rkn"])
def trained(request, tmp_path_factory):
    """A baseline trained on the rotation data (12 steps; 8 filtered, 4 predicted), and its checkpoint."""
    tmp = tmp_path_factory.mktemp(request.param)
    torch.manual_seed(0)
    cls, net, loss = (
        (LSTMBaseline, LSTM_NET, "mse") if request.param == "lstm" else (RKNBaseline, RKN_NET, "gaussian_nll")
    )
    model = cls(
        n_filter=8,
        network=net,
        loss=loss,
        lr=1e-2,
        metrics=["mse"],
        results_dir=str(tmp / "results"),
        experiment="rot",
        analysis={"valid_time": {"threshold": 0.3}, "dt": 0.1},
    )
    dm = rotation(tmp)
    dm.prepare_data()
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    model.build(dm.obs_shape)
    with torch.no_grad():
        before = model.loss(model.run(batch["y"], 8), batch["y"]).item()
    ckpt = ModelCheckpoint(dirpath=tmp / "ckpt", save_last=True)
    fast_trainer(tmp, max_epochs=40, callbacks=[ckpt], gradient_clip_val=5.0).fit(model, dm)
    with torch.no_grad():
        after = model.loss(model.run(batch["y"], 8), batch["y"]).item()
    return request.param, cls, model, tmp, before, after


def test_baselines_reduce_their_training_loss(trained):
    name, _, _, _, before, after = trained
    assert after < before - 0.3 * abs(before), (name, before, after)


def test_the_protocol_scores_a_baseline_like_any_forecaster(trained):
    """The numbers in the results file, recomputed here: the network run on each test sequence with the first
    8 steps observed, its last 4 outputs against the clean and noisy frames, its 8th output as `last`."""
    name, _, model, tmp, _, _ = trained
    dm = rotation(tmp)
    fast_trainer(tmp, max_epochs=1).test(model, dm)
    saved = json.loads((tmp / "results" / "rot.json").read_text())["runs"][name]
    test = dm.load_arrays("test")
    y, clean = torch.from_numpy(test["y"].copy()), torch.from_numpy(test["y_clean"].copy())
    observed = torch.arange(12).expand(len(y), 12) < 8
    with torch.no_grad():
        out = model.net(torch.where(observed[..., None], y, torch.zeros(())), observed).mean
    for target_name, target in (("clean", clean), ("noisy", y)):
        per_seq = [((out[b, 8:] - target[b, 8:]) ** 2).mean().item() for b in range(len(y))]
        last = [((out[b, 7] - target[b, 8:]) ** 2).mean().item() for b in range(len(y))]
        assert saved["summary"][f"{name}/{target_name}/mse"]["mean"] == pytest.approx(sum(per_seq) / len(y), rel=1e-5)
        assert saved["summary"][f"last/{target_name}/mse"]["mean"] == pytest.approx(sum(last) / len(y), rel=1e-5)
    # the valid prediction time: leading predicted steps whose error, over the std of the noiseless truth in
    # the predicted windows, stays <= 0.3 (4 steps if it never exceeds it: censored)
    scale = clean[:, 8:].double().std(unbiased=False)
    steps = []
    for b in range(len(y)):
        err = (out[b, 8:, 0].double() - clean[b, 8:, 0].double()).abs() / scale
        steps.append(next((t for t in range(4) if err[t] > 0.3), 4))
    vt = saved["analysis"]["valid_time"]
    assert vt["mean_steps"] == pytest.approx(sum(steps) / len(steps))
    assert vt["censored_share"] == pytest.approx(sum(s == 4 for s in steps) / len(steps))
    assert vt["mean_seconds"] == pytest.approx(0.1 * sum(steps) / len(steps))
    label = {"lstm": "LSTM", "rkn": "RKN"}[name]
    assert saved["info"]["model"] == label and saved["info"]["inference"] is None
    assert f"| {label} |" in render_file(tmp / "results" / "rot.json").read_text()


def test_baseline_checkpoint_reloads_on_its_own(trained):
    name, cls, model, tmp, _, _ = trained
    loaded = cls.load_from_checkpoint(tmp / "ckpt" / "last.ckpt")  # built from the recorded obs_shape
    y = torch.randn(3, 12, 1)
    observed = torch.arange(12).expand(3, 12) < 8
    with torch.no_grad():
        torch.testing.assert_close(loaded.net(y, observed).mean, model.net(y, observed).mean)
    # and the trainer restores it into a fresh module built from the config alone (network built in setup)
    fresh = cls(
        n_filter=8,
        network=LSTM_NET if name == "lstm" else RKN_NET,
        metrics=["mse"],
        results_dir=str(tmp / "results2"),
        experiment="rot",
    )
    fast_trainer(tmp, max_epochs=1).test(fresh, rotation(tmp), ckpt_path=str(tmp / "ckpt" / "last.ckpt"))
    fast_trainer(tmp, max_epochs=1).test(model, rotation(tmp))
    first = json.loads((tmp / "results" / "rot.json").read_text())["runs"][name]["summary"]
    again = json.loads((tmp / "results2" / "rot.json").read_text())["runs"][name]["summary"]
    assert again[f"{name}/clean/mse"]["mean"] == pytest.approx(first[f"{name}/clean/mse"]["mean"], rel=1e-6)


def test_an_int8_pretrained_baseline_tests_through_ckpt_path(trained, monkeypatch):
    """``python -m ssm_ms.pretrained --weights int8`` (threshold lowered: these networks are small): the trainer's
    ``--ckpt_path`` gives the module each stored weight within half an int8 step of its row, the rest exactly."""
    name, cls, _, tmp, _, _ = trained
    monkeypatch.setattr(pretrained, "NARROW_MIN_NUMEL", 64)
    saved = torch.load(tmp / "ckpt" / "last.ckpt", weights_only=True)
    torch.save(pretrained.strip(saved, weights="int8"), tmp / "int8.ckpt")
    fresh = cls(
        n_filter=8,
        network=LSTM_NET if name == "lstm" else RKN_NET,
        metrics=["mse"],
        results_dir=str(tmp / "results_int8"),
        experiment="rot",
    )
    fast_trainer(tmp, max_epochs=1).test(fresh, rotation(tmp), ckpt_path=str(tmp / "int8.ckpt"))
    rounded = 0
    for key, value in fresh.state_dict().items():
        ref = saved["state_dict"][key]
        if ref.is_floating_point() and ref.numel() >= 64:
            rows = [ref] if ref.ndim == 1 else list(ref)
            half_step = torch.stack([torch.full_like(r, r.abs().max().item() / 254) for r in rows]).reshape(ref.shape)
            assert ((value - ref).abs() <= half_step * (1 + 1e-4)).all(), key
            rounded += not torch.equal(value, ref)
        else:
            assert torch.equal(value, ref), key
    assert rounded > 0
    assert (tmp / "results_int8" / "rot.json").exists()


# ---------------------------------------------------------------------------- bad input
def test_checkpoints_of_the_other_kind_are_refused(trained, tmp_path):
    name, cls, _, tmp, _, _ = trained
    # a baseline checkpoint given to an SSM stage
    with pytest.raises(ValueError, match=rf"is a checkpoint of the {cls.__name__} baseline: ssm_checkpoint takes"):
        StateEncoderModule(str(tmp / "ckpt" / "last.ckpt"), n_filter=8)
    # ... or to an SSM fit's --ckpt_path
    ssm = MultipleShootingModule(ExactRotation(), Projection([0]), state_dim=2, n_nodes=3)
    with pytest.raises(ValueError, match=rf"the checkpoint is a {cls.__name__}'s \(a baseline\), not an SSM's"):
        fast_trainer(tmp_path, max_epochs=1).fit(ssm, rotation(tmp_path), ckpt_path=str(tmp / "ckpt" / "last.ckpt"))
    # an SSM checkpoint given to a baseline
    ssm_ckpt = ModelCheckpoint(dirpath=tmp_path / "ssm", save_last=True)
    fast_trainer(tmp_path, max_epochs=1, callbacks=[ssm_ckpt]).fit(ssm, rotation(tmp_path))
    baseline = cls(
        n_filter=8,
        network=LSTM_NET if name == "lstm" else RKN_NET,
        metrics=["mse"],
        results_dir=str(tmp_path / "results"),
    )
    with pytest.raises(
        ValueError, match=rf"the checkpoint is an SSM \(or one of its encoder stages\), not a {cls.__name__}"
    ):
        fast_trainer(tmp_path, max_epochs=1).test(
            baseline, rotation(tmp_path), ckpt_path=str(tmp_path / "ssm" / "last.ckpt")
        )


def test_training_windows_are_consecutive_steps_of_each_sequence():
    lstm = LSTMBaseline(n_filter=8, n_predict=2, network=LSTM_NET, train_window=5, obs_shape=[1])
    y = torch.arange(6 * 12, dtype=torch.float32).view(6, 12, 1)
    torch.manual_seed(0)
    crops = lstm.window(y, random=True)
    assert crops.shape == (6, 5, 1)
    starts = []
    for b in range(6):  # a run of 5 consecutive steps of sequence b
        start = int(crops[b, 0, 0]) - 12 * b
        assert 0 <= start <= 7 and torch.equal(crops[b, :, 0], y[b, start : start + 5, 0])
        starts.append(start)
    assert len(set(starts)) > 1  # drawn per sequence
    assert torch.equal(lstm.window(y, random=False), y[:, -5:])
    assert lstm.training_split(5) == 3  # n_filter 8 does not fit a 5-step window: 5 - n_predict given


def test_bad_baseline_settings_are_refused_before_any_work(tmp_path, monkeypatch):
    with pytest.raises(ValueError, match="latent_state_dim must be even .* got 5: use 4 or 6"):
        RKNBaseline(n_filter=8, network={"latent_state_dim": 5}, obs_shape=[1])
    with pytest.raises(ValueError, match="unknown loss 'l1'"):
        LSTMBaseline(n_filter=8, loss="l1")
    with pytest.raises(ValueError, match="gaussian_nll needs a network with a variance output; this LSTM has none"):
        LSTMBaseline(n_filter=8, loss="gaussian_nll", obs_shape=[1])
    with pytest.raises(ValueError, match="analysis.dynamics studies an SSM's f; a baseline has none"):
        LSTMBaseline(n_filter=8, analysis={"valid_time": {}, "dynamics": {}})
    with pytest.raises(ValueError, match=r"analysis.valid_time.horizon must be a whole number >= 1, got 0"):
        LSTMBaseline(n_filter=8, analysis={"valid_time": {"horizon": 0}})
    with pytest.raises(ValueError, match="network.obs_shape comes from the data"):
        LSTMBaseline(n_filter=8, network={"obs_shape": [1]})
    # a prediction phase longer than the test sequences (12 steps)
    lstm = LSTMBaseline(n_filter=8, n_predict=10, network=LSTM_NET, metrics=["mse"], results_dir=str(tmp_path))
    with pytest.raises(ValueError, match="cannot filter 8 and predict 10 frames of sequences of length 12"):
        fast_trainer(tmp_path, max_epochs=1).test(lstm, rotation(tmp_path))
    # training pieces that leave nothing to predict
    lstm = LSTMBaseline(n_filter=20, network=LSTM_NET, metrics=["mse"])
    with pytest.raises(ValueError, match="training sequences have 12 steps: giving 12 of them leaves nothing"):
        fast_trainer(tmp_path, max_epochs=1).fit(lstm, rotation(tmp_path))
    lstm = LSTMBaseline(n_filter=8, n_predict=2, network=LSTM_NET, train_window=20, metrics=["mse"])
    with pytest.raises(ValueError, match=r"train_window=20 is longer than the training sequences \(12 steps\)"):
        fast_trainer(tmp_path, max_epochs=1).fit(lstm, rotation(tmp_path))
    # an LSTM that cannot train in the memory available (made 30 kB; it needs at least 60 x 4 x 12 x 16 bytes,
    # 46 kB): refused before its first step
    lstm = LSTMBaseline(n_filter=8, network=LSTM_NET, metrics=["mse"])
    trainer = fast_trainer(tmp_path, max_epochs=1)
    with monkeypatch.context() as m:
        m.setattr(memory, "available_memory", lambda: 30_000)
        with pytest.raises(ValueError, match=r"the LSTM needs at least 46 kB to train on batches of 4 sequences of 12"):
            trainer.fit(lstm, rotation(tmp_path))
    assert trainer.global_step == 0
    # a model built for other data
    lstm = LSTMBaseline(n_filter=8, network=LSTM_NET, obs_shape=[3], metrics=["mse"])
    with pytest.raises(ValueError, match=r"built for measurements of shape \[3\], the data have \[1\]"):
        fast_trainer(tmp_path, max_epochs=1).fit(lstm, rotation(tmp_path))
