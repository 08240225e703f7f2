"""Moving MNIST (Srivastava et al. 2015), generated deterministically on the fly from real digits.

Each trajectory shows ``n_digits`` MNIST digits of ``digit_size`` pixels bouncing in an
``image_size`` canvas, composed with ``max``. A digit's top-left corner starts uniformly in
``[0, L]^2`` with ``L = image_size - digit_size``, moves in a uniformly drawn direction at a
constant ``step`` pixels per frame, and when a move would take a coordinate to or past ``0`` or
``L`` the coordinate is set to that border and its velocity component flips (the rule of the
original generator, whose step is 0.1 of ``L``: 3.6 px). Frames are pasted at the integer part of
the corner's position; frame 0 shows the start position (the original moves once before its first
frame, which only shifts the uniform start).

Trajectory ``i`` of a split is a pure function of ``(seed, split, i)``: its digit indices, start
positions and directions come from a per-item RNG seeded with ``[seed, split code, i]``, and its
frames are rendered when the item is loaded. A 100,000-trajectory training set therefore costs
only the MNIST digits it draws from (47 MB of uint8 for MNIST train, shared with DataLoader
workers), never ``N x T x H x W`` floats. Training trajectories use MNIST train digits, test
trajectories MNIST test digits.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset, get_worker_info

from datamodules.base import TrajectoryDataModule
from datamodules.mnist_idx import check_mnist_files, download_mnist, load_mnist, missing_mnist_files

#: Split -> seed-stream code: the test trajectories come from another stream than the training ones.
SPLIT_CODES = {"train": 0, "test": 1}
_INV_255 = np.float32(1.0 / 255.0)


def trajectory(
    seed: int,
    split: str,
    index: int,
    n_images: int,
    seq_len: int = 20,
    image_size: int = 64,
    digit_size: int = 28,
    n_digits: int = 2,
    step: float = 3.6,
) -> dict[str, np.ndarray]:
    """The parameters and motion of trajectory ``index`` of ``split`` (a pure function of its arguments).

    Args:
        seed: the data set's seed (>= 0).
        split: "train" or "test" (selects the seed stream).
        index: the trajectory's index in its split (>= 0).
        n_images: number of MNIST images the digits are drawn from.

    Returns:
        ``digit_indices`` int64 ``[n_digits]`` (into the split's MNIST images);
        ``positions`` float64 ``[T, n_digits, 2]``: top-left corner (row, column), in ``[0, L]``;
        ``velocities`` float64 ``[T, n_digits, 2]``: the move from frame ``t`` to ``t + 1``; its
        components keep their magnitude and flip sign at the borders;
        ``top_left`` int64 ``[T, n_digits, 2]``: where each digit is pasted (floor of ``positions``).
    """
    if split not in SPLIT_CODES:
        raise ValueError(f"split must be one of {sorted(SPLIT_CODES)}, got {split!r}")
    if seed < 0 or index < 0:
        raise ValueError(f"seed and index must be >= 0, got seed={seed}, index={index}")
    rng = np.random.default_rng([int(seed), SPLIT_CODES[split], int(index)])
    digit_indices = rng.integers(0, n_images, size=n_digits)
    lim = float(image_size - digit_size)
    p = rng.random((n_digits, 2)) * lim
    theta = rng.random(n_digits) * (2.0 * math.pi)
    v = step * np.stack([np.sin(theta), np.cos(theta)], axis=-1)
    # The motion in plain floats (a handful of coordinates: numpy calls would cost more than the work).
    pos, vel = p.tolist(), v.tolist()
    track_p, track_v = [], []
    for t in range(seq_len):
        if t > 0:
            for pd, vd in zip(pos, vel):
                for a in (0, 1):
                    q = pd[a] + vd[a]
                    if q <= 0.0:
                        pd[a], vd[a] = 0.0, abs(vd[a])
                    elif q >= lim:
                        pd[a], vd[a] = lim, -abs(vd[a])
                    else:
                        pd[a] = q
        track_p.append([pd[:] for pd in pos])
        track_v.append([vd[:] for vd in vel])
    positions = np.array(track_p, dtype=np.float64).reshape(seq_len, n_digits, 2)
    velocities = np.array(track_v, dtype=np.float64).reshape(seq_len, n_digits, 2)
    return {
        "digit_indices": digit_indices.astype(np.int64),
        "positions": positions,
        "velocities": velocities,
        "top_left": np.floor(positions).astype(np.int64),
    }


def render(
    digits: np.ndarray, digit_indices: np.ndarray, top_left: np.ndarray, image_size: int, out: np.ndarray | None = None
) -> np.ndarray:
    """Paste ``digits[digit_indices[d]]`` at ``top_left[t, d]`` into blank frames, composed with max.

    Returns uint8 ``[T, image_size, image_size]`` (written into ``out`` if given: it must be zeros).
    """
    s = digits.shape[1]
    n_frames = top_left.shape[0]
    canvas = np.zeros((n_frames, image_size, image_size), dtype=np.uint8) if out is None else out
    corners = top_left.tolist()
    for d, k in enumerate(digit_indices.tolist()):
        img = digits[k]
        for t in range(n_frames):
            r, c = corners[t][d]
            window = canvas[t, r : r + s, c : c + s]
            np.maximum(window, img, out=window)
    return canvas


def _float_batch(shape: tuple[int, ...]) -> torch.Tensor:
    """An empty float32 tensor; inside a DataLoader worker it lives in shared memory, as
    ``default_collate`` does, so that sending the batch to the main process copies nothing."""
    if get_worker_info() is None:
        return torch.empty(shape, dtype=torch.float32)
    elem = torch.empty(0, dtype=torch.float32)
    try:
        storage = elem._typed_storage()._new_shared(math.prod(shape), device=elem.device)
        return elem.new(storage).resize_(shape)
    except (AttributeError, RuntimeError):  # private API moved: fall back to one extra copy
        return torch.empty(shape, dtype=torch.float32).share_memory_()


class MovingMNISTDataset(Dataset):
    """Moving MNIST trajectories rendered on access: items ``{"index", "y": float32 [T, 1, H, W]}``.

    The digits are held once as a uint8 tensor; DataLoader workers share it (inherited on fork,
    passed through shared memory otherwise), and a subset shares it with its parent.

    Args:
        digits: uint8 ``[N, s, s]`` MNIST images of the split.
        n: number of trajectories of the split.
        seed, split, seq_len, image_size, n_digits, step: see :func:`trajectory`.
        indices: restrict to these trajectory indices, which the items keep (default: all ``n``).
    """

    def __init__(
        self,
        digits: np.ndarray | torch.Tensor,
        n: int,
        seed: int,
        split: str,
        seq_len: int = 20,
        image_size: int = 64,
        n_digits: int = 2,
        step: float = 3.6,
        indices: Sequence[int] | np.ndarray | None = None,
    ):
        digits = torch.as_tensor(digits)
        if digits.dtype != torch.uint8 or digits.ndim != 3 or digits.shape[1] != digits.shape[2] or len(digits) == 0:
            raise ValueError(
                f"digits must be a non-empty uint8 array [N, s, s] of square images, got {digits.dtype} "
                f"{tuple(digits.shape)}"
            )
        if digits.shape[1] > image_size:
            raise ValueError(f"digits of {digits.shape[1]} px do not fit in a {image_size} px canvas: raise image_size")
        if split not in SPLIT_CODES:
            raise ValueError(f"split must be one of {sorted(SPLIT_CODES)}, got {split!r}")
        self.digits = digits
        self.n, self.seed, self.split = int(n), int(seed), split
        self.seq_len_, self.image_size, self.n_digits, self.step = (
            int(seq_len),
            int(image_size),
            int(n_digits),
            float(step),
        )
        self.indices = None if indices is None else np.asarray(indices, dtype=np.int64)
        if self.indices is not None and len(self.indices) and (self.indices.min() < 0 or self.indices.max() >= n):
            raise ValueError(f"subset indices must lie in [0, {n}), got {self.indices.min()}..{self.indices.max()}")

    def __len__(self) -> int:
        return self.n if self.indices is None else len(self.indices)

    @property
    def seq_len(self) -> int:
        return self.seq_len_

    @property
    def obs_shape(self) -> tuple[int, ...]:
        return (1, self.image_size, self.image_size)

    @property
    def digit_size(self) -> int:
        return int(self.digits.shape[1])

    def trajectory(self, index: int) -> dict[str, np.ndarray]:
        """Digit indices and motion of trajectory ``index`` (its index in the split, as in the items)."""
        if not 0 <= index < self.n:
            raise IndexError(f"trajectory index {index} out of range [0, {self.n})")
        return trajectory(
            self.seed,
            self.split,
            index,
            len(self.digits),
            self.seq_len_,
            self.image_size,
            self.digit_size,
            self.n_digits,
            self.step,
        )

    def frames(self, index: int) -> np.ndarray:
        """uint8 frames ``[T, H, W]`` of trajectory ``index``."""
        tr = self.trajectory(index)
        return render(self.digits.numpy(), tr["digit_indices"], tr["top_left"], self.image_size)

    def _trajectory_index(self, i: int) -> int:
        if not -len(self) <= i < len(self):
            raise IndexError(f"item {i} out of range for a data set of {len(self)} trajectories")
        i = i % len(self)
        return i if self.indices is None else int(self.indices[i])

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        j = self._trajectory_index(i)
        # uint8 -> [0, 1] as normalizer.to_float does, in numpy: torch's threaded cast is slow on a busy machine
        y = torch.from_numpy(np.multiply(self.frames(j), _INV_255, dtype=np.float32)).unsqueeze(1)
        return {"index": torch.tensor(j, dtype=torch.long), "y": y}

    def __getitems__(self, items: list[int]) -> dict[str, torch.Tensor]:
        """A whole batch, already collated (the DataLoader calls this instead of ``__getitem__``).

        Each trajectory is rendered into one reused uint8 buffer and converted straight into its row
        of the batch tensor, which saves the per-item tensors and the copy of stacking them.
        """
        js = [self._trajectory_index(int(i)) for i in items]
        s = self.image_size
        y = _float_batch((len(js), self.seq_len_, 1, s, s))
        out = y.numpy()[:, :, 0]
        frames = np.empty((self.seq_len_, s, s), dtype=np.uint8)  # one small buffer, reused
        digits = self.digits.numpy()
        for b, j in enumerate(js):
            tr = self.trajectory(j)
            frames.fill(0)
            render(digits, tr["digit_indices"], tr["top_left"], s, out=frames)
            np.multiply(frames, _INV_255, out=out[b])
        return {"index": torch.tensor(js, dtype=torch.long), "y": y}

    def subset(self, positions: Sequence[int] | np.ndarray) -> MovingMNISTDataset:
        """Items at ``positions`` of this data set, keeping their trajectory indices (shares the digits)."""
        pos = np.asarray(positions, dtype=np.int64)
        base = np.arange(self.n) if self.indices is None else self.indices
        return MovingMNISTDataset(
            self.digits,
            self.n,
            self.seed,
            self.split,
            self.seq_len_,
            self.image_size,
            self.n_digits,
            self.step,
            base[pos],
        )


class MovingMNISTDataModule(TrajectoryDataModule):
    """Moving MNIST over real MNIST digits, deterministic and rendered on the fly.

    Args:
        mnist_root: folder holding ``MNIST/raw/{train,t10k}-{images-idx3,labels-idx1}-ubyte[.gz]``
            (torchvision's layout); downloads go there too.
        download: download missing MNIST files through torchvision (the `vision` extra).
        n_train: training trajectories (100,000 in the paper).
        n_test: test trajectories (10,000), drawn from MNIST test digits with another seed stream.
        seq_len: frames per trajectory (20: 10 to filter, 10 to predict).
        image_size: canvas side in pixels (64).
        digit_size: MNIST image side (28); checked against the files.
        n_digits: digits per trajectory (2).
        step: speed in pixels per frame (3.6, the original generator's 0.1 of ``image_size - digit_size``).
        data_dir: unused (nothing is cached: frames are rendered on access).
        batch_size: trajectories per training batch (50 in the paper).
        normalize: must stay false: frames are in [0, 1] for the BCE loss.
        Other arguments: see :class:`~datamodules.base.TrajectoryDataModule`.
    """

    name = "moving_mnist"
    split_params = {"train": ("n_train",), "test": ("n_test",)}

    def __init__(
        self,
        mnist_root: str = "data",
        download: bool = False,
        n_train: int = 100_000,
        n_test: int = 10_000,
        seq_len: int = 20,
        image_size: int = 64,
        digit_size: int = 28,
        n_digits: int = 2,
        step: float = 3.6,
        batch_size: int = 50,
        normalize: bool = False,
        seed: int = 0,
        **kwargs: Any,
    ):
        if normalize:
            raise ValueError(
                "moving_mnist: normalize must stay false: frames are pixel intensities in [0, 1], as the BCE "
                "loss needs; remove `normalize: true` from the data config"
            )
        for arg, value, low in (
            ("n_train", n_train, 1),
            ("n_test", n_test, 1),
            ("seq_len", seq_len, 1),
            ("image_size", image_size, 1),
            ("digit_size", digit_size, 1),
            ("n_digits", n_digits, 1),
            ("seed", seed, 0),
        ):
            if not isinstance(value, int) or value < low:
                raise ValueError(f"moving_mnist: {arg} must be an integer >= {low}, got {value!r}")
        if digit_size > image_size:
            raise ValueError(
                f"moving_mnist: digit_size ({digit_size}) exceeds image_size ({image_size}): digits must fit in "
                "the canvas; raise image_size"
            )
        if not (math.isfinite(step) and step >= 0):
            raise ValueError(f"moving_mnist: step (pixels per frame) must be finite and >= 0, got {step}")
        super().__init__(batch_size=batch_size, normalize=False, seed=seed, **kwargs)
        self.mnist_root = mnist_root
        self.download = download
        self.n_train, self.n_test = n_train, n_test
        self.seq_len_, self.image_size, self.digit_size = seq_len, image_size, digit_size
        self.n_digits, self.step = n_digits, float(step)

    @property
    def num_train_trajectories(self) -> int:
        return self.n_train

    def generator_params(self) -> dict[str, Any]:
        return {
            "digits": "MNIST",
            "n_train": self.n_train,
            "n_test": self.n_test,
            "seq_len": self.seq_len_,
            "image_size": self.image_size,
            "digit_size": self.digit_size,
            "n_digits": self.n_digits,
            "step": self.step,
            "seed": self.seed,
        }

    def generate(self, split: str) -> dict[str, np.ndarray]:
        raise NotImplementedError("moving_mnist renders trajectories on access; there are no arrays to generate")

    def prepare_split(self, split: str) -> None:
        """Check that the four MNIST files exist under ``mnist_root`` (download them if ``download``)."""
        if self.download and missing_mnist_files(self.mnist_root):
            download_mnist(self.mnist_root)
        check_mnist_files(self.mnist_root)

    def load_split(self, split: str) -> MovingMNISTDataset:
        """The split's trajectories over MNIST ``split`` digits (read and checked here)."""
        images, _ = load_mnist(self.mnist_root, split)
        if images.shape[1:] != (self.digit_size, self.digit_size):
            raise ValueError(
                f"moving_mnist: the MNIST {split} images under {self.mnist_root} are {images.shape[1]}x"
                f"{images.shape[2]} but digit_size is {self.digit_size}: set digit_size: {images.shape[1]}"
                + ("" if images.shape[1] == images.shape[2] else " (and use square images)")
            )
        n = self.n_train if split == "train" else self.n_test
        return MovingMNISTDataset(images, n, self.seed, split, self.seq_len_, self.image_size, self.n_digits, self.step)

    def subset(self, ds: Dataset, indices: np.ndarray) -> Dataset:
        """The items ``indices`` of ``ds``, keeping their trajectory index (the validation subset)."""
        if not isinstance(ds, MovingMNISTDataset):
            return super().subset(ds, indices)
        return ds.subset(indices)

    def compute_statistics(self, train: Dataset, max_trajectories: int = 256) -> tuple[torch.Tensor, torch.Tensor]:
        """Pixel mean and std over up to ``max_trajectories`` evenly spaced training trajectories.

        Not used for training (normalisation is off); useful for reporting.
        """
        if not isinstance(train, MovingMNISTDataset):
            return super().compute_statistics(train)
        idx = np.unique(np.linspace(0, len(train) - 1, min(max_trajectories, len(train))).round().astype(np.int64))
        s = s2 = 0.0
        count = 0
        for i in idx.tolist():
            y = train[i]["y"].double()
            s += float(y.sum())
            s2 += float((y**2).sum())
            count += y.numel()
        mean = s / count
        std = math.sqrt(max(s2 / count - mean**2, 0.0))
        return torch.tensor([mean], dtype=torch.float32), torch.tensor([std], dtype=torch.float32)

    def trajectory(self, split: str, index: int) -> dict[str, np.ndarray]:
        """Digit indices and motion of trajectory ``index`` of ``split`` (after :meth:`setup`)."""
        if split not in self.datasets:
            raise RuntimeError(f"moving_mnist: the {split} split is not set up; call setup() first")
        ds = self.datasets[split]
        assert isinstance(ds, MovingMNISTDataset)
        return ds.trajectory(index)
