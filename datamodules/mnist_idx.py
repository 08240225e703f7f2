"""Reading MNIST from the four standard IDX files (gzipped or not), without torchvision.

The files are looked up in torchvision's raw layout::

    <root>/MNIST/raw/train-images-idx3-ubyte[.gz]   train-labels-idx1-ubyte[.gz]
    <root>/MNIST/raw/t10k-images-idx3-ubyte[.gz]    t10k-labels-idx1-ubyte[.gz]

An IDX file is a big-endian header (two zero bytes, a type code, the number of dimensions, one
32-bit size per dimension) followed by the data in C order. torchvision is only used, imported
lazily, by :func:`download_mnist`; nothing else here needs it.
"""

from __future__ import annotations

import gzip
import struct
from pathlib import Path
from typing import BinaryIO

import numpy as np

#: IDX type code -> numpy dtype (multi-byte types are big-endian on disk).
IDX_DTYPES: dict[int, np.dtype] = {
    0x08: np.dtype(np.uint8),
    0x09: np.dtype(np.int8),
    0x0B: np.dtype(">i2"),
    0x0C: np.dtype(">i4"),
    0x0D: np.dtype(">f4"),
    0x0E: np.dtype(">f8"),
}

#: MNIST split -> file prefix.
MNIST_PREFIX = {"train": "train", "test": "t10k"}
#: Magic numbers of the MNIST files: images are uint8 with 3 dims, labels uint8 with 1 dim.
IMAGES_MAGIC = 0x00000803  # 2051
LABELS_MAGIC = 0x00000801  # 2049

HOW_TO_GET = (
    "set `mnist_root` to the folder that holds MNIST/raw/, put the four files "
    "{train,t10k}-{images-idx3,labels-idx1}-ubyte.gz there (e.g. from https://ossci-datasets.s3.amazonaws.com/mnist/), "
    "or install the `vision` extra (pip install 'ssm-ms[vision]') and set `download: true`"
)

_CHUNK = 1 << 20


class IDXFormatError(ValueError):
    """An IDX file whose header or size is not what it should be."""


def _open(path: Path) -> BinaryIO:
    return gzip.open(path, "rb") if path.suffix == ".gz" else open(path, "rb")  # type: ignore[return-value]


def _read_exact(f: BinaryIO, n: int, path: Path, what: str) -> bytes:
    data = f.read(n)
    if len(data) != n:
        raise IDXFormatError(
            f"{path}: the file ends inside its {what} ({len(data)} of {n} bytes): it is truncated or not an "
            f"IDX file; download it again"
        )
    return data


def read_idx_header(f: BinaryIO, path: Path) -> tuple[int, np.dtype, tuple[int, ...]]:
    """Read the header of an open IDX file: ``(magic, dtype, shape)``."""
    magic_bytes = _read_exact(f, 4, path, "magic number")
    magic = struct.unpack(">I", magic_bytes)[0]
    zero, code, ndim = struct.unpack(">HBB", magic_bytes)
    if zero != 0 or code not in IDX_DTYPES or ndim == 0:
        raise IDXFormatError(
            f"{path}: bad IDX magic number 0x{magic:08x} (expected 0x0000TTDD with a type code TT in "
            f"{[hex(c) for c in IDX_DTYPES]} and DD >= 1 dimensions; MNIST images have 0x{IMAGES_MAGIC:08x}, "
            f"labels 0x{LABELS_MAGIC:08x}): the file is not an (uncompressed) IDX file"
            + (" — is it gzipped without a .gz suffix?" if magic_bytes[:2] == b"\x1f\x8b" else "")
        )
    shape = struct.unpack(f">{ndim}I", _read_exact(f, 4 * ndim, path, "dimension sizes"))
    return magic, IDX_DTYPES[code], tuple(int(s) for s in shape)


def read_idx(path: str | Path) -> np.ndarray:
    """Read an IDX file (``.gz`` or uncompressed) into a native-endian numpy array.

    The data are read in chunks straight into the result, so a 47 MB file needs 47 MB.

    Raises:
        FileNotFoundError: the file does not exist.
        IDXFormatError: bad magic number, or the data are shorter or longer than the header says.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"IDX file {path} does not exist")
    try:
        with _open(path) as f:
            _, dtype, shape = read_idx_header(f, path)
            out = np.empty(shape, dtype=dtype)
            view = memoryview(out.reshape(-1).view(np.uint8))
            pos = 0
            while pos < len(view):
                n = f.readinto(view[pos : pos + _CHUNK])  # type: ignore[attr-defined]
                if not n:
                    raise IDXFormatError(
                        f"{path}: the header announces shape {shape} of {dtype.name} ({len(view)} bytes of data) "
                        f"but the file holds only {pos} bytes: it is truncated; download it again"
                    )
                pos += n
            if f.read(1):
                raise IDXFormatError(
                    f"{path}: the file holds more data than its header announces (shape {shape} of "
                    f"{dtype.name}): it is not a valid IDX file"
                )
    except (OSError, EOFError, gzip.BadGzipFile) as e:
        if isinstance(e, FileNotFoundError):
            raise
        raise IDXFormatError(f"{path}: cannot read it ({e}): the file is corrupt; download it again") from e
    return out if out.dtype.isnative else out.astype(out.dtype.newbyteorder("="))


# ---------------------------------------------------------------------------------- MNIST layout
def mnist_raw_dir(root: str | Path) -> Path:
    """The folder that holds the MNIST files: ``<root>/MNIST/raw`` (torchvision's layout)."""
    return Path(root) / "MNIST" / "raw"


def mnist_candidates(root: str | Path, split: str, kind: str) -> list[Path]:
    """Paths where one MNIST file may be, in the order they are tried (uncompressed first)."""
    if split not in MNIST_PREFIX:
        raise ValueError(f"MNIST split must be one of {sorted(MNIST_PREFIX)}, got {split!r}")
    if kind not in ("images", "labels"):
        raise ValueError(f"MNIST file kind must be 'images' or 'labels', got {kind!r}")
    stem = f"{MNIST_PREFIX[split]}-{'images-idx3' if kind == 'images' else 'labels-idx1'}-ubyte"
    d = mnist_raw_dir(root)
    return [d / stem, d / f"{stem}.gz"]


def missing_mnist_files(root: str | Path, splits: tuple[str, ...] = ("train", "test")) -> list[Path]:
    """The ``.gz`` names of the MNIST files of ``splits`` found under ``root`` in neither form."""
    missing = []
    for split in splits:
        for kind in ("images", "labels"):
            cands = mnist_candidates(root, split, kind)
            if not any(p.is_file() for p in cands):
                missing.append(cands[-1])
    return missing


def find_mnist_file(root: str | Path, split: str, kind: str) -> Path:
    """The path of one MNIST file, or a FileNotFoundError that says where it looked and what to do."""
    cands = mnist_candidates(root, split, kind)
    for p in cands:
        if p.is_file():
            return p
    raise FileNotFoundError(
        f"MNIST {split} {kind} not found: looked for {', '.join(str(p) for p in cands)} "
        f"(mnist_root={str(root)!r}, resolved to {Path(root).resolve()}). To fix: {HOW_TO_GET}"
    )


def check_mnist_files(root: str | Path, splits: tuple[str, ...] = ("train", "test")) -> None:
    """Raise a FileNotFoundError naming every missing MNIST file of ``splits`` and how to get them."""
    missing = missing_mnist_files(root, splits)
    if missing:
        raise FileNotFoundError(
            f"MNIST files missing under {mnist_raw_dir(root)} (mnist_root={str(root)!r}, resolved to "
            f"{Path(root).resolve()}): looked for "
            + "; ".join(f"{p} or {p.with_suffix('')}" for p in missing)
            + f". To fix: {HOW_TO_GET}"
        )


def _read_checked(path: Path, magic_expected: int, ndim: int) -> np.ndarray:
    with _open(path) as f:
        magic, _, _ = read_idx_header(f, path)
    if magic != magic_expected:
        raise IDXFormatError(
            f"{path}: magic number 0x{magic:08x}, but MNIST {'images' if ndim == 3 else 'labels'} have "
            f"0x{magic_expected:08x} (uint8, {ndim} dimension{'s' if ndim > 1 else ''}): wrong or swapped file"
        )
    return read_idx(path)


def load_mnist_images(root: str | Path, split: str) -> np.ndarray:
    """MNIST images of ``split`` ("train" or "test") as uint8 ``[N, H, W]`` (28 x 28 for MNIST)."""
    return _read_checked(find_mnist_file(root, split, "images"), IMAGES_MAGIC, 3)


def load_mnist_labels(root: str | Path, split: str) -> np.ndarray:
    """MNIST labels of ``split`` as uint8 ``[N]``, checked to lie in 0..9."""
    path = find_mnist_file(root, split, "labels")
    labels = _read_checked(path, LABELS_MAGIC, 1)
    if labels.size and labels.max() > 9:
        raise IDXFormatError(f"{path}: labels must lie in 0..9, found {int(labels.max())}: wrong file")
    return labels


def load_mnist(root: str | Path, split: str) -> tuple[np.ndarray, np.ndarray]:
    """``(images uint8 [N, H, W], labels uint8 [N])`` of an MNIST split, with their counts checked."""
    images = load_mnist_images(root, split)
    labels = load_mnist_labels(root, split)
    if len(images) != len(labels):
        raise IDXFormatError(
            f"MNIST {split} under {mnist_raw_dir(root)}: {len(images)} images but {len(labels)} labels: "
            "the files do not belong together; download them again"
        )
    return images, labels


def download_mnist(root: str | Path) -> None:
    """Download the four MNIST files into ``<root>/MNIST/raw`` through torchvision (imported here only)."""
    try:
        from torchvision.datasets import MNIST  # noqa: PLC0415 (optional dependency, imported lazily)
    except ImportError as e:
        raise ImportError(
            f"download: true needs torchvision, which is not installed ({e}). Install the `vision` extra "
            f"(pip install 'ssm-ms[vision]'), or put the four MNIST files under {mnist_raw_dir(root)} "
            "yourself and set download: false"
        ) from e
    Path(root).mkdir(parents=True, exist_ok=True)
    for train in (True, False):
        MNIST(root=str(root), train=train, download=True)
