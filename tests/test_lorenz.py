"""LorenzDataModule: dynamics against scipy, noise statistics, cut pieces, normalisation, cache."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import stats
from scipy.integrate import solve_ivp

from datamodules.lorenz import LorenzDataModule, lorenz_rk4

SIGMA, BETA, RHO, DT = 10.0, 8.0 / 3.0, 28.0, 0.005
SMALL = dict(n_train=6, train_steps=1000, n_test=5, test_steps=200, val_trajectories=4)


def lorenz_ode(t, s):
    """The Lorenz vector field, written out independently of the module."""
    return [SIGMA * (s[1] - s[0]), s[0] * (RHO - s[2]) - s[1], s[0] * s[1] - BETA * s[2]]


def reference(x0: np.ndarray, steps: int, dt: float) -> np.ndarray:
    """[steps, 3] samples at t = k dt from a tight-tolerance adaptive integrator."""
    t = np.arange(steps) * dt
    sol = solve_ivp(lorenz_ode, (0.0, t[-1]), x0, method="DOP853", rtol=1e-11, atol=1e-11, t_eval=t)
    assert sol.success
    return sol.y.T


def small(tmp_path, **kw) -> LorenzDataModule:
    return LorenzDataModule(data_dir=str(tmp_path), **{**SMALL, **kw})


# ---------------------------------------------------------------------------- dynamics
def test_rk4_matches_scipy_and_is_fourth_order():
    rng = np.random.default_rng(123)
    x0 = rng.uniform(-10, 10, size=(6, 3))
    errors = []
    for dt in (DT, DT / 2):
        steps = int(round(1.0 / dt)) + 1  # 1 s horizon
        ours = lorenz_rk4(x0, steps, dt, SIGMA, BETA, RHO)
        assert ours.shape == (6, steps, 3) and ours.dtype == np.float64
        np.testing.assert_array_equal(ours[:, 0], x0)
        errors.append(max(np.abs(ours[j] - reference(x0[j], steps, dt)).max() for j in range(len(x0))))
    # RK4's global error ~ C dt^4: small in absolute terms (states reach |x| ~ 40) ...
    assert errors[0] < 1e-3, errors
    # ... and halving dt divides it by ~2^4 = 16 (Euler would give 2, RK2 4).
    assert 12 < errors[0] / errors[1] < 21, errors


def test_generated_states_follow_lorenz(tmp_path):
    dm = small(tmp_path)
    arrays = dm.generate("train")
    state = arrays["state"]
    assert state.shape == (6, 1000, 3) and arrays["y"].shape == (6, 1000, 1)
    assert arrays["y"].dtype == np.float32
    steps = 201  # 1 s
    for j in range(len(state)):
        ref = reference(state[j, 0].astype(np.float64), steps, DT)
        # RK4 error (< 1e-3, see above) plus float32 storage of the states (|x| <~ 50: ~3e-6).
        np.testing.assert_allclose(state[j, :steps], ref, atol=1.5e-3, rtol=0)
    # The noiseless measurement is the first coordinate.
    np.testing.assert_array_equal(arrays["y_clean"][..., 0], state[..., 0])


def test_initial_states_uniform_and_streams_separate(tmp_path):
    dm = small(tmp_path, n_train=40, train_steps=10, n_test=40, test_steps=10)
    train, test = dm.generate("train"), dm.generate("test")
    x0 = np.concatenate([train["state"][:, 0], test["state"][:, 0]]).ravel()
    assert np.abs(x0).max() <= 10.0
    assert stats.kstest(x0, stats.uniform(loc=-10, scale=20).cdf).pvalue > 1e-3
    # Train and test come from different random streams ...
    assert not np.allclose(train["state"][:, 0], test["state"][:, 0])
    # ... deterministic given the seed, different for another seed.
    again = small(tmp_path, n_train=40, train_steps=10, n_test=40, test_steps=10).generate("train")
    np.testing.assert_array_equal(again["y"], train["y"])
    other = small(tmp_path, n_train=40, train_steps=10, n_test=40, test_steps=10, seed=1).generate("train")
    assert not np.allclose(other["state"][:, 0], train["state"][:, 0])


def test_measurement_noise_statistics(tmp_path):
    dm = small(tmp_path, n_train=20, train_steps=1000)
    arrays = dm.generate("train")
    noise = (arrays["y"].astype(np.float64) - arrays["y_clean"]).ravel()
    n = noise.size
    # Sampling standard errors of the mean (s/sqrt n) and of the std (s/sqrt(2n)) of Gaussian noise; 5 SE.
    assert abs(noise.mean()) < 5 * 2.5 / np.sqrt(n)
    assert abs(noise.std() - 2.5) < 5 * 2.5 / np.sqrt(2 * n)
    # White in time: lag-1 autocorrelation within 5 SE (1/sqrt n) of 0.
    per_traj = noise.reshape(20, 1000)
    lag1 = (per_traj[:, 1:] * per_traj[:, :-1]).mean() / per_traj.var()
    assert abs(lag1) < 5 / np.sqrt(n)
    # The noise does not touch the state.
    np.testing.assert_array_equal(arrays["y_clean"][..., 0], arrays["state"][..., 0])


# ---------------------------------------------------------------------------- pieces and cache
def test_paper_piece_counts_without_generating(tmp_path):
    dms = {T: LorenzDataModule(piece_length=T, data_dir=str(tmp_path)) for T in (10, 100, 1000, 10_000)}
    for T, dm in dms.items():
        assert dm.num_train_trajectories == 1000 * 10_000 // T
        assert dm.cache_dir == dms[10_000].cache_dir  # one cache for the whole length study
        assert dm.batch_size == 40 and dm.normalize
    default = LorenzDataModule(data_dir=str(tmp_path))
    assert default.piece_length == 10_000 and default.num_train_trajectories == 1000
    assert not any(tmp_path.iterdir())  # nothing generated


@pytest.mark.parametrize("bad", [300, 7, 20_000])
def test_invalid_piece_length(bad, tmp_path):
    with pytest.raises(
        ValueError, match=rf"piece_length={bad} does not divide train_steps=10000.*Valid choices: \[1, 2, 4, 5, 8, 10,"
    ):
        LorenzDataModule(piece_length=bad, data_dir=str(tmp_path))
    with pytest.raises(ValueError, match="piece_length must be a positive integer"):
        LorenzDataModule(piece_length=0, data_dir=str(tmp_path))


def test_pieces_are_consecutive_segments(tmp_path):
    dm = small(tmp_path, piece_length=100, normalize=False)
    assert dm.num_train_trajectories == 60
    dm.prepare_data()
    dm.setup()
    raw = {k: np.load(dm.split_file("train", k)) for k in ("y", "y_clean", "state")}
    ds = dm.datasets["train"]
    assert len(ds) == 60 and ds.seq_len == 100 and dm.obs_shape == (1,)
    assert ds.arrays["y"].size == raw["y"].size  # same number of samples
    assert not ds.arrays["y"].flags.owndata  # a view of the memory-mapped cache, not a copy
    for j in range(6):
        for k in range(10):
            item = ds[j * 10 + k]
            assert int(item["index"]) == j * 10 + k
            for key in raw:
                np.testing.assert_array_equal(item[key].numpy(), raw[key][j, k * 100 : (k + 1) * 100])
    # The test set is never cut.
    dm.setup("test")
    assert dm.datasets["test"].arrays["y"].shape == (5, 200, 1)
    batch = next(iter(dm.train_dataloader()))
    assert batch["y"].shape == (40, 100, 1) and batch["y"].dtype == torch.float32
    assert batch["state"].shape == (40, 100, 3) and batch["index"].dtype == torch.long


def test_cache_is_shared_across_piece_lengths(tmp_path, monkeypatch):
    calls = []
    original = LorenzDataModule.generate

    def counting(self, split):
        calls.append(split)
        return original(self, split)

    monkeypatch.setattr(LorenzDataModule, "generate", counting)
    first = small(tmp_path, piece_length=1000)
    first.prepare_data()
    assert sorted(calls) == ["test", "train"]
    for T in (10, 100, 500):
        dm = small(tmp_path, piece_length=T)
        dm.prepare_data()
        dm.setup()
        assert len(dm.datasets["train"]) == dm.num_train_trajectories == 6 * 1000 // T
    assert sorted(calls) == ["test", "train"]  # generated once
    assert len([p for p in tmp_path.iterdir() if p.is_dir()]) == 1
    # A parameter that changes the data does get its own cache.
    small(tmp_path, noise_std=1.0).prepare_data()
    assert len(calls) == 4 and len([p for p in tmp_path.iterdir() if p.is_dir()]) == 2


# ---------------------------------------------------------------------------- normalisation
def test_normalisation_statistics_and_round_trip(tmp_path):
    dm = small(tmp_path, piece_length=250)
    dm.prepare_data()
    dm.setup()
    raw_y = np.load(dm.split_file("train", "y")).astype(np.float64)
    raw_clean = np.load(dm.split_file("train", "y_clean")).astype(np.float64)
    mean, std = raw_y.mean(), raw_y.std()
    norm = dm.normalizer
    np.testing.assert_allclose(norm.mean.numpy(), [mean], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(norm.std.numpy(), [std], rtol=1e-5)

    ds = dm.datasets["train"]
    served = torch.stack([ds[i]["y"] for i in range(len(ds))]).double()
    assert abs(served.mean().item()) < 1e-5 and abs(served.std(unbiased=False).item() - 1) < 1e-5
    np.testing.assert_allclose(served.numpy().reshape(raw_y.shape), (raw_y - mean) / std, atol=1e-5)
    clean = torch.stack([ds[i]["y_clean"] for i in range(len(ds))]).double().numpy()
    np.testing.assert_allclose(clean.reshape(raw_clean.shape), (raw_clean - mean) / std, atol=1e-5)
    # The state stays in original units.
    np.testing.assert_array_equal(ds[3]["state"].numpy(), np.load(dm.split_file("train", "state"))[0, 750:1000])

    # Test split: normalised with the training statistics; denormalize gives original units back.
    dm.setup("test")
    raw_test = np.load(dm.split_file("test", "y"))
    item = dm.datasets["test"][2]["y"]
    np.testing.assert_allclose(item.numpy(), (raw_test[2] - mean) / std, atol=1e-5)
    np.testing.assert_allclose(norm.denormalize(item).numpy(), raw_test[2], atol=1e-4)
    y = torch.from_numpy(raw_test[:3])
    np.testing.assert_allclose(norm.denormalize(norm.normalize(y)).numpy(), raw_test[:3], atol=1e-5)


def test_statistics_survive_state_dict(tmp_path):
    dm = small(tmp_path)
    dm.prepare_data()
    dm.setup()
    state = dm.state_dict()
    path = tmp_path / "dm_state.pt"
    torch.save(state, path)  # as inside a Lightning checkpoint
    loaded = torch.load(path, weights_only=False)

    # A fresh DataModule over *other* data (another seed) must use the stored statistics, not recompute.
    fresh = small(tmp_path, seed=7)
    fresh.load_state_dict(loaded)
    fresh.prepare_data()
    fresh.setup()
    torch.testing.assert_close(fresh.normalizer.mean, dm.normalizer.mean, rtol=0, atol=0)
    torch.testing.assert_close(fresh.normalizer.std, dm.normalizer.std, rtol=0, atol=0)
    own_mean = np.load(fresh.split_file("train", "y")).astype(np.float64).mean()
    assert abs(own_mean - dm.normalizer.mean.item()) > 1e-3  # the data really differ
    raw = np.load(fresh.split_file("train", "y"))[1]
    expected = (raw - dm.normalizer.mean.numpy()) / dm.normalizer.std.numpy()
    np.testing.assert_allclose(fresh.datasets["train"][1]["y"].numpy(), expected, atol=1e-5)
    assert state["generator_params"]["seed"] == 0 and "piece_length" not in state["generator_params"]


def test_arguments_are_yaml_expressible(tmp_path):
    from jsonargparse import ArgumentParser

    parser = ArgumentParser()
    parser.add_class_arguments(LorenzDataModule, "data")
    cfg = parser.parse_string(f"data:\n  piece_length: 100\n  data_dir: {tmp_path}\n  noise_std: 1.5\n")
    dm = LorenzDataModule(**cfg.data.as_dict())
    assert dm.num_train_trajectories == 100_000 and dm.noise_std == 1.5 and dm.rho == 28.0
