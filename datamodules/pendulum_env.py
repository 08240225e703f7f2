"""The pendulum as a system to control, frame by frame, and the files of episodes recorded on it (training data
of :class:`~datamodules.pendulum.PendulumDataModule`).
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from datamodules.pendulum_render import angle_reading, quantize, render
from datamodules.pendulum_sim import pendulum_model, simulate


class PendulumEnvironment:
    """The pendulum as a system to control: the simulator of the data set (Pinocchio, RK4) and its camera, one frame
    per call, for a batch of episodes.

    :meth:`reset` places the chains at given joint angles and velocities and returns the first measurements;
    :meth:`step` holds the torques ``u [B, n_links]`` (N m) for one frame period, as the data's torques are held, and
    returns the next. Measurements are made as the data's: frames rendered and noised (``noise_std``, clipped,
    quantised to 8 bits), float32 ``[B, 1, H, W]`` in [0, 1]; with the data's ``sensors`` the encoders' reading too
    (``angle_noise_std``; NaN between samples every ``angle_every`` periods), packed as a batch's ``y`` is
    (``[B, P]``; the reading alone ``[B, 2 n]``, :func:`angle_reading` of the angles noised).
    :attr:`state` ``[B, 2 n]`` (angles, then velocities) is the truth, for scoring only. The noise of episode
    ``i`` comes from ``numpy.random.default_rng([seed, 2, i])`` (split id 2: neither the training nor the test data's
    streams).
    """

    def __init__(self, params: dict[str, Any], seed: int = 0):
        self.params = dict(params)
        self.model = pendulum_model(params["n_links"])
        self.data = self.model.createData()
        self.steps = int(round(params["frame_dt"] / params["dt"]))
        self.seed = int(seed)
        self.frame_dt = float(params["frame_dt"])

    def reset(self, q0: np.ndarray, v0: np.ndarray) -> np.ndarray:
        self.q = np.array(q0, dtype=np.float64, ndmin=2)
        self.v = np.array(v0, dtype=np.float64, ndmin=2)
        self.rngs = [np.random.default_rng([self.seed, 2, i]) for i in range(len(self.q))]
        self.period = 0
        return self.measure()

    def measure(self) -> np.ndarray:
        """The measurements now, in the data's layout (see the class doc)."""
        sensors = self.params.get("sensors", ["image"])
        parts = {}
        if "image" in sensors:
            parts["image"] = self.frames()
        if "angle" in sensors:
            noise = np.stack([r.standard_normal(self.q.shape[1]) for r in self.rngs])
            angle = angle_reading(self.q + self.params["angle_noise_std"] * noise)
            if self.period % self.params["angle_every"]:
                angle[:] = np.nan
            parts["angle"] = angle
        if len(parts) == 1:
            return next(iter(parts.values()))
        return np.concatenate([parts[s].reshape(len(self.q), -1) for s in sensors], axis=1)

    @property
    def state(self) -> np.ndarray:
        return np.concatenate([self.q, self.v], axis=-1)

    def frames(self) -> np.ndarray:
        p = self.params
        out = np.empty((len(self.q), 1, p["image_size"], p["image_size"]), np.float32)
        for j, r in enumerate(self.rngs):
            clean = render(self.q[j : j + 1], p["image_size"], p["line_width"], p["rendering"])[0]
            noisy = np.clip(clean + np.float32(p["noise_std"]) * r.standard_normal(clean.shape, dtype=np.float32), 0, 1)
            out[j] = quantize(noisy) / np.float32(255.0)
        return out

    def clean_frames(self) -> np.ndarray:
        """The current frames without noise (for pictures)."""
        p = self.params
        return np.stack(
            [
                quantize(render(q[None], p["image_size"], p["line_width"], p["rendering"])[0]) / np.float32(255)
                for q in self.q
            ]
        )

    def step(self, u: np.ndarray) -> np.ndarray:
        u = np.asarray(u, dtype=np.float64).reshape(len(self.q), 1, -1)
        q, v, _ = simulate(
            self.model, self.data, self.q, self.v, 2, self.steps, self.params["dt"], self.params["damping"], u
        )
        self.q, self.v = q[:, 1], v[:, 1]
        self.period += 1
        return self.measure()


# ---------------------------------------------------------------------------------- recorded episodes
# What a recorded episode's system must share with the data's (the excitation, the starts and the seed may differ)
RECORDED_SYSTEM = (
    "n_links",
    "image_size",
    "rendering",
    "line_width",
    "noise_std",
    "frame_dt",
    "dt",
    "damping",
    "gravity",
)
RECORDED_KEYS = ("y", "y_clean", "state", "u")


def read_recorded(path: str, params: dict[str, Any], n_frames: int) -> dict[str, np.ndarray]:
    """The arrays of a file of recorded episodes (``ClosedLoop(record=...)``), checked against the data's system
    ``params`` and length ``n_frames``: ``ValueError`` with one line naming what differs."""
    import json

    if not os.path.isfile(path):
        raise ValueError(f"recorded: no file {path} (write one with the closed loop's record option, docs/control.md)")
    try:
        with np.load(path) as z:
            missing = [k for k in (*RECORDED_KEYS, "params") if k not in z.files]
            if missing:
                raise ValueError(f"recorded: {path} lacks {missing}: not a file written by the closed loop's record")
            arrays = {k: z[k] for k in RECORDED_KEYS}
            system = json.loads(str(z["params"]))
    except (OSError, EOFError) as exc:
        raise ValueError(f"recorded: {path} is not a readable .npz file ({exc})") from None
    differ = [k for k in RECORDED_SYSTEM if system.get(k) != params.get(k)]
    if system.get("torque_limit", 0) > params.get("torque_limit", 0):
        differ.append("torque_limit")
    if differ:
        shown = ", ".join(f"{k} {system.get(k)} (data: {params.get(k)})" for k in differ)
        raise ValueError(f"recorded: {path} was recorded on another system: {shown}")
    count, size = len(arrays["u"]), params["image_size"]
    expected = {
        "y": (count, n_frames, 1, size, size),
        "y_clean": (count, n_frames, 1, size, size),
        "state": (count, n_frames, 2 * params["n_links"]),
        "u": (count, n_frames, params["n_links"]),
    }
    for key, shape in expected.items():
        if arrays[key].shape != shape:
            raise ValueError(
                f"recorded: {path}'s {key} has shape {list(arrays[key].shape)}, the data need {list(shape)} "
                f"(episodes of duration / frame_dt = {n_frames} frames)"
            )
        if not np.isfinite(arrays[key]).all():
            raise ValueError(f"recorded: {path}'s {key} holds NaN or inf")
    if arrays["y"].dtype != np.uint8 or arrays["y_clean"].dtype != np.uint8:
        raise ValueError(f"recorded: {path}'s frames must be uint8, as the data's")
    return arrays


def file_digest(path: str) -> str:
    """A short hash of a file's bytes (what the cache key records of a recorded file)."""
    import hashlib

    h = hashlib.sha1()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:10]
