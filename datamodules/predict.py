"""The sequences to forecast (``predict_path``): read and checked against what the model was trained on."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from datamodules.arrays import check_header, concat_shape, load_files, read_beside, read_header, stream_headers
from datamodules.dataset import TrajectoryDataset


def read_predict(
    paths: Sequence[str],
    *,
    predict_key: str,
    obs_shape: tuple[int, ...],
    predict_given: int | None,
    input_dim: int,
    input_key: str,
    sensor_layout: list[dict[str, Any]] | None = None,
) -> TrajectoryDataset:
    """The sequences of ``paths`` (``predict_path``; checked like a user's training files), whole, as ``[N, T,
    *obs]``. For data driven by inputs the files are ``.npz`` holding them beside the measurements (``input_key``,
    ``[N, T_u, m]``): those of the given samples, and, to forecast, those of the horizon (``T_u`` may exceed ``T``).
    Several sensors: ``.npz`` files holding one array per stream, named as the streams (``sensor_layout``;
    ``predict_key`` is not read), the streams after the first with NaN where they did not sample. Whatever differs
    from the training data (``obs_shape``, ``input_dim``) or ``predict_given`` beyond ``T``: one message."""
    layout = {s["name"]: tuple(s["shape"]) for s in sensor_layout or []}
    keys = list(layout) or [predict_key]
    heads = [read_header(path, keys[0], "predict_path") for path in paths]
    for h in heads:
        check_header(h, "predict_path")
        if layout and h.key is None:
            raise ValueError(
                f"predict_path: a model of several sensors reads .npz files holding one array per sensor, named "
                f"{keys} (numpy.savez(path, {', '.join(f'{k}=...' for k in keys)})), not {h.path}"
            )
    shape = concat_shape(heads, "predict_path")  # served [N, T, *obs]
    arrays = {"y": load_files(heads)}
    shapes = {keys[0]: tuple(shape[2:])}
    for key in keys[1:]:  # further sensors: same N and T, NaN where they did not sample
        what = f"predict_path (stream '{key}')"
        streams = stream_headers(heads, key, keys[0], what)
        shapes[key] = tuple(concat_shape(streams, what)[2:])
        arrays[f"y_{key}"] = load_files(streams, missing=True)
    expected = layout or {keys[0]: tuple(obs_shape)}
    for key, got in shapes.items():
        if got != expected[key]:
            named = f" '{key}'" if layout else ""
            raise ValueError(
                f"predict_path: the sequences hold measurements{named} of shape {got} but the model was trained "
                f"on {expected[key]} (served layout [N, T, *obs]): give recordings of the same sensors"
            )
    if predict_given is not None and predict_given > shape[1]:
        raise ValueError(
            f"predict_given={predict_given} but the sequences of predict_path have T={shape[1]} samples: "
            f"give at most {shape[1]} (or leave predict_given unset to use all of them)"
        )
    if input_dim:
        arrays["u"] = _inputs(heads, input_dim, input_key)
    return TrajectoryDataset(arrays, streams=list(layout) or None)


def _inputs(heads: list, input_dim: int, input_key: str) -> np.ndarray:
    what = f"predict_path (inputs '{input_key}')"
    refusal = (
        f"{what}: this model is driven by {input_dim} inputs per step; give .npz files holding them beside the "
        "measurements (numpy.savez(path, y=..., u=...)), not {path}"
    )
    inputs = []
    for h in heads:
        u = read_beside(h, input_key, what, refusal)
        check_header(u, what)
        if len(u.shape) != 3 or u.shape[2] != input_dim or u.shape[0] != h.shape[0]:
            raise ValueError(
                f"{what}: {u.label} must be [N, T_u, {input_dim}] with the measurements' N = "
                f"{h.shape[0]}, got {u.shape}"
            )
        inputs.append(u)
    if len({u.shape[1] for u in inputs}) > 1:
        raise ValueError(f"{what}: every file must hold inputs of the same length T_u")
    return load_files(inputs)
