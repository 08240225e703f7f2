"""Moving MNIST: IDX reading, deterministic trajectories, bouncing motion, rendering, DataModule."""

from __future__ import annotations

import gzip
import math
import pickle
import struct
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy import stats

from datamodules.mnist_idx import (
    IDXFormatError,
    check_mnist_files,
    load_mnist,
    load_mnist_images,
    read_idx,
)
from datamodules.moving_mnist import MovingMNISTDataModule, MovingMNISTDataset, trajectory

# The real MNIST files live in the `shared` folder beside the repository root (CI: ../shared).
SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
HAVE_REAL_MNIST = all(
    (SHARED_DATA / "MNIST" / "raw" / f"{p}-{k}-ubyte.gz").is_file()
    for p in ("train", "t10k")
    for k in ("images-idx3", "labels-idx1")
)
needs_real_mnist = pytest.mark.skipif(
    not HAVE_REAL_MNIST, reason=f"real MNIST files not found under {SHARED_DATA}/MNIST/raw"
)

TYPE_CODES = {
    np.dtype(np.uint8): 0x08,
    np.dtype(np.int8): 0x09,
    np.dtype(np.int16): 0x0B,
    np.dtype(np.int32): 0x0C,
    np.dtype(np.float32): 0x0D,
    np.dtype(np.float64): 0x0E,
}


# ---------------------------------------------------------------------------------- helpers
def write_idx(path: Path, a: np.ndarray, gz: bool = False, header: bytes | None = None) -> Path:
    """A minimal IDX writer: 0, 0, type code, ndim, big-endian int32 sizes, big-endian data."""
    a = np.asarray(a)
    if header is None:
        header = bytes([0, 0, TYPE_CODES[a.dtype], a.ndim]) + struct.pack(f">{a.ndim}i", *a.shape)
    data = header + a.astype(a.dtype.newbyteorder(">")).tobytes()
    path.parent.mkdir(parents=True, exist_ok=True)
    if gz:
        path = path.with_name(path.name + ".gz")
        with gzip.open(path, "wb") as f:
            f.write(data)
    else:
        path.write_bytes(data)
    return path


def make_digits(n: int, size: int, rng: np.random.Generator) -> np.ndarray:
    """Digit-like uint8 images: zero background with a random blob of values up to 255."""
    d = np.zeros((n, size, size), np.uint8)
    for k in range(n):
        mask = rng.random((size, size)) < 0.5
        d[k][mask] = rng.integers(1, 256, size=int(mask.sum()))
        d[k][size // 2, size // 2] = 255
    return d


def write_tiny_mnist(root: Path, size: int = 8, n_train: int = 30, n_test: int = 12, gz: bool = True, seed: int = 0):
    rng = np.random.default_rng(seed)
    out = {}
    for split, prefix, n in (("train", "train", n_train), ("test", "t10k", n_test)):
        images, labels = make_digits(n, size, rng), rng.integers(0, 10, size=n).astype(np.uint8)
        raw = root / "MNIST" / "raw"
        write_idx(raw / f"{prefix}-images-idx3-ubyte", images, gz=gz)
        write_idx(raw / f"{prefix}-labels-idx1-ubyte", labels, gz=gz)
        out[split] = (images, labels)
    return out


@pytest.fixture
def tiny(tmp_path):
    """Tiny MNIST files (8x8 digits) under tmp_path and the arrays they hold."""
    return tmp_path, write_tiny_mnist(tmp_path)


def tiny_dm(root: Path, **kw) -> MovingMNISTDataModule:
    args = dict(
        mnist_root=str(root),
        n_train=40,
        n_test=10,
        image_size=24,
        digit_size=8,
        step=3.0,
        batch_size=8,
        val_trajectories=5,
        data_dir=str(root / "cache"),
    )
    args.update(kw)
    return MovingMNISTDataModule(**args)


def naive_frames(digits: np.ndarray, digit_indices, top_left, image_size: int) -> np.ndarray:
    """Max-composition pixel by pixel, in float64 in [0, 1]."""
    T, n, _ = top_left.shape
    s = digits.shape[1]
    canvas = np.zeros((T, image_size, image_size))
    for t in range(T):
        for d in range(n):
            r, c = int(top_left[t, d, 0]), int(top_left[t, d, 1])
            for a in range(s):
                for b in range(s):
                    canvas[t, r + a, c + b] = max(canvas[t, r + a, c + b], digits[digit_indices[d]][a, b] / 255.0)
    return canvas


# ---------------------------------------------------------------------------------- IDX reading
@pytest.mark.parametrize("gz", [False, True])
@pytest.mark.parametrize(
    "dtype,shape",
    [
        (np.uint8, (5, 7, 3)),
        (np.uint8, (11,)),
        (np.int16, (4, 6)),
        (np.int32, (3, 2, 2)),
        (np.float32, (9,)),
        (np.float64, (2, 3)),
    ],
)
def test_read_idx_round_trip(tmp_path, gz, dtype, shape):
    rng = np.random.default_rng(1)
    a = (
        (rng.normal(size=shape) * 1000).astype(dtype)
        if dtype not in (np.uint8,)
        else rng.integers(0, 256, size=shape).astype(np.uint8)
    )
    path = write_idx(tmp_path / "x-idx", a, gz=gz)
    b = read_idx(path)
    assert b.shape == a.shape and b.dtype == np.dtype(dtype) and b.dtype.isnative
    np.testing.assert_array_equal(b, a)


@pytest.mark.parametrize("gz", [False, True])
def test_load_mnist_reads_gz_and_raw_layout(tmp_path, gz):
    arrays = write_tiny_mnist(tmp_path, gz=gz)
    for split in ("train", "test"):
        images, labels = load_mnist(tmp_path, split)
        np.testing.assert_array_equal(images, arrays[split][0])
        np.testing.assert_array_equal(labels, arrays[split][1])


def test_bad_magic_is_a_clear_error(tmp_path):
    a = np.zeros((2, 3, 3), np.uint8)
    path = write_idx(tmp_path / "bad", a, header=b"\x12\x34\x08\x03" + struct.pack(">3i", 2, 3, 3))
    with pytest.raises(ValueError, match="bad IDX magic number 0x12340803"):
        read_idx(path)
    # unknown type code
    path = write_idx(tmp_path / "bad2", a, header=b"\x00\x00\x07\x03" + struct.pack(">3i", 2, 3, 3))
    with pytest.raises(IDXFormatError, match="magic"):
        read_idx(path)
    # a labels file where the images should be: a valid IDX file with the wrong MNIST magic
    raw = tmp_path / "root" / "MNIST" / "raw"
    write_idx(raw / "train-images-idx3-ubyte", np.zeros(4, np.uint8))
    with pytest.raises(IDXFormatError, match=r"magic number 0x00000801, but MNIST images have 0x00000803"):
        load_mnist_images(tmp_path / "root", "train")


def test_truncated_and_oversized_files_are_clear_errors(tmp_path):
    a = np.arange(24, dtype=np.uint8).reshape(2, 3, 4)
    good = write_idx(tmp_path / "a", a).read_bytes()
    (tmp_path / "short").write_bytes(good[:-5])
    with pytest.raises(IDXFormatError, match="truncated"):
        read_idx(tmp_path / "short")
    (tmp_path / "long").write_bytes(good + b"\x00")
    with pytest.raises(IDXFormatError, match="more data than its header"):
        read_idx(tmp_path / "long")
    (tmp_path / "hdr").write_bytes(good[:6])
    with pytest.raises(IDXFormatError, match="truncated"):
        read_idx(tmp_path / "hdr")
    with gzip.open(tmp_path / "c.gz", "wb") as f:
        f.write(good)
    (tmp_path / "cut.gz").write_bytes((tmp_path / "c.gz").read_bytes()[:-12])
    with pytest.raises(IDXFormatError):
        read_idx(tmp_path / "cut.gz")


def test_missing_files_error_names_looked_up_paths(tmp_path):
    raw = tmp_path / "MNIST" / "raw"
    with pytest.raises(FileNotFoundError) as e:
        check_mnist_files(tmp_path)
    msg = str(e.value)
    for name in (
        "train-images-idx3-ubyte",
        "train-labels-idx1-ubyte",
        "t10k-images-idx3-ubyte",
        "t10k-labels-idx1-ubyte",
    ):
        assert str(raw / f"{name}.gz") in msg and str(raw / name) in msg
    assert "mnist_root" in msg and "download: true" in msg and "vision" in msg
    # the DataModule says the same before anything else happens
    with pytest.raises(FileNotFoundError, match="t10k-labels-idx1-ubyte"):
        tiny_dm(tmp_path).prepare_data()
    # one file missing: only that one is named
    write_tiny_mnist(tmp_path)
    (raw / "t10k-labels-idx1-ubyte.gz").unlink()
    with pytest.raises(FileNotFoundError) as e:
        check_mnist_files(tmp_path)
    assert "t10k-labels" in str(e.value) and "train-images" not in str(e.value)
    with pytest.raises(FileNotFoundError, match=str(raw / "t10k-labels-idx1-ubyte")):
        tiny_dm(tmp_path).load_split("test")


def test_download_needs_torchvision(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "torchvision", None)  # import torchvision -> ImportError
    with pytest.raises(ImportError, match=r"vision.*extra"):
        tiny_dm(tmp_path, download=True).prepare_data()


def test_download_goes_through_torchvision(tmp_path, monkeypatch):
    calls = []

    class FakeMNIST:  # torchvision.datasets.MNIST's download writes <root>/MNIST/raw/*
        def __init__(self, root, train, download):
            calls.append((root, train, download))
            if not (Path(root) / "MNIST" / "raw" / "train-images-idx3-ubyte.gz").exists():
                write_tiny_mnist(Path(root))

    tv = types.ModuleType("torchvision")
    tv.datasets = types.ModuleType("torchvision.datasets")
    tv.datasets.MNIST = FakeMNIST
    monkeypatch.setitem(sys.modules, "torchvision", tv)
    monkeypatch.setitem(sys.modules, "torchvision.datasets", tv.datasets)
    root = tmp_path / "dl"
    dm = tiny_dm(root, download=True)
    dm.prepare_data()
    assert sorted(calls) == [(str(root), False, True), (str(root), True, True)]
    dm.setup()
    assert len(dm.datasets["train"]) == 40
    calls.clear()
    tiny_dm(root, download=True).prepare_data()  # files present: no second download
    assert calls == []


# ---------------------------------------------------------------------------------- motion
def check_motion(tr, lim: float, step: float) -> tuple[int, int]:
    """Assert the bouncing rule frame by frame; return (bounces, free moves) seen."""
    p, v = tr["positions"], tr["velocities"]
    assert (p >= 0).all() and (p <= lim).all()
    np.testing.assert_array_equal(tr["top_left"], np.floor(p).astype(np.int64))
    # constant speed per axis and in total
    np.testing.assert_allclose(np.abs(v), np.broadcast_to(np.abs(v[0]), v.shape), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.hypot(v[..., 0], v[..., 1]), step, rtol=1e-12)
    bounces = free = 0
    for t in range(1, len(p)):
        for d in range(p.shape[1]):
            for a in range(2):
                q = p[t - 1, d, a] + v[t - 1, d, a]
                if 0 < q < lim:
                    assert p[t, d, a] == q and v[t, d, a] == v[t - 1, d, a]
                    free += 1
                else:  # the move would reach or leave the range: clamp to the border, flip the velocity
                    assert p[t, d, a] == (0.0 if q <= 0 else lim)
                    assert v[t, d, a] == -v[t - 1, d, a]
                    assert (v[t, d, a] >= 0) == (q <= 0)  # it now points back inside
                    bounces += 1
    return bounces, free


@pytest.mark.parametrize("image_size,digit_size,step", [(64, 28, 3.6), (24, 8, 7.5)])
def test_digits_stay_on_canvas_and_bounce(image_size, digit_size, step):
    bounces = free = 0
    for i in range(150):
        tr = trajectory(3, "train", i, 1000, 20, image_size, digit_size, 2, step)
        assert tr["positions"].shape == (20, 2, 2) and tr["digit_indices"].shape == (2,)
        assert ((tr["digit_indices"] >= 0) & (tr["digit_indices"] < 1000)).all()
        b, f = check_motion(tr, image_size - digit_size, step)
        bounces, free = bounces + b, free + f
    assert bounces > 20 and free > 1000  # both branches of the rule were exercised


def test_starts_and_directions_are_uniform():
    lim = 36.0
    starts, angles, digits = [], [], []
    for i in range(1500):
        tr = trajectory(0, "train", i, 50, 2, 64, 28, 2, 3.6)
        starts.append(tr["positions"][0].ravel() / lim)
        v = tr["velocities"][0]
        angles.append(np.mod(np.arctan2(v[:, 0], v[:, 1]), 2 * np.pi) / (2 * np.pi))
        digits.append(tr["digit_indices"])
    for sample in (np.concatenate(starts), np.concatenate(angles)):
        assert stats.kstest(sample, "uniform").pvalue > 1e-3
    counts = np.bincount(np.concatenate(digits), minlength=50)
    assert stats.chisquare(counts).pvalue > 1e-3


def test_trajectory_is_a_pure_function_of_seed_split_index():
    a = trajectory(5, "train", 123, 60000)
    b = trajectory(5, "train", 123, 60000)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    for other in (
        trajectory(5, "train", 124, 60000),
        trajectory(5, "test", 123, 60000),
        trajectory(6, "train", 123, 60000),
    ):
        assert not np.array_equal(a["positions"], other["positions"])


# ---------------------------------------------------------------------------------- rendering
def test_frames_are_max_composition_at_the_positions(tiny):
    root, arrays = tiny
    digits = arrays["train"][0]
    ds = MovingMNISTDataset(digits, 25, seed=1, split="train", seq_len=20, image_size=24, n_digits=3, step=3.0)
    overlaps = 0
    for j in range(25):
        tr = ds.trajectory(j)
        y = ds[j]["y"]
        assert y.shape == (20, 1, 24, 24) and y.dtype == torch.float32
        expected = naive_frames(digits, tr["digit_indices"], tr["top_left"], 24)
        np.testing.assert_allclose(y[:, 0].numpy(), expected, rtol=0, atol=1e-7)
        tl = tr["top_left"]
        overlaps += int((np.abs(tl[:, :, None, :] - tl[:, None, :, :]).max(-1) < 8).sum() - 20 * 3)
    assert overlaps > 0  # some digits overlapped, so the max composition was exercised


def test_pixel_range(tiny):
    root, _ = tiny
    dm = tiny_dm(root)
    dm.setup()
    ys = torch.stack([dm.datasets[s][i]["y"] for s in ("train", "test") for i in range(10)])
    assert ys.dtype == torch.float32 and ys.min() >= 0 and ys.max() <= 1
    assert ys.max() == 1  # every tiny digit has a 255 pixel
    # pixel values are k / 255
    np.testing.assert_allclose(ys.numpy() * 255, np.round(ys.numpy() * 255), atol=1e-4)


# ---------------------------------------------------------------------------------- determinism
def test_items_are_deterministic_across_instances_and_loaders(tiny):
    root, _ = tiny
    dm1, dm2 = tiny_dm(root), tiny_dm(root)
    dm1.setup()
    dm2.setup()
    train1, train2 = dm1.datasets["train"], dm2.datasets["train"]
    for j in (0, 7, 39):
        assert torch.equal(train1[j]["y"], train1[j]["y"])
        assert torch.equal(train1[j]["y"], train2[j]["y"])
        assert int(train1[j]["index"]) == j
    for j, k in ((0, 1), (5, 30), (2, 39)):
        assert not torch.equal(train1[j]["y"], train1[k]["y"])
    # train and test differ (other digits and another seed stream)
    assert not torch.equal(train1[3]["y"], dm1.datasets["test"][3]["y"])
    assert not np.array_equal(train1.trajectory(3)["positions"], dm1.datasets["test"].trajectory(3)["positions"])
    # another seed -> other trajectories
    dm3 = tiny_dm(root, seed=1)
    dm3.setup()
    assert not torch.equal(train1[3]["y"], dm3.datasets["train"][3]["y"])
    # a DataLoader (sequential, workers=0 and workers=2) serves the same items
    for workers in (0, 2):
        dm = tiny_dm(root, num_workers=workers, eval_batch_size=4)
        dm.setup()
        batches = list(dm.test_dataloader())
        idx = torch.cat([b["index"] for b in batches])
        assert idx.tolist() == list(range(10))
        y = torch.cat([b["y"] for b in batches])
        for i in range(10):
            assert torch.equal(y[i], dm2.datasets["test"][i]["y"])


def test_dataset_pickles_and_subsets_share_digits(tiny):
    root, _ = tiny
    dm = tiny_dm(root)
    dm.setup()
    ds = dm.datasets["train"]
    clone = pickle.loads(pickle.dumps(ds))
    assert torch.equal(clone[11]["y"], ds[11]["y"])
    sub = dm.subset(ds, np.array([4, 2]))
    assert sub.digits.data_ptr() == ds.digits.data_ptr()
    subsub = dm.subset(sub, np.array([1]))
    assert len(subsub) == 1 and int(subsub[0]["index"]) == 2 and torch.equal(subsub[0]["y"], ds[2]["y"])
    # a batch fetched at once (what the DataLoader uses) equals the items fetched one by one
    batch = sub.__getitems__([1, 0, 1])
    assert batch["index"].tolist() == [2, 4, 2]
    assert batch["y"].shape == (3, 20, 1, 24, 24) and batch["y"].dtype == torch.float32
    for b, j in enumerate([2, 4, 2]):
        assert torch.equal(batch["y"][b], ds[j]["y"])


# ---------------------------------------------------------------------------------- DataModule
def test_normalize_true_is_refused():
    with pytest.raises(ValueError, match="normalize must stay false"):
        MovingMNISTDataModule(normalize=True)


@pytest.mark.parametrize(
    "kw,match",
    [
        (dict(digit_size=30, image_size=24), "digit_size"),
        (dict(n_train=0), "n_train"),
        (dict(step=-1.0), "step"),
        (dict(step=float("nan")), "step"),
        (dict(seed=-2), "seed"),
    ],
)
def test_bad_arguments(kw, match):
    with pytest.raises(ValueError, match=match):
        MovingMNISTDataModule(**kw)


def test_digit_size_is_checked_against_the_files(tiny):
    root, _ = tiny
    with pytest.raises(ValueError, match="set digit_size: 8"):
        tiny_dm(root, digit_size=10).setup()


def test_datamodule_end_to_end(tiny):
    root, arrays = tiny
    dm = tiny_dm(root)
    assert dm.num_train_trajectories == 40
    dm.prepare_data()
    dm.setup()
    assert dm.seq_len == 20 and dm.obs_shape == (1, 24, 24)
    assert len(dm.datasets["train"]) == 40 and len(dm.datasets["test"]) == 10
    batch = next(iter(dm.train_dataloader()))
    assert set(batch) == {"index", "y"}
    assert batch["index"].dtype == torch.long and batch["index"].shape == (8,)
    assert batch["y"].dtype == torch.float32 and batch["y"].shape == (8, 20, 1, 24, 24)
    for b in range(8):  # the batch rows are the trajectories their index names
        assert torch.equal(batch["y"][b], dm.datasets["train"][int(batch["index"][b])]["y"])
    # validation: evenly spaced training trajectories, keeping their indices
    (val_batch,) = list(dm.val_dataloader())
    expected = np.unique(np.linspace(0, 39, 5).round().astype(int))
    assert val_batch["index"].tolist() == expected.tolist()
    for b, j in enumerate(expected):
        assert torch.equal(val_batch["y"][b], dm.datasets["train"][int(j)]["y"])
    # test frames use MNIST test digits: trajectory 0 rendered naively from the test arrays
    tr = dm.trajectory("test", 0)
    expected0 = naive_frames(arrays["test"][0], tr["digit_indices"], tr["top_left"], 24)
    np.testing.assert_allclose(dm.datasets["test"][0]["y"][:, 0].numpy(), expected0, atol=1e-7)
    # checkpoint state and statistics
    state = dm.state_dict()
    assert state["name"] == "moving_mnist" and state["generator_params"]["n_train"] == 40
    mean, std = dm.compute_statistics(dm.datasets["train"])
    ys = torch.stack([dm.datasets["train"][i]["y"] for i in range(40)]).double()
    assert abs(float(mean) - float(ys.mean())) < 1e-6 and abs(float(std) - float(ys.std(unbiased=False))) < 1e-6


# ---------------------------------------------------------------------------------- real digits
@needs_real_mnist
def test_real_mnist_files():
    images, labels = load_mnist(SHARED_DATA, "train")
    assert images.shape == (60000, 28, 28) and images.dtype == np.uint8 and labels.shape == (60000,)
    # the published class counts of the MNIST training set
    assert np.bincount(labels).tolist() == [5923, 6742, 5958, 6131, 5842, 5421, 5918, 6265, 5851, 5949]
    # the test images, read independently: 16-byte header, then raw bytes
    with gzip.open(SHARED_DATA / "MNIST" / "raw" / "t10k-images-idx3-ubyte.gz", "rb") as f:
        raw = f.read()
    expected = np.frombuffer(raw, np.uint8, offset=16).reshape(10000, 28, 28)
    np.testing.assert_array_equal(load_mnist_images(SHARED_DATA, "test"), expected)


@needs_real_mnist
def test_real_digits_smoke():
    dm = MovingMNISTDataModule(mnist_root=str(SHARED_DATA), n_train=1000, n_test=100, batch_size=4)
    dm.prepare_data()
    dm.setup()
    assert dm.obs_shape == (1, 64, 64) and dm.seq_len == 20 and dm.datasets["train"].digit_size == 28
    batch = next(iter(dm.train_dataloader()))
    assert batch["y"].shape == (4, 20, 1, 64, 64) and batch["y"].min() >= 0 and batch["y"].max() <= 1
    test = dm.datasets["test"]
    with gzip.open(SHARED_DATA / "MNIST" / "raw" / "t10k-images-idx3-ubyte.gz", "rb") as f:
        digits = np.frombuffer(f.read(), np.uint8, offset=16).reshape(10000, 28, 28)
    tr = test.trajectory(7)
    check_motion(tr, 36.0, 3.6)
    np.testing.assert_allclose(
        test[7]["y"][:, 0].numpy(), naive_frames(digits, tr["digit_indices"], tr["top_left"], 64), atol=1e-7
    )
    # two digits of ~100-200 lit pixels each: a frame lights a few hundred pixels
    lit = (test[7]["y"] > 0).sum(dim=(1, 2, 3))
    assert ((lit > 50) & (lit < 2 * 28 * 28)).all()
    # MNIST's mean pixel is 0.1307 on 28x28: two digits on 64x64 give about 2 * 0.1307 * 784 / 4096 = 0.050
    assert math.isclose(float(dm.compute_statistics(dm.datasets["train"], 32)[0]), 0.05, abs_tol=0.03)
