"""Sequence-to-sequence CNN-LSTM: the paper's LSTM baseline (Tables 1, 2 and 4).

Every step reads the measurement through the same per-frame CNN as the SSM's state encoder of that data
set (:class:`~ssm_ms.nets.encoder.FrameEncoder`; vectors pass unchanged), appends a flag that says
whether the step is filtered (1) or predicted (0), and feeds an LSTM (1024 hidden units in the paper)
whose hidden state a decoder maps back to the measurement: the data set's transposed-convolution decoder
for images (sigmoid pixels), a linear layer for vectors (Lorenz). While predicting the measurement is set
to zero before the CNN, as the paper does after the RKN authors, so the network only sees the flag.

The output at ``t`` estimates ``y[t]`` from the observed ``y[s]``, ``s <= t``: a reconstruction while
filtering, a prediction afterwards -- the same convention as :class:`~ssm_ms.baselines.rkn.RecurrentKalmanNetwork`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import Tensor, nn

from ssm_ms.baselines.common import SequenceOutput, frame_encoder, image_decoder, preset_for


class Seq2SeqLSTM(nn.Module):
    """CNN -> LSTM -> decoder, with a "filtering / predicting" flag at every step.

    Args:
        obs_shape: one measurement: ``[C, H, W]`` images or ``[D]`` vectors.
        hidden: LSTM hidden size (paper: 1024).
        encoder_preset: preset of the per-frame CNN; ``None``: ``"vector"`` for vectors, by image size for
            images (24 -> ``"pendulum"``, 48 -> ``"quad"``, 64 -> ``"mnist"``: the SSM encoders' CNNs; other
            sizes: the nearest of these); or the CNN itself as a mapping of ``FrameEncoder``'s ``conv_channels``,
            ``final_channels``, ``final_relu`` (e.g. a narrower CNN for a CPU-sized run).
        decoder_preset: images only: the ``ConvDecoder`` preset (``None``: by image size, as the encoder's),
            drawn at the image size of ``obs_shape`` (``ConvDecoder(image_size=...)``); or the layers
            themselves as a mapping of ``stem_channels`` and ``layers``.
        output: images: ``"sigmoid"`` (default) or ``"linear"``; vectors are always linear.
    """

    def __init__(
        self,
        obs_shape: Sequence[int],
        hidden: int = 1024,
        encoder_preset: str | Mapping[str, Any] | None = None,
        decoder_preset: str | Mapping[str, Any] | None = None,
        output: str = "sigmoid",
    ):
        super().__init__()
        obs_shape = tuple(int(s) for s in obs_shape)
        if len(obs_shape) not in (1, 3):
            raise ValueError(f"obs_shape must be [C, H, W] (images) or [D] (vectors), got {list(obs_shape)}")
        if hidden < 1:
            raise ValueError(f"hidden must be >= 1, got {hidden}")
        is_image = len(obs_shape) == 3
        if encoder_preset is None:
            encoder_preset = preset_for(obs_shape, "encoder_preset") if is_image else "vector"
        self.obs_shape = obs_shape
        self.frames = frame_encoder(obs_shape, encoder_preset)
        self.lstm = nn.LSTM(self.frames.out_features + 1, hidden, batch_first=True)
        if is_image:
            if output not in ("sigmoid", "linear"):
                raise ValueError(f"output for images must be 'sigmoid' or 'linear', got {output!r}")
            self.decoder: nn.Module = image_decoder(hidden, obs_shape, decoder_preset, output)
        else:
            self.decoder = nn.Linear(hidden, obs_shape[0])

    def inputs(self, y: Tensor, observed: Tensor) -> Tensor:
        """What the LSTM reads: ``[CNN(y[t] or 0), flag]`` per step, ``[B, T, features + 1]``."""
        k = len(self.obs_shape)
        if y.dim() != 2 + k or tuple(y.shape[2:]) != self.obs_shape:
            raise ValueError(f"y must be [B, T, *{list(self.obs_shape)}], got {list(y.shape)}")
        if tuple(observed.shape) != tuple(y.shape[:2]):
            raise ValueError(f"observed must be [B, T] = {list(y.shape[:2])}, got {list(observed.shape)}")
        observed = observed.to(device=y.device, dtype=torch.bool)
        mask = observed.view(*observed.shape, *([1] * k))
        y = torch.where(mask, y, torch.zeros((), dtype=y.dtype, device=y.device))  # predicting: no measurement
        return torch.cat([self.frames(y), observed.unsqueeze(-1).to(y.dtype)], dim=-1)

    def forward(self, y: Tensor, observed: Tensor | None = None) -> SequenceOutput:
        """``y [B, T, *obs_shape]``, ``observed [B, T]`` (default: all) ->
        ``SequenceOutput(mean [B, T, *obs_shape])``."""
        if observed is None:
            observed = torch.ones(y.shape[:2], dtype=torch.bool, device=y.device)
        out, _ = self.lstm(self.inputs(y, observed))
        return SequenceOutput(self.decoder(out))
