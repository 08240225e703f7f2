"""CNN-LSTM state encoder: measurements ``[B, T, *obs_shape]`` -> latent states ``[B, T, state_dim]``.

Each frame goes through a small CNN (``[Conv 3x3, LayerNorm, ReLU, MaxPool 2]`` blocks, then one
more 3x3 convolution); the per-frame features feed an LSTM whose hidden state a linear head maps to
the latent state. The state at time ``t`` depends on measurements ``0..t`` only, so the encoder is
a causal filter: its output at the last measured frame starts the forecast. Vector measurements
(Lorenz) skip the CNN. The per-frame CNN is its own module, :class:`FrameEncoder`, shared with the
baselines in :mod:`ssm_ms.baselines`. Several sensors packed side by side (:mod:`ssm_ms.nets.sensors`)
are read stream by stream, :class:`StreamsEncoder`: each image through its CNN, each vector as it is, a
missing sample (NaN) as zeros beside a flag.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import torch
from torch import nn

# conv_channels, final_channels, final_relu (the paper's encoders)
ENCODER_PRESETS: dict[str, tuple[list[int], int | None, bool]] = {
    "pendulum": ([16, 16], 16, False),
    "quad": ([16, 16, 16], 16, False),
    "mnist": ([64, 128, 512], 16, True),
    "vector": ([], None, False),
}


class FrameEncoder(nn.Module):
    """The per-frame CNN of the paper's encoders: measurements ``[N, *obs_shape]`` -> features ``[N, out_features]``.

    Images go through ``[Conv 3x3, LayerNorm, ReLU, MaxPool 2]`` blocks and one more 3x3 convolution;
    vector measurements pass unchanged. Shared by the SSM's state encoder and the baselines
    (sequence-to-sequence CNN-LSTM, RKN), so that every method reads a frame the same way.

    Args:
        obs_shape: shape of one measurement: ``[C, H, W]`` images or ``[D]`` vectors.
        preset: ``"pendulum"``, ``"quad"``, ``"mnist"``, ``"vector"``, or ``None`` to give
            ``conv_channels`` / ``final_channels`` / ``final_relu`` explicitly.
        conv_channels: output channels of each conv-LayerNorm-ReLU-maxpool block.
        final_channels: channels of the last 3x3 convolution (``None``: no final convolution).
        final_relu: a ReLU after the last convolution.
    """

    def __init__(
        self,
        obs_shape: Sequence[int],
        preset: str | None = None,
        conv_channels: Sequence[int] | None = None,
        final_channels: int | None = None,
        final_relu: bool = False,
    ):
        super().__init__()
        obs_shape = tuple(int(s) for s in obs_shape)
        if preset is not None:
            if preset not in ENCODER_PRESETS:
                raise ValueError(f"unknown encoder preset {preset!r}; choose one of {sorted(ENCODER_PRESETS)} or None")
            conv_channels, final_channels, final_relu = ENCODER_PRESETS[preset]
        conv_channels = list(conv_channels or [])
        self.obs_shape = obs_shape
        if len(obs_shape) == 3:
            layers: list[nn.Module] = []
            c, h, w = obs_shape
            for out_c in conv_channels:
                if h < 4 or w < 4:
                    raise ValueError(
                        f"images of shape {list(obs_shape)} are too small for {len(conv_channels)} conv blocks"
                    )
                layers += [nn.Conv2d(c, out_c, 3), nn.LayerNorm((out_c, h - 2, w - 2)), nn.ReLU(), nn.MaxPool2d(2)]
                c, h, w = out_c, (h - 2) // 2, (w - 2) // 2
            if final_channels is not None:
                if h < 3 or w < 3:
                    raise ValueError(f"images of shape {list(obs_shape)} are too small for the final convolution")
                layers.append(nn.Conv2d(c, final_channels, 3))
                c, h, w = final_channels, h - 2, w - 2
                if final_relu:
                    layers.append(nn.ReLU())
            self.cnn: nn.Module = nn.Sequential(*layers)
            self.out_features = c * h * w
        elif len(obs_shape) == 1:
            if conv_channels or final_channels is not None:
                raise ValueError(f"vector measurements {list(obs_shape)} take no convolutions: use preset 'vector'")
            self.cnn = nn.Identity()
            self.out_features = obs_shape[0]
        else:
            raise ValueError(f"obs_shape must be [C, H, W] or [D], got {list(obs_shape)}")

    def forward(self, y: torch.Tensor) -> torch.Tensor:
        """``y [..., *obs_shape]`` -> ``[..., out_features]``."""
        n_obs = len(self.obs_shape)
        if tuple(y.shape[y.dim() - n_obs :]) != self.obs_shape:
            raise ValueError(
                f"the encoder was built for measurements of shape {list(self.obs_shape)}, "
                f"got {list(y.shape[y.dim() - n_obs :])}"
            )
        lead = y.shape[: y.dim() - n_obs]
        return self.cnn(y.reshape(-1, *self.obs_shape)).reshape(*lead, self.out_features)


class StreamsEncoder(nn.Module):
    """The per-frame features of several sensors packed side by side: ``[N, P] -> [N, out_features]``.

    The packed vector (the streams flattened and concatenated in the order of ``shapes``,
    :class:`~ssm_ms.nets.sensors.SensorLayout`) is split back into streams; each goes through its own
    :class:`FrameEncoder`, an image stream (``[C, H, W]``) through the CNN of ``preset`` / ``conv_channels`` /
    ``final_channels`` / ``final_relu``, a vector stream unchanged. A stream sampled at a lower rate holds NaN where it
    was not sampled: it is read as zeros, beside a flag per stream that is 1 where the stream was sampled (every
    component finite) and 0 where not, so the LSTM after it tells a missing sample from a zero.

    Args:
        shapes: ``{stream name: shape of one sample}``, in the packed order (e.g. ``SensorHeads.shapes``).
        preset, conv_channels, final_channels, final_relu: the CNN of the image streams (:class:`FrameEncoder`).
    """

    def __init__(
        self,
        shapes: Mapping[str, Sequence[int]],
        preset: str | None = None,
        conv_channels: Sequence[int] | None = None,
        final_channels: int | None = None,
        final_relu: bool = False,
    ):
        super().__init__()
        if not shapes:
            raise ValueError("StreamsEncoder needs at least one stream")
        self.names = list(shapes)
        self.shapes = [tuple(int(v) for v in shape) for shape in shapes.values()]
        self.sizes = [math.prod(shape) for shape in self.shapes]
        self.streams = nn.ModuleList(
            FrameEncoder(shape, preset, conv_channels, final_channels, final_relu)
            if len(shape) == 3
            else FrameEncoder(shape, "vector")
            for shape in self.shapes
        )
        self.obs_shape = (sum(self.sizes),)
        self.out_features = sum(e.out_features for e in self.streams) + len(self.streams)

    def forward(self, y: torch.Tensor) -> torch.Tensor:
        """``y [..., P]`` -> ``[..., out_features]``: each stream's features, then its flag, in the packed order."""
        if y.shape[-1] != self.obs_shape[0]:
            raise ValueError(
                f"the encoder was built for sensors {dict(zip(self.names, self.shapes))} packed into "
                f"{self.obs_shape[0]} values per step, got {y.shape[-1]}"
            )
        lead = y.shape[:-1]
        features = []
        for part, shape, encoder in zip(y.reshape(-1, y.shape[-1]).split(self.sizes, dim=1), self.shapes, self.streams):
            sampled = torch.isfinite(part).all(dim=1, keepdim=True)
            part = torch.where(sampled, part, torch.zeros_like(part))
            features += [encoder(part.reshape(-1, *shape)), sampled.to(part.dtype)]
        return torch.cat(features, dim=1).reshape(*lead, self.out_features)


class StateEncoder(nn.Module):
    """CNN-LSTM encoder of measurement sequences: :class:`FrameEncoder`, LSTM, linear head.

    Args:
        state_dim: latent dimension produced at every step.
        obs_shape: shape of one measurement: ``[C, H, W]`` images or ``[D]`` vectors.
        preset, conv_channels, final_channels, final_relu: the per-frame CNN, see :class:`FrameEncoder`.
        hidden: LSTM hidden size.
        input_dim: inputs per step of a driven system (0: none). The LSTM then reads, beside frame ``t``'s
            features, the input ``u[t - 1]`` that moved the system to it (zeros at ``t = 0``).
        streams: several sensors packed into ``obs_shape = [P]``: ``{name: shape}`` in the packed order, read by a
            :class:`StreamsEncoder` (the CNN settings for its image streams); ``None``: one sensor.
    """

    def __init__(
        self,
        state_dim: int,
        obs_shape: Sequence[int],
        preset: str | None = None,
        conv_channels: Sequence[int] | None = None,
        final_channels: int | None = None,
        final_relu: bool = False,
        hidden: int = 1024,
        input_dim: int = 0,
        streams: Mapping[str, Sequence[int]] | None = None,
    ):
        super().__init__()
        cnn = (preset, conv_channels, final_channels, final_relu)
        self.frames = FrameEncoder(obs_shape, *cnn) if not streams else StreamsEncoder(streams, *cnn)
        if tuple(int(v) for v in obs_shape) != self.frames.obs_shape:
            raise ValueError(
                f"the sensors {dict(streams)} pack into {list(self.frames.obs_shape)} values per step, "
                f"obs_shape is {list(obs_shape)}"
            )
        self.obs_shape, self.state_dim, self.input_dim = self.frames.obs_shape, state_dim, int(input_dim)
        self.lstm = nn.LSTM(self.frames.out_features + self.input_dim, hidden, batch_first=True)
        self.head = nn.Linear(hidden, state_dim)

    def forward(self, y: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        """``y [B, T, *obs_shape]`` (and, driven, the inputs ``u [B, >= T - 1, input_dim]`` between them) -> latent
        states ``[B, T, state_dim]``."""
        features = self.frames(y)
        if self.input_dim:
            b, t = y.shape[:2]
            if u is None or u.shape[0] != b or u.shape[1] < t - 1 or u.shape[2] != self.input_dim:
                raise ValueError(
                    f"the encoder of a driven system needs the inputs u [{b}, >= {t - 1}, {self.input_dim}] "
                    f"between the frames, got {None if u is None else list(u.shape)}"
                )
            previous = torch.cat([u.new_zeros(b, 1, self.input_dim), u[:, : t - 1]], dim=1)
            features = torch.cat([features, previous.to(features)], dim=-1)
        out, _ = self.lstm(features)
        return self.head(out)

    def step(
        self, y: torch.Tensor, u: torch.Tensor | None = None, memory: tuple[torch.Tensor, torch.Tensor] | None = None
    ) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        """One measurement at a time, as a recursive filter: ``y [B, *obs_shape]``, the input ``u [B, input_dim]``
        that moved the system to it (driven; ``None`` at the first measurement: zeros, as :meth:`forward`) and the
        LSTM's ``memory`` (``None`` at the first) -> the latent state ``[B, state_dim]`` and the memory to pass on.
        Step by step equals :meth:`forward` over the whole sequence."""
        features = self.frames(y)
        if self.input_dim:
            if u is None:
                u = features.new_zeros(len(y), self.input_dim)
            if u.shape != (len(y), self.input_dim):
                raise ValueError(f"the encoder's step needs u [{len(y)}, {self.input_dim}], got {list(u.shape)}")
            features = torch.cat([features, u.to(features)], dim=-1)
        out, memory = self.lstm(features[:, None], memory)
        return self.head(out[:, 0]), memory
