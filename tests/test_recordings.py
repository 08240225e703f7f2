"""Training windows (datamodules/windows.py) and Recordings (arrays in memory), checked against windows enumerated and
arrays sliced by hand, statistics computed with numpy, and one message for each mistake."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from datamodules.recordings import Recordings
from datamodules.windows import cut_windows, default_window
from ssm_ms.module import MultipleShootingModule
from ssm_ms.nets import LinearReadout, LocallyLinearTransition
from tests.conftest import fast_trainer


def rng(seed: int = 0) -> np.random.Generator:
    return np.random.default_rng(seed)


def served(dm: Recordings) -> dict[str, np.ndarray]:
    """Every training trajectory as a shuffled loader serves it, put back in index order."""
    dm.setup("fit")
    batches = list(dm.train_dataloader())
    index = torch.cat([b["index"] for b in batches]).numpy()
    assert sorted(index.tolist()) == list(range(dm.num_train_trajectories))
    order = np.argsort(index)
    return {k: torch.cat([b[k] for b in batches]).numpy()[order] for k in batches[0] if k != "index"}


def by_hand(recordings: list[np.ndarray], origins: list[tuple[int, int]], w: int) -> np.ndarray:
    return np.stack([recordings[r][s : s + w] for r, s in origins]).astype(np.float64)


# ---------------------------------------------------------------------------- windows
def test_windows_by_hand():
    # lengths 10, 7, 3, 12 in windows of 4: 10 -> 0, 4 and the last ending at 10 (6); 7 -> 0 and 3; 3 is too short;
    # 12 -> 0, 4, 8 (the last ends at 12: no extra window)
    w = cut_windows([10, 7, 3, 12], window=4)
    assert w.origins.tolist() == [[0, 0], [0, 4], [0, 6], [1, 0], [1, 3], [3, 0], [3, 4], [3, 8]]
    assert w.window == 4 and w.stride == 4 and w.too_short == (2,) and len(w) == 8
    assert "recordings 2 (3 samples) are shorter than the window of 4" in w.note()
    # stride 3, window 5: 11 -> 0, 3, 6 (ends at 11); 12 -> 0, 3, 6 and 7 (ending at 12)
    assert cut_windows([11, 12], window=5, stride=3).origins.tolist() == [[0, 0], [0, 3], [0, 6]] + [
        [1, 0],
        [1, 3],
        [1, 6],
        [1, 7],
    ]
    # a stride above the window skips samples between windows, and still ends at the recording's end
    assert cut_windows([20], window=4, stride=7).origins.tolist() == [[0, 0], [0, 7], [0, 14], [0, 16]]


@pytest.mark.parametrize("seed", range(5))
def test_windows_cover_every_sample(seed):
    g = rng(seed)
    lengths = g.integers(1, 60, size=6).tolist()
    window = int(g.integers(1, max(lengths) + 1))
    stride = int(g.integers(1, window + 1))
    w = cut_windows(lengths, window=window, stride=stride)
    for r, t in enumerate(lengths):
        starts = [s for rr, s in w.origins.tolist() if rr == r]
        if t < window:
            assert starts == [] and r in w.too_short
            continue
        covered = np.zeros(t, bool)
        for s in starts:
            assert 0 <= s and s + window <= t
            covered[s : s + window] = True
        assert covered.all()
        # the starts: the multiples of the stride that fit, then the one ending at the recording's end if missing
        fitting = [s for s in range(t) if s % stride == 0 and s + window <= t]
        assert starts == fitting + ([t - window] if fitting[-1] + window != t else [])


def test_gather_slices_every_array_at_the_origins():
    y = [rng(0).normal(size=(9, 2)), rng(1).normal(size=(6, 2))]
    u = [rng(2).normal(size=(9, 1)), rng(3).normal(size=(6, 1))]
    w = cut_windows([9, 6], window=4, stride=2)
    # 9 -> 0, 2, 4 and 5; 6 -> 0, 2
    expected = [(0, 0), (0, 2), (0, 4), (0, 5), (1, 0), (1, 2)]
    assert [tuple(o) for o in w.origins.tolist()] == expected
    for arrays in (y, u):
        out = w.gather(arrays)
        assert out.shape == (6, 4, arrays[0].shape[1])
        np.testing.assert_array_equal(out, np.stack([arrays[r][s : s + 4] for r, s in expected]))
    assert w.gather(y, np.float32).dtype == np.float32


def test_default_window():
    assert default_window([1500]) == 200  # one long recording: capped at 200
    assert default_window([37]) == 30  # rounded down to a multiple of 10
    assert default_window([300, 120, 400]) == 120  # the shortest recording
    assert default_window([7]) == 7  # fewer than 10 samples: all of them
    assert default_window([50, 50, 50]) is None  # several of one length: served whole
    whole = cut_windows([50, 50])
    assert whole.whole and whole.window == 50 and whole.origins.tolist() == [[0, 0], [1, 0]]
    assert cut_windows([50]).whole and cut_windows([50]).window == 50  # one recording of 50: one window of 50
    assert not cut_windows([50, 60]).whole  # the shortest: 50; the second cut at 0 and 10


def test_split_last_drops_training_windows_that_overlap():
    w = cut_windows([10, 7], window=4)  # (0, 0), (0, 4), (0, 6), (1, 0), (1, 3)
    kept, held = w.split_last(2)
    assert held.tolist() == [3, 4] and kept.tolist() == [0, 1, 2]
    kept, held = w.split_last(1)  # (1, 3) held out: (1, 0) shares samples 3 with it
    assert held.tolist() == [4] and kept.tolist() == [0, 1, 2]
    kept, held = w.split_last(3)  # (0, 6) held out: (0, 4) shares samples 6 and 7
    assert held.tolist() == [2, 3, 4] and kept.tolist() == [0]


@pytest.mark.parametrize(
    "lengths,window,stride,match",
    [
        ([10, 7], 11, None, r"window=11 is longer than every recording \(y: the longest has 10 samples\): give window"),
        ([10], 4, 0, "stride must be >= 1"),
        ([10], 0, None, "window must be >= 1"),
        ([10, 10], None, 2, "stride=2 is given, but the 2 recordings of 10 samples are served whole: give a window"),
        ([], None, None, "no recordings"),
    ],
)
def test_bad_windows(lengths, window, stride, match):
    with pytest.raises(ValueError, match=match):
        cut_windows(lengths, window, stride, what="y")


# ---------------------------------------------------------------------------- Recordings: what is served
def test_recordings_serve_the_windows_normalised_by_hand():
    lengths = [23, 9, 15]
    y = [(rng(r).normal(size=(t, 2)) * [1.0, 4.0] + [3.0, -2.0]) for r, t in enumerate(lengths)]
    u = [rng(10 + r).normal(2.0, 0.5, size=(t, 1)) for r, t in enumerate(lengths)]
    clean = [a + 0.5 for a in y]
    dm = Recordings(y=y, u=u, y_clean=clean, dt=0.05, window=5, stride=3, batch_size=4)
    # 23 -> 0, 3, ..., 18 (ends at 23); 9 -> 0, 3 and 4; 15 -> 0, 3, 6, 9, 10
    origins = [(0, s) for s in (0, 3, 6, 9, 12, 15, 18)] + [(1, 0), (1, 3), (1, 4)]
    origins += [(2, s) for s in (0, 3, 6, 9, 10)]
    assert [tuple(o) for o in dm.window_origins.tolist()] == origins
    assert dm.num_train_trajectories == 15 and dm.seq_len == dm.window == 5 and dm.stride == 3
    assert dm.obs_shape == (2,) and dm.input_dim == 1 and dm.sample_period == 0.05 and dm.sensor_layout is None
    assert dm.normalize  # float vectors: normalised by default
    y_win, u_win, clean_win = (by_hand(a, origins, 5) for a in (y, u, clean))
    # the statistics of the training windows, per component
    y_mean, y_std = y_win.reshape(-1, 2).mean(0), y_win.reshape(-1, 2).std(0)
    u_mean, u_std = u_win.reshape(-1, 1).mean(0), u_win.reshape(-1, 1).std(0)
    out = served(dm)
    np.testing.assert_allclose(dm.normalizer.mean.numpy(), y_mean, rtol=1e-5)
    np.testing.assert_allclose(dm.input_normalizer.std.numpy(), u_std, rtol=1e-5)
    np.testing.assert_allclose(out["y"], (y_win - y_mean) / y_std, atol=1e-5)
    np.testing.assert_allclose(out["u"], (u_win - u_mean) / u_std, atol=1e-5)
    np.testing.assert_allclose(out["y_clean"], (clean_win - y_mean) / y_std, atol=1e-5)


def test_one_long_recording_unnormalised():
    y = rng().normal(size=(450, 3)).astype(np.float32)
    dm = Recordings(y=torch.from_numpy(y), normalize=False, batch_size=2)
    # the default window: 200 samples; windows at 0 and 200, and one ending at 450 (250)
    assert dm.window_origins.tolist() == [[0, 0], [0, 200], [0, 250]] and dm.seq_len == 200
    out = served(dm)
    np.testing.assert_array_equal(out["y"], np.stack([y[0:200], y[200:400], y[250:450]]))
    assert "u" not in out and "y_clean" not in out and dm.sample_period is None


def test_recordings_of_one_length_are_served_whole():
    y = rng().normal(size=(5, 12, 2))
    dm = Recordings(y=y, normalize=False)
    assert dm.window_origins.tolist() == [[r, 0] for r in range(5)] and dm.seq_len == 12
    np.testing.assert_allclose(served(dm)["y"], y, rtol=1e-6)


def test_a_recording_shorter_than_the_window_is_left_out_with_a_warning():
    y = [rng(0).normal(size=(20, 1)), rng(1).normal(size=(6, 1)), rng(2).normal(size=(10, 1))]
    with pytest.warns(UserWarning, match=r"y: recordings 1 \(6 samples\) are shorter than the window of 10"):
        dm = Recordings(y=y, window=10, normalize=False)
    assert dm.window_origins.tolist() == [[0, 0], [0, 10], [2, 0]]
    np.testing.assert_allclose(served(dm)["y"], by_hand(y, [(0, 0), (0, 10), (2, 0)], 10), rtol=1e-6)


@pytest.mark.parametrize(
    "make,obs_shape,n,seq_len",
    [
        (lambda g: g.normal(size=30), (1,), 1, 30),  # [T]: one scalar recording, one window of 30
        (lambda g: g.normal(size=(30, 3)), (3,), 1, 30),  # [T, D]
        (lambda g: g.normal(size=(4, 12, 3)), (3,), 4, 12),  # [N, T, D]
        (lambda g: g.integers(0, 256, size=(2, 5, 6, 7), dtype=np.uint8), (1, 6, 7), 2, 5),  # [N, T, H, W]
        (lambda g: g.random(size=(2, 5, 3, 6, 7)).astype(np.float32), (3, 6, 7), 2, 5),  # [N, T, C, H, W]
        (lambda g: [g.normal(size=12), g.normal(size=15)], (1,), 4, 10),  # [T_i]: windows of 10 (rounded down)
        (lambda g: [g.normal(size=(12, 2)), g.normal(size=(12, 2))], (2,), 2, 12),  # [T_i, D] of one length
        (lambda g: [g.random(size=(8, 6, 7)), g.random(size=(9, 6, 7))], (1, 6, 7), 3, 8),  # [T_i, H, W]
        (lambda g: [torch.rand(8, 3, 4, 4), torch.rand(8, 3, 4, 4)], (3, 4, 4), 2, 8),  # [T_i, C, H, W] tensors
        (lambda g: {"pos": g.normal(size=(3, 8, 2)), "cam": g.random(size=(3, 8, 4, 4))}, (18,), 3, 8),  # sensors
    ],
)
def test_every_layout_gives_its_obs_shape(make, obs_shape, n, seq_len):
    dm = Recordings(y=make(rng()), normalize=False)
    assert dm.obs_shape == obs_shape and dm.num_train_trajectories == n and dm.seq_len == seq_len
    out = served(dm)
    assert out["y"].shape == (n, seq_len, *obs_shape)


def test_list_of_recordings_12_and_15_samples():
    """The default window of recordings of 12 and 15 samples: 12 rounded down to 10."""
    y = [rng(0).normal(size=12), rng(1).normal(size=15)]
    dm = Recordings(y=y, normalize=False)
    assert dm.window_origins.tolist() == [[0, 0], [0, 2], [1, 0], [1, 5]]
    expected = by_hand([a[:, None] for a in y], [(0, 0), (0, 2), (1, 0), (1, 5)], 10)
    np.testing.assert_allclose(served(dm)["y"], expected, rtol=1e-6)


def test_uint8_images_are_served_in_0_1_unnormalised():
    y = rng().integers(0, 256, size=(3, 4, 5, 5), dtype=np.uint8)
    dm = Recordings(y=y)
    assert not dm.normalize  # images: not normalised by default
    np.testing.assert_allclose(served(dm)["y"], y[:, :, None].astype(np.float64) / 255.0, atol=1e-7)
    # a uint8 recording beside float ones is mapped to [0, 1] as well
    mixed = Recordings(y=[y[0], y[1].astype(np.float32) / 255.0])
    np.testing.assert_allclose(served(mixed)["y"], y[:2, :, None] / 255.0, atol=1e-6)


def test_several_sensors_are_packed_unnormalised():
    pos = rng(0).normal(size=(3, 9, 2))
    enc = rng(1).normal(size=(3, 9, 1))
    enc[:, 1::3] = np.nan  # sampled every third step
    dm = Recordings(y={"pos": pos, "enc": enc}, noise_std={"enc": 0.5})
    assert dm.sensor_layout == [
        {"name": "pos", "shape": [2], "noise_std": 1.0},
        {"name": "enc", "shape": [1], "noise_std": 0.5},
    ]
    assert dm.obs_shape == (3,) and not dm.normalize
    np.testing.assert_allclose(served(dm)["y"], np.concatenate([pos, enc], -1), rtol=1e-6)


def test_generator_params_tell_other_data():
    y = rng().normal(size=(4, 20, 2)).astype(np.float32)
    a = Recordings(y=y, window=10).generator_params()
    assert a["window"] == 10 and a["stride"] == 10 and a["recordings"] == 4 and a["samples"] == 80
    assert a["sample_shapes"] == {"y": [2]} and a["input_dim"] == 0
    assert Recordings(y=list(y), window=10).generator_params() == a  # the same recordings as a list: the same data
    other = y.copy()
    other[3, 19, 1] += 1e-3
    assert Recordings(y=other, window=10).generator_params()["sha1"] != a["sha1"]
    assert Recordings(y=y, window=10, stride=5).generator_params()["stride"] == 5


# ---------------------------------------------------------------------------- Recordings: mistakes
Y = np.zeros((3, 10, 2))


def nan_at(a: np.ndarray, where: tuple, value: float = np.nan) -> np.ndarray:
    a = a.copy()
    a[where] = value
    return a


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(y=np.zeros((1, 2, 3, 4, 5, 6))), r"y has shape \(1, 2, 3, 4, 5, 6\) \(rank 6\); give one recording"),
        (
            dict(y=[np.zeros((5, 2)), np.zeros((5, 1, 2, 3, 4))]),
            r"y: recording 1 of the list has shape \(5, 1, 2, 3, 4\)",
        ),
        (dict(y=[np.zeros((5, 2)), np.zeros((6, 3))]), r"y: recording 1 holds samples of shape \(3,\) but recording 0"),
        (dict(y=[]), "y is an empty list: give at least one recording"),
        (dict(y=np.zeros((0, 5, 2))), "no recordings"),
        (dict(y=[np.zeros((5, 2)), np.zeros((0, 2))]), r"y: recording 1 is empty \(shape \(0, 2\)\)"),
        (dict(y=np.full((4, 2), "a")), "y: recording 0 has dtype <U1; give real numbers"),
        (dict(y=nan_at(Y, (1, 4, 0))), "y: recording 1 holds nan at sample 4: remove or interpolate"),
        (dict(y=nan_at(Y, (2, 7, 1), np.inf)), "y: recording 2 holds inf at sample 7"),
        (dict(y=Y, u=nan_at(np.zeros((3, 10, 1)), (0, 2, 0), np.inf)), "u: recording 0 holds inf at sample 2"),
        (dict(y=Y, u=np.zeros((3, 9, 1))), "u: recording 0 has 9 samples but y's recording 0 has 10: give one per"),
        (dict(y=Y, u=np.zeros((2, 10, 1))), "u holds 2 recordings but y holds 3: give one per recording"),
        (dict(y=[np.zeros(8), np.zeros(6)], u=[np.zeros(8), np.zeros(7)]), "u: recording 1 has 7 samples but y's"),
        (dict(y=Y, u=np.zeros((3, 10, 1, 1))), r"u has shape \(3, 10, 1, 1\) \(rank 4\); give one recording's"),
        (dict(y=Y, y_clean=np.zeros((3, 10, 1))), r"y_clean holds samples of shape \(1,\) but y holds \(2,\)"),
        (dict(y=Y, window=11), r"window=11 is longer than every recording \(y: the longest has 10 samples\)"),
        (dict(y=Y, window=4, stride=0), "stride must be >= 1"),
        (dict(y=Y, dt=0.0), "dt must be the seconds per sample, a number > 0"),
        (dict(y={"a": Y, "b": np.zeros((3, 9, 1))}), r"y\['b'\]: recording 0 has 9 samples but y\['a'\]'s recording"),
        (dict(y={"a": Y, "b": nan_at(Y, (0, 1, 0), np.inf)}), r"y\['b'\]: recording 0 holds inf at sample 1"),
        (dict(y={"a": nan_at(Y, (0, 1, 0)), "b": Y}), r"y\['a'\]: recording 0 holds nan at sample 1"),
        (dict(y={"a": Y, "b": Y}, normalize=True), "several sensors .* are served unnormalised"),
        (dict(y={"a": Y, "clean": Y}), "sensor names must be non-empty strings other than 'clean'"),
        (dict(y={"a": Y, "b": Y}, noise_std={"c": 1.0}), r"noise_std names sensors of y \(\['a', 'b'\]\)"),
        (dict(y={"a": Y, "b": Y}, y_clean={"a": Y}), r"y_clean must have y's sensors \['a', 'b'\]"),
    ],
)
def test_each_mistake_gets_one_message(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Recordings(**kwargs)


def test_no_test_split():
    dm = Recordings(y=Y)
    with pytest.raises(ValueError, match="no test split: Recordings serve the recordings given as training data"):
        dm.test_dataloader()


# ---------------------------------------------------------------------------- a fit
def test_a_tiny_fit_on_one_driven_recording(tmp_path):
    g = rng()
    u = g.normal(size=(80, 1)).astype(np.float32)
    x, y = np.zeros(2), np.zeros((80, 1), np.float32)
    for t in range(80):
        y[t, 0] = x[0] + 0.01 * g.normal()
        x = np.array([x[0] + 0.1 * x[1], x[1] - 0.1 * x[0] + 0.1 * u[t, 0]])
    dm = Recordings(y=y, u=u, dt=0.1, window=20, batch_size=2, val_trajectories=2)
    assert dm.num_train_trajectories == 4
    torch.manual_seed(0)
    model = MultipleShootingModule(
        f=LocallyLinearTransition(state_dim=2, n_matrices=2, hidden=8, input_dim=1),
        g=LinearReadout(state_dim=2, out_features=None),
        state_dim=2,
        n_nodes=4,
        lr=1e-2,
    )
    before = model.f.matrices.detach().clone()
    trainer = fast_trainer(tmp_path, max_epochs=2)
    trainer.fit(model, dm)
    assert model.nodes.num_embeddings == 4 and model.g.out_features == 1
    assert not torch.equal(model.f.matrices.detach(), before)
    assert all(torch.isfinite(p).all() for p in model.parameters())
    assert trainer.state.finished and trainer.current_epoch == 2
