"""FileDataModule: a user's .npy / .npz trajectories, checked against the arrays written here."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import lightning.pytorch as pl
import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp

import datamodules.arrays as arrays_mod
from datamodules.files import FileDataModule
from tests.conftest import fast_trainer

ROOT = Path(__file__).resolve().parents[1]


def rng(seed: int = 0) -> np.random.Generator:
    return np.random.default_rng(seed)


def save(path: Path, **arrays) -> str:
    """np.save for one unnamed array to .npy, np.savez otherwise."""
    if path.suffix == ".npy":
        (a,) = arrays.values()
        np.save(path, a)
    else:
        np.savez(path, **arrays)
    return str(path)


def all_items(ds, key: str = "y") -> np.ndarray:
    return torch.stack([ds[i][key] for i in range(len(ds))]).numpy()


# ---------------------------------------------------------------------------- layouts and values
def test_vectors_npy(tmp_path):
    y = rng().normal(size=(7, 12, 3)).astype(np.float32)
    dm = FileDataModule(train_path=save(tmp_path / "y.npy", y=y), batch_size=4)
    assert dm.num_train_trajectories == 7 and dm.obs_shape == (3,) and dm.seq_len == 12
    assert dm.splits == ("train",)
    dm.prepare_data()
    dm.setup()
    ds = dm.datasets["train"]
    assert isinstance(ds.arrays["y"], np.memmap)  # read lazily from disk
    np.testing.assert_array_equal(all_items(ds), y)
    batch = next(iter(dm.train_dataloader()))
    assert batch["y"].shape == (4, 12, 3) and batch["y"].dtype == torch.float32
    for b, i in enumerate(batch["index"].tolist()):
        np.testing.assert_array_equal(batch["y"][b].numpy(), y[i])
    assert "y_clean" not in batch


def test_float64_is_served_as_float32(tmp_path):
    y = rng().normal(size=(3, 5, 2))
    dm = FileDataModule(train_path=save(tmp_path / "y.npy", y=y))
    dm.setup()
    item = dm.datasets["train"][1]["y"]
    assert item.dtype == torch.float32
    np.testing.assert_allclose(item.numpy(), y[1], rtol=1e-6)


def test_uint8_grey_images(tmp_path):
    y = rng().integers(0, 256, size=(4, 6, 5, 7), dtype=np.uint8)
    dm = FileDataModule(train_path=save(tmp_path / "img.npy", y=y))
    assert dm.obs_shape == (1, 5, 7) and dm.num_train_trajectories == 4
    dm.setup()
    ds = dm.datasets["train"]
    assert ds.arrays["y"].dtype == np.uint8  # stays uint8 on disk / in memory
    served = all_items(ds)
    assert served.shape == (4, 6, 1, 5, 7) and served.dtype == np.float32
    np.testing.assert_allclose(served[:, :, 0], y.astype(np.float64) / 255.0, atol=1e-7)


def test_float_colour_images_npz(tmp_path):
    y = rng().random(size=(3, 4, 2, 5, 6)).astype(np.float32)
    dm = FileDataModule(train_path=save(tmp_path / "img.npz", frames=y), key="frames")
    assert dm.obs_shape == (2, 5, 6)
    dm.setup()
    np.testing.assert_array_equal(all_items(dm.datasets["train"]), y)


@pytest.mark.parametrize("compressed", [False, True])
def test_npz_keys_and_clean_targets(tmp_path, compressed):
    y = rng().normal(size=(5, 8, 2)).astype(np.float32)
    clean = rng(1).normal(size=(5, 8, 2)).astype(np.float32)
    path = tmp_path / "rec.npz"
    (np.savez_compressed if compressed else np.savez)(path, y=y, y_clean=clean, other=np.zeros(3))
    dm = FileDataModule(train_path=str(path), clean_key="y_clean")
    dm.setup()
    ds = dm.datasets["train"]
    # Uncompressed members are memory-mapped straight from the archive; compressed ones are read.
    assert isinstance(ds.arrays["y"], np.memmap) == (not compressed)
    np.testing.assert_array_equal(all_items(ds, "y"), y)
    np.testing.assert_array_equal(all_items(ds, "y_clean"), clean)


def test_fortran_ordered_npz_member(tmp_path):
    y = np.asfortranarray(rng().normal(size=(3, 4, 2)).astype(np.float32))
    dm = FileDataModule(train_path=save(tmp_path / "f.npz", y=y))
    dm.setup()
    np.testing.assert_array_equal(all_items(dm.datasets["train"]), y)


def test_several_files_concatenated(tmp_path):
    parts = [rng(s).normal(size=(n, 6, 2)).astype(np.float32) for s, n in enumerate((3, 1, 4))]
    cleans = [p + 1.0 for p in parts]
    paths = [save(tmp_path / f"p{i}.npy", y=p) for i, p in enumerate(parts)]
    clean_paths = [save(tmp_path / "c.npz", y=np.concatenate(cleans[:2])), save(tmp_path / "c2.npy", y=cleans[2])]
    dm = FileDataModule(train_path=paths, train_clean_path=clean_paths)
    assert dm.num_train_trajectories == 8
    dm.setup()
    ds = dm.datasets["train"]
    np.testing.assert_array_equal(all_items(ds), np.concatenate(parts))
    np.testing.assert_array_equal(all_items(ds, "y_clean"), np.concatenate(cleans))


def test_mixed_uint8_and_float_files(tmp_path):
    a = rng().integers(0, 256, size=(2, 3, 4, 4), dtype=np.uint8)
    b = rng(1).random(size=(1, 3, 4, 4)).astype(np.float32)
    dm = FileDataModule(train_path=[save(tmp_path / "a.npy", y=a), save(tmp_path / "b.npy", y=b)])
    dm.setup()
    served = all_items(dm.datasets["train"])[:, :, 0]
    np.testing.assert_allclose(served, np.concatenate([a / 255.0, b]), atol=1e-6)


# ---------------------------------------------------------------------------- splits
def test_test_fraction_holds_out_last_trajectories(tmp_path):
    y = rng().normal(size=(10, 4, 1)).astype(np.float32)
    clean = y * 0.5
    dm = FileDataModule(train_path=save(tmp_path / "d.npz", y=y, clean=clean), clean_key="clean", test_fraction=0.2)
    assert dm.splits == ("train", "test") and dm.num_train_trajectories == 8
    dm.setup()
    np.testing.assert_array_equal(all_items(dm.datasets["train"]), y[:8])
    np.testing.assert_array_equal(all_items(dm.datasets["test"]), y[8:])
    np.testing.assert_array_equal(all_items(dm.datasets["test"], "y_clean"), clean[8:])
    batch = next(iter(dm.test_dataloader()))
    assert batch["index"].tolist() == [0, 1]  # position in the test split
    # A tiny fraction still holds out one trajectory; one that leaves nothing to train on is refused.
    assert FileDataModule(train_path=str(tmp_path / "d.npz"), test_fraction=0.01).num_train_trajectories == 9
    with pytest.raises(ValueError, match="leaves none to train on"):
        FileDataModule(train_path=save(tmp_path / "one.npy", y=y[:1]), test_fraction=0.5)


class ValidationRecorder(pl.LightningModule):
    """Records the trajectories Lightning's validation loop gives it."""

    def __init__(self):
        super().__init__()
        self.y, self.index = [], []

    def validation_step(self, batch, batch_idx):
        self.y.append(batch["y"].numpy())
        self.index.append(batch["index"].numpy())


def test_val_and_test_files(tmp_path):
    tr = rng(0).normal(size=(6, 10, 2)).astype(np.float32)
    va = rng(1).normal(size=(2, 10, 2)).astype(np.float32)
    te = rng(2).normal(size=(3, 25, 2)).astype(np.float32)  # test trajectories may be longer
    te_clean = te * 2
    dm = FileDataModule(
        train_path=save(tmp_path / "tr.npy", y=tr),
        val_path=[save(tmp_path / "va.npy", y=va)],
        test_path=save(tmp_path / "te.npy", y=te),
        test_clean_path=save(tmp_path / "tec.npy", y=te_clean),
        val_trajectories=3,
    )
    assert dm.splits == ("train", "val", "test") and dm.num_train_trajectories == 6
    dm.setup("fit")
    assert set(dm.datasets) == {"train", "val"}
    np.testing.assert_array_equal(all_items(dm.datasets["val"]), va)
    val_batch = next(iter(dm.split_dataloader("val")))
    np.testing.assert_array_equal(val_batch["y"].numpy(), va)
    # Lightning's validation loop runs on the val files; a model that validates from the training
    # trajectories' own states (the SSM's shooting nodes) gets the evenly spaced training subset.
    seen = ValidationRecorder()
    fast_trainer(tmp_path, max_epochs=1).validate(seen, dm)
    np.testing.assert_array_equal(np.concatenate(seen.y), va)
    ssm_like = ValidationRecorder()
    ssm_like.validates_on_training_trajectories = True
    fast_trainer(tmp_path, max_epochs=1).validate(ssm_like, dm)
    assert np.concatenate(seen.index).tolist() == [0, 1] and np.concatenate(ssm_like.index).tolist() == [0, 2, 5]
    np.testing.assert_array_equal(np.concatenate(ssm_like.y), tr[[0, 2, 5]])  # np.linspace(0, 5, 3).round()
    dm.setup("test")
    np.testing.assert_array_equal(all_items(dm.datasets["test"]), te)
    np.testing.assert_array_equal(all_items(dm.datasets["test"], "y_clean"), te_clean)
    assert next(iter(dm.test_dataloader()))["y"].shape == (3, 25, 2)


def test_no_test_split(tmp_path):
    dm = FileDataModule(train_path=save(tmp_path / "y.npy", y=np.ones((2, 3, 1), np.float32)))
    dm.setup()
    with pytest.raises(ValueError, match="no test split: pass test_path, or test_fraction"):
        dm.test_dataloader()


# ---------------------------------------------------------------------------- normalisation, headers
def test_normalisation_vectors(tmp_path):
    y = (rng().normal(size=(6, 20, 3)) * [1.0, 5.0, 0.1] + [2.0, -3.0, 10.0]).astype(np.float32)
    te = rng(1).normal(size=(2, 20, 3)).astype(np.float32)
    dm = FileDataModule(
        train_path=save(tmp_path / "y.npy", y=y), test_path=save(tmp_path / "t.npy", y=te), normalize=True
    )
    dm.setup()
    y64 = y.astype(np.float64)
    mean, std = y64.mean(axis=(0, 1)), y64.std(axis=(0, 1))
    np.testing.assert_allclose(dm.normalizer.mean.numpy(), mean, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(dm.normalizer.std.numpy(), std, rtol=1e-5)
    served = all_items(dm.datasets["train"]).astype(np.float64)
    np.testing.assert_allclose(served.mean(axis=(0, 1)), 0, atol=1e-5)
    np.testing.assert_allclose(served.std(axis=(0, 1)), 1, atol=1e-5)
    np.testing.assert_allclose(all_items(dm.datasets["test"]), (te - mean) / std, atol=1e-5)
    back = dm.normalizer.denormalize(torch.from_numpy(served.astype(np.float32)))
    np.testing.assert_allclose(back.numpy(), y, atol=1e-4)


def test_normalisation_images_per_channel(tmp_path):
    y = rng().integers(0, 256, size=(3, 4, 2, 5, 5), dtype=np.uint8)
    y[:, :, 1] //= 4  # a darker second channel
    dm = FileDataModule(train_path=save(tmp_path / "img.npy", y=y), normalize=True)
    dm.setup()
    f = y.astype(np.float64) / 255.0
    np.testing.assert_allclose(dm.normalizer.mean.numpy(), f.mean(axis=(0, 1, 3, 4)), rtol=1e-5)
    np.testing.assert_allclose(dm.normalizer.std.numpy(), f.std(axis=(0, 1, 3, 4)), rtol=1e-5)
    served = all_items(dm.datasets["train"]).astype(np.float64)
    np.testing.assert_allclose(served.mean(axis=(0, 1, 3, 4)), 0, atol=1e-5)
    np.testing.assert_allclose(served.std(axis=(0, 1, 3, 4)), 1, atol=1e-5)


def test_sizes_come_from_headers_only(tmp_path, monkeypatch):
    y = rng().normal(size=(9, 4, 2)).astype(np.float32)
    paths = [save(tmp_path / "a.npy", y=y), save(tmp_path / "b.npz", y=y[:5])]

    def no_reading(*args, **kwargs):
        raise AssertionError("data read at construction")

    monkeypatch.setattr(arrays_mod, "open_array", no_reading)
    monkeypatch.setattr(np, "load", no_reading)
    dm = FileDataModule(train_path=paths, test_fraction=0.25)
    assert dm.num_train_trajectories == 14 - round(14 * 0.25) == 10
    assert dm.obs_shape == (2,) and dm.seq_len == 4


def test_arguments_are_yaml_expressible(tmp_path):
    from jsonargparse import ArgumentParser

    a, b = (
        save(tmp_path / "a.npy", y=np.ones((2, 3, 1), np.float32)),
        save(tmp_path / "b.npy", y=np.ones((1, 3, 1), np.float32)),
    )
    parser = ArgumentParser()
    parser.add_class_arguments(FileDataModule, "data")
    cfg = parser.parse_string(f"data:\n  train_path: [{a}, {b}]\n  normalize: true\n  test_fraction: 0.3\n")
    dm = FileDataModule(**cfg.data.as_dict())
    assert dm.num_train_trajectories == 2
    cfg = parser.parse_string(f"data:\n  train_path: {a}\n  window: 2\n  stride: 1\n")
    assert FileDataModule(**cfg.data.as_dict()).num_train_trajectories == 4  # 2 recordings of 3: windows at 0, 1


# ---------------------------------------------------------------------------- recordings cut into windows
def windows_by_hand(recordings: list[np.ndarray], origins: list[tuple[int, int]], w: int) -> np.ndarray:
    return np.stack([recordings[r][s : s + w] for r, s in origins])


def test_one_recording_file_is_windowed(tmp_path):
    y = rng().normal(size=(47, 2)).astype(np.float32)
    u = rng(1).normal(size=(47, 1)).astype(np.float32)
    path = save(tmp_path / "one.npz", y=y, u=u)
    dm = FileDataModule(train_path=path, input_key="u", window=10, batch_size=3)
    # windows of 10 at 0, 10, 20, 30, and the one ending at 47 (37)
    origins = [(0, 0), (0, 10), (0, 20), (0, 30), (0, 37)]
    assert dm.num_train_trajectories == 5 and dm.seq_len == 10 and dm.obs_shape == (2,) and dm.input_dim == 1
    assert dm.windows["train"].origins.tolist() == [list(o) for o in origins]
    assert dm.generator_params()["window"] == 10 and dm.generator_params()["stride"] == 10
    dm.setup("fit")
    for batch in dm.train_dataloader():
        index = batch["index"].numpy()
        np.testing.assert_array_equal(batch["y"].numpy(), windows_by_hand([y], origins, 10)[index])
        np.testing.assert_array_equal(batch["u"].numpy(), windows_by_hand([u], origins, 10)[index])
    # the default window: 47 samples rounded down to 40, at 0 and ending at 47
    default = FileDataModule(train_path=path)
    assert default.windows["train"].origins.tolist() == [[0, 0], [0, 7]] and default.seq_len == 40
    # a scalar recording [T] is one recording of one component
    scalar = FileDataModule(train_path=save(tmp_path / "s.npy", y=y[:, 0]), window=20)
    assert scalar.obs_shape == (1,) and scalar.num_train_trajectories == 3
    scalar.setup()
    served = all_items(scalar.datasets["train"])
    np.testing.assert_array_equal(served, np.stack([y[0:20, :1], y[20:40, :1], y[27:47, :1]]))


def test_files_of_different_lengths_are_windowed(tmp_path):
    a = rng(0).normal(size=(23, 2)).astype(np.float32)  # one recording
    b = rng(1).normal(size=(3, 14, 2)).astype(np.float32)  # three of 14 samples
    paths = [save(tmp_path / "a.npz", y=a, clean=a + 1), save(tmp_path / "b.npz", y=b, clean=b + 1)]
    dm = FileDataModule(train_path=paths, clean_key="clean", batch_size=4, normalize=True)
    # the default window: the shortest, 14, rounded down to 10; 23 -> 0, 10, 13; each 14 -> 0, 4
    recordings = [a, *b]
    origins = [(0, 0), (0, 10), (0, 13), (1, 0), (1, 4), (2, 0), (2, 4), (3, 0), (3, 4)]
    assert dm.windows["train"].origins.tolist() == [list(o) for o in origins]
    assert dm.num_train_trajectories == 9 and dm.seq_len == 10
    dm.setup("fit")
    y_win = windows_by_hand(recordings, origins, 10).astype(np.float64)
    mean, std = y_win.reshape(-1, 2).mean(0), y_win.reshape(-1, 2).std(0)
    np.testing.assert_allclose(all_items(dm.datasets["train"]), (y_win - mean) / std, atol=1e-5)
    np.testing.assert_allclose(all_items(dm.datasets["train"], "y_clean"), (y_win + 1 - mean) / std, atol=1e-5)
    # a window longer than some recordings leaves them out, and says so
    with pytest.warns(UserWarning, match=r"train_path: recordings 1 \(14 samples\), 2 \(14 samples\), 3 \(14"):
        long = FileDataModule(train_path=paths, window=15)
    assert long.windows["train"].origins.tolist() == [[0, 0], [0, 8]]
    with pytest.raises(ValueError, match=r"window=30 is longer than every recording \(train_path: the longest has 23"):
        FileDataModule(train_path=paths, window=30)


def test_recordings_of_one_length_stay_mapped_and_whole(tmp_path):
    y = rng().normal(size=(4, 20, 2)).astype(np.float32)
    path = save(tmp_path / "y.npy", y=y)
    dm = FileDataModule(train_path=path)
    assert dm.windows["train"].whole and dm.generator_params()["window"] is None
    dm.setup()
    assert isinstance(dm.datasets["train"].arrays["y"], np.memmap)
    # given a window, they are cut too
    cut = FileDataModule(train_path=path, window=8, stride=6)
    origins = [(r, s) for r in range(4) for s in (0, 6, 12)]  # 12 + 8 = 20: no extra window
    assert cut.windows["train"].origins.tolist() == [list(o) for o in origins]
    cut.setup()
    np.testing.assert_array_equal(all_items(cut.datasets["train"]), windows_by_hand(list(y), origins, 8))


def test_test_fraction_of_windows_never_overlaps_training(tmp_path):
    y = rng().normal(size=(40, 1)).astype(np.float32)
    dm = FileDataModule(train_path=save(tmp_path / "y.npy", y=y), window=10, stride=5, test_fraction=0.3)
    # windows at 0, 5, ..., 30; the last round(0.3 * 7) = 2 (25, 30) are the test split; 20 shares samples with 25
    assert dm.num_train_trajectories == 4
    dm.setup()
    np.testing.assert_array_equal(
        all_items(dm.datasets["train"]), windows_by_hand([y], [(0, s) for s in (0, 5, 10, 15)], 10)
    )
    np.testing.assert_array_equal(all_items(dm.datasets["test"]), windows_by_hand([y], [(0, 25), (0, 30)], 10))


def test_one_recording_file_of_several_sensors(tmp_path):
    pos = rng(0).normal(size=(30, 2)).astype(np.float32)
    enc = rng(1).normal(size=(30, 1)).astype(np.float32)
    enc[1::3] = np.nan
    path = save(tmp_path / "rec.npz", pos=pos, enc=enc)
    dm = FileDataModule(train_path=path, key=["pos", "enc"], window=10)
    assert dm.obs_shape == (3,) and dm.num_train_trajectories == 3
    assert dm.sensor_layout == [
        {"name": "pos", "shape": [2], "noise_std": 1.0},
        {"name": "enc", "shape": [1], "noise_std": 1.0},
    ]
    dm.setup()
    packed = np.concatenate([pos, enc], -1)
    np.testing.assert_array_equal(
        all_items(dm.datasets["train"]), windows_by_hand([packed], [(0, 0), (0, 10), (0, 20)], 10)
    )


def test_inputs_beside_one_recording(tmp_path):
    y = np.zeros((47, 2), np.float32)
    with pytest.raises(
        ValueError, match=r"holds 1 trajectories of 46 inputs but its measurements hold 1 of 47 samples"
    ):
        FileDataModule(train_path=save(tmp_path / "a.npz", y=y, u=np.zeros((46, 1), np.float32)), input_key="u")
    with pytest.raises(
        ValueError, match=r"must be a float \(or signed integer\) array \[T, m\], got shape \(1, 47, 1\)"
    ):
        FileDataModule(train_path=save(tmp_path / "b.npz", y=y, u=np.zeros((1, 47, 1), np.float32)), input_key="u")


# ---------------------------------------------------------------------------- bad input
def test_missing_file(tmp_path):
    missing = tmp_path / "nope.npy"
    with pytest.raises(FileNotFoundError, match=r"train_path: .*nope\.npy does not exist.*expected a \.npy or \.npz"):
        FileDataModule(train_path=str(missing))
    good = save(tmp_path / "y.npy", y=np.ones((2, 3, 1), np.float32))
    with pytest.raises(FileNotFoundError, match=r"test_path: .*gone\.npz does not exist"):
        FileDataModule(train_path=good, test_path=str(tmp_path / "gone.npz"))


def test_ragged_trajectories(tmp_path):
    ragged = np.empty(2, dtype=object)
    ragged[0], ragged[1] = np.zeros((5, 2)), np.zeros((7, 2))
    np.save(tmp_path / "r.npy", ragged, allow_pickle=True)
    with pytest.raises(ValueError, match="object array .*: save each set of recordings of one length as one numeric"):
        FileDataModule(train_path=str(tmp_path / "r.npy"))
    np.savez(tmp_path / "r.npz", y=ragged)  # a pickled list inside an .npz
    with pytest.raises(ValueError, match=r"r\.npz.*object array.*in its own file, and give the files as a list"):
        FileDataModule(train_path=str(tmp_path / "r.npz"))


@pytest.mark.parametrize("shape", [(1, 2, 3, 4, 5, 6), ()])
def test_wrong_rank(tmp_path, shape):
    path = save(tmp_path / "w.npy", y=np.zeros(shape, np.float32))
    with pytest.raises(
        ValueError,
        match=rf"shape {re.escape(str(shape))}.*accepted layouts: \[T\] or \[T, D\] one recording, \[N, T, D\] vectors",
    ):
        FileDataModule(train_path=path)


def test_mismatched_shapes(tmp_path):
    a = save(tmp_path / "a.npy", y=np.zeros((2, 5, 3), np.float32))
    b = save(tmp_path / "b.npy", y=np.zeros((2, 6, 4), np.float32))
    c = save(tmp_path / "c.npy", y=np.zeros((2, 5, 4), np.float32))
    with pytest.raises(ValueError, match=r"b\.npy holds samples of shape \(4,\) but .*a\.npy holds \(3,\)"):
        FileDataModule(train_path=[a, b])
    with pytest.raises(
        ValueError, match=r"val_path: observations of shape \(4,\) do not match the training observations \(3,\)"
    ):
        FileDataModule(train_path=a, val_path=c)
    # grey [N, T, H, W] and one-channel [N, T, 1, H, W] images are the same observations
    g = save(tmp_path / "g.npy", y=np.zeros((1, 2, 4, 4), np.uint8))
    g1 = save(tmp_path / "g1.npy", y=np.zeros((1, 3, 1, 4, 4), np.uint8))
    assert FileDataModule(train_path=g, test_path=g1).obs_shape == (1, 4, 4)


def test_clean_targets_of_another_shape(tmp_path):
    y = np.zeros((3, 5, 2), np.float32)
    path = save(tmp_path / "d.npz", y=y, y_clean=np.zeros((3, 5, 1), np.float32))
    with pytest.raises(
        ValueError, match=r"clean targets have shape \(3, 5, 1\) but the measurements have shape \(3, 5, 2\)"
    ):
        FileDataModule(train_path=path, clean_key="y_clean")
    with pytest.raises(ValueError, match=r"train_clean_path: the clean targets have shape \(2, 5, 2\)"):
        FileDataModule(train_path=path, train_clean_path=save(tmp_path / "c.npy", y=y[:2]))
    with pytest.raises(ValueError, match="holds no array 'clean'"):
        FileDataModule(train_path=path, clean_key="clean")
    with pytest.raises(
        ValueError, match=r"clean_key applies to \.npz files.*pass the noiseless targets as train_clean_path"
    ):
        FileDataModule(train_path=save(tmp_path / "y.npy", y=y), clean_key="y_clean")


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_values(tmp_path, bad):
    y = np.zeros((3, 5, 2), np.float32)
    y[1, 3, 0] = bad
    good = save(tmp_path / "good.npy", y=np.zeros((3, 5, 2), np.float32))
    dm = FileDataModule(train_path=[good, save(tmp_path / "bad.npy", y=y)])
    with pytest.raises(
        ValueError, match=r"bad\.npy holds a non-finite value .* at index \(1, 3, 0\) \(trajectory, time"
    ):
        dm.setup()
    clean = save(tmp_path / "rec.npz", y=np.zeros((3, 5, 2), np.float32), y_clean=y)
    with pytest.raises(ValueError, match=r"rec\.npz \(array 'y_clean'\) holds a non-finite value .* \(1, 3, 0\)"):
        FileDataModule(train_path=clean, clean_key="y_clean").setup()


@pytest.mark.parametrize("shape", [(0, 5, 2), (3, 0, 2), (2, 3, 0, 4)])
def test_empty_files(tmp_path, shape):
    path = save(tmp_path / "e.npz", y=np.zeros(shape, np.float32))
    with pytest.raises(ValueError, match=r"e\.npz \(array 'y'\) is empty .*at least one trajectory"):
        FileDataModule(train_path=path)


def test_other_bad_arguments(tmp_path):
    good = save(tmp_path / "y.npy", y=np.ones((4, 3, 1), np.float32))
    (tmp_path / "notes.txt").write_text("1 2 3")
    with pytest.raises(ValueError, match="neither .npy nor .npz"):
        FileDataModule(train_path=str(tmp_path / "notes.txt"))
    (tmp_path / "fake.npy").write_text("not numpy")
    with pytest.raises(ValueError, match="is not a NumPy .npy array"):
        FileDataModule(train_path=str(tmp_path / "fake.npy"))
    with pytest.raises(ValueError, match="either test_path or test_fraction"):
        FileDataModule(train_path=good, test_path=good, test_fraction=0.5)
    with pytest.raises(ValueError, match="train_path is required"):
        FileDataModule(train_path=[])
    with pytest.raises(ValueError, match="dtype <U"):
        FileDataModule(train_path=save(tmp_path / "s.npy", y=np.full((2, 2, 2), "a")))


# ---------------------------------------------------------------------------- example data
def test_example_oscillator_data(tmp_path):
    spec = importlib.util.spec_from_file_location("make_oscillator_data", ROOT / "examples" / "make_oscillator_data.py")
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    out = example.main(["--out", str(tmp_path / "osc.npz"), "--n", "40", "--steps", "100"])

    data = np.load(out)
    y, clean, t = data["y"], data["y_clean"], data["t"]
    assert y.shape == clean.shape == (40, 100, 2) and y.dtype == np.float32
    np.testing.assert_allclose(np.diff(t), 0.05, rtol=1e-5)
    # y_clean solves x'' + 2 zeta omega x' + omega^2 x = 0 (default zeta 0.05, omega pi) from its first sample.
    zeta, omega = 0.05, np.pi
    for j in (0, 17):
        sol = solve_ivp(
            lambda _, s: [s[1], -2 * zeta * omega * s[1] - omega**2 * s[0]],
            (0, float(t[-1])),
            clean[j, 0].astype(np.float64),
            t_eval=t.astype(np.float64),
            rtol=1e-10,
            atol=1e-10,
        )
        np.testing.assert_allclose(sol.y.T, clean[j], atol=1e-5)
    noise = (y - clean).astype(np.float64).ravel()
    assert abs(noise.std() - 0.05) < 5 * 0.05 / np.sqrt(2 * noise.size)

    dm = FileDataModule(train_path=str(out), clean_key="y_clean", test_fraction=0.2, normalize=True)
    assert dm.num_train_trajectories == 32 and dm.obs_shape == (2,)
    dm.setup()
    np.testing.assert_allclose(dm.normalizer.mean.numpy(), y[:32].astype(np.float64).mean(axis=(0, 1)), atol=1e-6)
    assert len(dm.datasets["test"]) == 8
