"""Arrays on disk: ``.npy`` / ``.npz`` headers read without loading, checks, memory-mapped loading.

Used by :mod:`datamodules.files` (a user's recorded trajectories) and by
:func:`datamodules.predict.read_predict` (sequences to forecast); it imports nothing of
either, so neither imports the other to read an array. A file holds ``N`` trajectories ``[N, T, ...]`` or, where
``one_recording`` is allowed (training files), a single recording ``[T]`` / ``[T, D]``, served as ``[1, T, D]``.
"""

from __future__ import annotations

import struct
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

LAYOUTS = "[N, T, D] vectors, [N, T, H, W] grey images or [N, T, C, H, W] images"
RECORDING_LAYOUTS = "[T] or [T, D] one recording, " + LAYOUTS


@dataclass(frozen=True)
class ArrayHeader:
    """Where one array lives and what its header says (no data read)."""

    path: Path
    key: str | None  # member of an .npz (None for .npy)
    shape: tuple[int, ...]
    dtype: np.dtype
    fortran_order: bool
    data_offset: int | None = None  # byte offset of the data in an uncompressed .npz (memory-mappable)

    @property
    def label(self) -> str:
        return f"{self.path}" + (f" (array '{self.key}')" if self.key is not None else "")


def _read_npy_header(fp, where: str) -> tuple[tuple[int, ...], bool, np.dtype]:
    try:
        version = np.lib.format.read_magic(fp)
    except ValueError as err:
        raise ValueError(
            f"{where} is not a NumPy .npy array ({err}); write arrays with numpy.save / numpy.savez"
        ) from err
    if version == (1, 0):
        return np.lib.format.read_array_header_1_0(fp)
    return np.lib.format.read_array_header_2_0(fp)


def read_beside(head: ArrayHeader, key: str, what: str, npy_message: str) -> ArrayHeader:
    """The header of the member ``key`` of the ``.npz`` file ``head`` was read from (an array stored beside the
    measurements: inputs, noiseless targets). A ``.npy`` file holds one array only: ValueError ``npy_message``, its
    ``{path}`` filled in."""
    if head.key is None:
        raise ValueError(npy_message.replace("{path}", str(head.path)))
    return read_header(head.path, key, what)


def read_header(path: str | Path, key: str, what: str) -> ArrayHeader:
    """Read the header of a ``.npy`` file or of the member ``key`` of an ``.npz`` file.

    ``what`` names the argument the path came from, for error messages.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(
            f"{what}: {path} does not exist (or is not a file); expected a .npy or .npz file holding "
            f"trajectories as {LAYOUTS}"
        )
    suffix = path.suffix.lower()
    if suffix == ".npy":
        with open(path, "rb") as fp:
            shape, fortran, dtype = _read_npy_header(fp, str(path))
        return ArrayHeader(path, None, tuple(shape), dtype, fortran)
    if suffix != ".npz":
        raise ValueError(
            f"{what}: {path} is neither .npy nor .npz; save your trajectories with numpy.save or numpy.savez"
        )
    if not zipfile.is_zipfile(path):
        raise ValueError(f"{what}: {path} is not a valid .npz (zip) archive; write it with numpy.savez")
    with zipfile.ZipFile(path) as zf:
        member = f"{key}.npy"
        names = [n[:-4] for n in zf.namelist() if n.endswith(".npy")]
        if member not in zf.namelist():
            raise ValueError(
                f"{what}: {path} holds no array '{key}' (it holds {names}); set the key argument to one of them"
            )
        info = zf.getinfo(member)
        with zf.open(member) as fp:
            shape, fortran, dtype = _read_npy_header(fp, f"{path}['{key}']")
            header_len = fp.tell()
    offset = None
    if info.compress_type == zipfile.ZIP_STORED:
        with open(path, "rb") as fh:  # local file header: 30 bytes, then name and extra field
            fh.seek(info.header_offset)
            local = fh.read(30)
        if local[:4] == b"PK\x03\x04":
            name_len, extra_len = struct.unpack("<HH", local[26:30])
            offset = info.header_offset + 30 + name_len + extra_len + header_len
    return ArrayHeader(path, key, tuple(shape), dtype, fortran, offset)


def open_array(h: ArrayHeader) -> np.ndarray:
    """The array of a header: memory-mapped where possible, else read into memory."""
    if h.key is None:
        return np.load(h.path, mmap_mode="r")
    if h.data_offset is not None and not h.dtype.hasobject:
        return np.memmap(
            h.path, dtype=h.dtype, mode="r", offset=h.data_offset, shape=h.shape, order="F" if h.fortran_order else "C"
        )
    with np.load(h.path) as npz:
        return npz[h.key]


def check_header(h: ArrayHeader, what: str, one_recording: bool = False) -> None:
    """Refuse arrays that cannot be trajectories: object arrays, non-numeric dtypes, other ranks, empty ones.
    ``one_recording``: a single recording ``[T]`` or ``[T, D]`` is accepted too."""
    layouts = RECORDING_LAYOUTS if one_recording else LAYOUTS
    if h.dtype.hasobject:
        raise ValueError(
            f"{what}: {h.label} is an object array (ragged trajectories or a pickled list): save each set of "
            f"recordings of one length as one numeric array ({layouts}), each in its own file, and give the files "
            "as a list"
        )
    if h.dtype.kind not in "biuf":
        raise ValueError(f"{what}: {h.label} has dtype {h.dtype}; expected a real numeric (float, int or uint8) array")
    if len(h.shape) not in ((1, 2, 3, 4, 5) if one_recording else (3, 4, 5)):
        hint = (
            " (scalar measurements [N, T]: add a trailing axis, y[..., None])"
            if len(h.shape) == 2 and not one_recording
            else ""
        )
        raise ValueError(
            f"{what}: {h.label} has shape {h.shape} (rank {len(h.shape)}); accepted layouts: {layouts}{hint}"
        )
    if 0 in h.shape:
        raise ValueError(
            f"{what}: {h.label} is empty (shape {h.shape}, layout [N, T, ...]): it needs at least one trajectory "
            "of at least one sample"
        )


def served_shape(shape: tuple[int, ...]) -> tuple[int, ...]:
    """The served layout ``[N, T, *obs]`` of an array: one recording ``[T]`` / ``[T, D]`` as ``[1, T, 1]`` /
    ``[1, T, D]``, grey images ``[N, T, H, W]`` channel-first as ``[N, T, 1, H, W]``."""
    shape = tuple(shape)
    if len(shape) == 1:
        return (1, shape[0], 1)
    if len(shape) == 2:
        return (1, *shape)
    return (shape[0], shape[1], 1, *shape[2:]) if len(shape) == 4 else shape


def concat_shape(heads: list[ArrayHeader], what: str) -> tuple[int, ...]:
    """The served shape ``[N, T, *obs]`` of files concatenated along ``N`` (their ``[T, *obs]`` must agree)."""
    first = served_shape(heads[0].shape)
    for h in heads[1:]:
        other = served_shape(h.shape)
        if other[1:] != first[1:]:
            raise ValueError(
                f"{what}: {h.label} holds trajectories of shape {other[1:]} but {heads[0].label} holds "
                f"{first[1:]} ([T, *obs]); files of one split are concatenated along N and must agree"
            )
    return (sum(h.shape[0] for h in heads), *first[1:])


def stream_headers(
    heads: list[ArrayHeader], key: str, first: str, what: str, one_recording: bool = False
) -> list[ArrayHeader]:
    """A further sensor's array ``key`` in the ``.npz`` files of ``heads`` (the first sensor's, named ``first``),
    checked: one per file, numeric, with the first sensor's ``N`` and ``T`` (a sample slot per step, NaN where the
    sensor has none). ``one_recording``: as :func:`check_header`'s."""
    streams = []
    for h in heads:
        if h.key is None:
            raise ValueError(f"{what}: several sensors are read from .npz files holding them all, not {h.path}")
        s = read_header(h.path, key, what)
        check_header(s, what, one_recording)
        if served_shape(s.shape)[:2] != served_shape(h.shape)[:2]:
            raise ValueError(
                f"{what}: {s.label} holds {served_shape(s.shape)[:2]} (N, T) but '{first}' holds "
                f"{served_shape(h.shape)[:2]}: every sensor of a trajectory has a sample slot per step (NaN where it "
                "has none)"
            )
        streams.append(s)
    return streams


def harmonise(arrays: list[np.ndarray]) -> list[np.ndarray]:
    """Arrays of one kind of measurement in one dtype: as they are where they share one, else float32 with the uint8
    ones mapped to [0, 1] (images stored as 0..255, as they are served)."""
    if len({a.dtype for a in arrays}) <= 1:
        return arrays
    return [a.astype(np.float32) / 255.0 if a.dtype == np.uint8 else a.astype(np.float32) for a in arrays]


def stored_dtype(dtype: np.dtype) -> np.dtype:
    """The dtype an array is held in once copied: uint8 stays (images, served in [0, 1]), anything else float32 (as
    it is served)."""
    return np.dtype(np.uint8) if np.dtype(dtype) == np.uint8 else np.dtype(np.float32)


def open_files(heads: list[ArrayHeader], missing: bool = False) -> list[np.ndarray]:
    """The arrays of headers, each checked finite (with ``missing``: NaN allowed, the samples a sensor did not take;
    inf refused), in the served layout ``[N, T, *obs]`` (memory-mapped where the file allows it), in one dtype
    (:func:`harmonise`)."""
    arrays = []
    for h in heads:
        a = open_array(h)
        check_finite(h.label, a, missing=missing)
        shape = served_shape(a.shape)
        arrays.append(a.reshape(shape) if a.shape != shape else a)
    return harmonise(arrays)


def load_files(heads: list[ArrayHeader], missing: bool = False) -> np.ndarray:
    """The arrays of :func:`open_files` concatenated along ``N`` (one file stays mapped; several are concatenated,
    float32 where they are floats)."""
    arrays = open_files(heads, missing)
    if len(arrays) == 1:
        return arrays[0]
    if arrays[0].dtype.kind == "f" and arrays[0].dtype != np.float32:
        arrays = [a.astype(np.float32) for a in arrays]
    return np.concatenate(arrays)


def check_finite(name: str, a: np.ndarray, chunk: int = 1 << 22, missing: bool = False) -> None:
    """Raise if a float array holds NaN or inf (checked in chunks: arrays may be memory-mapped); with ``missing``,
    NaN (a missing sample) is allowed and only inf refused."""
    if not np.issubdtype(a.dtype, np.floating):
        return
    flat = a.reshape(-1)
    for start in range(0, flat.size, chunk):
        block = np.asarray(flat[start : start + chunk])
        bad_values = np.isinf(block) if missing else ~np.isfinite(block)
        if bad_values.any():
            bad = start + int(np.flatnonzero(bad_values)[0])
            where = np.unravel_index(bad, a.shape)
            raise ValueError(
                f"{name} holds a non-finite value ({block[bad - start]}) at index {tuple(int(w) for w in where)} "
                "(trajectory, time, ...): remove or interpolate missing samples before training"
            )
