"""What the baselines share: their networks map a measurement sequence and an "observed" mask to an
estimate of every measurement, filtering where the mask is set and predicting where it is not; images
are read by the paper's per-frame CNN and written by its transposed-convolution decoders, chosen by
image size unless a config names them (the decoder drawn at the data's image size)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, NamedTuple

from torch import Tensor

from ssm_ms.nets.decoder import PRESETS as DECODER_PRESETS
from ssm_ms.nets.decoder import ConvDecoder
from ssm_ms.nets.encoder import FrameEncoder

# Image side -> preset of both the encoder and the decoder (the paper's three image experiments).
PRESET_BY_IMAGE_SIZE = {24: "pendulum", 48: "quad", 64: "mnist"}


class SequenceOutput(NamedTuple):
    """A baseline network's estimate of each measurement ``y[t]`` given ``y[s]`` for observed ``s <= t``.

    ``mean [B, T, *obs_shape]``: the estimate (pixels in [0, 1] for images); ``var``: its variance,
    same shape, for networks with a Gaussian output (``None`` otherwise).
    """

    mean: Tensor
    var: Tensor | None = None


def preset_for(obs_shape: tuple[int, ...], argument: str) -> str:
    """The encoder / decoder preset of an image size: that of the nearest of the paper's sizes (24 ->
    pendulum, 48 -> quad, 64 -> mnist; a tie goes to the smaller); the decoder is then drawn at the
    data's size (``ConvDecoder(image_size=...)``), the encoder's CNN reads any size."""
    c, h, w = obs_shape
    if h != w:
        raise ValueError(
            f"no default {argument} for non-square images of shape {list(obs_shape)}: the decoders draw square "
            f"images; give {argument} and square frames"
        )
    return PRESET_BY_IMAGE_SIZE[min(PRESET_BY_IMAGE_SIZE, key=lambda size: (abs(size - h), size))]


def decoder_preset_shape(preset: str) -> tuple[int, int, int]:
    """Output shape of a ConvDecoder preset, from its spec (without building it)."""
    _, size, layers = DECODER_PRESETS[preset]
    for _, kernel, stride in layers:
        size = (size - 1) * stride + kernel
    return (layers[-1][0] if layers else 0, size, size)


def frame_encoder(obs_shape: tuple[int, ...], preset: str | Mapping[str, Any]) -> FrameEncoder:
    """The per-frame CNN of a preset name, or of the layers themselves as a mapping of ``FrameEncoder``'s
    ``conv_channels``, ``final_channels``, ``final_relu``."""
    if not isinstance(preset, Mapping):
        return FrameEncoder(obs_shape, preset=preset)
    unknown = sorted(set(preset) - {"conv_channels", "final_channels", "final_relu"})
    if unknown:
        raise ValueError(
            f"encoder_preset as a mapping takes conv_channels, final_channels, final_relu; unknown: {unknown}"
        )
    return FrameEncoder(obs_shape, **preset)


def image_decoder(
    in_features: int, obs_shape: tuple[int, ...], preset: str | Mapping[str, Any] | None, output: str
) -> ConvDecoder:
    """The paper's transposed-convolution decoder from ``in_features`` to images of ``obs_shape``
    (``preset=None``: by image size; a mapping: the layers themselves, as ``ConvDecoder``'s ``stem_channels`` and
    ``layers``), refusing one that draws another image size."""
    if preset is None:
        preset = preset_for(obs_shape, "decoder_preset")
    square = len(obs_shape) == 3 and obs_shape[1] == obs_shape[2]
    image_size = obs_shape[-1] if square else None
    if isinstance(preset, Mapping):
        unknown = sorted(set(preset) - {"stem_channels", "layers"})
        if unknown or "layers" not in preset:
            raise ValueError(
                f"decoder_preset as a mapping takes 'layers' (and optionally 'stem_channels'), got "
                f"{sorted(preset)}: e.g. {{stem_channels: 64, layers: [[32, 3, 2], [1, 4, 2]]}}"
            )
        decoder = ConvDecoder(in_features, preset=None, output=output, image_size=image_size, **preset)
    else:
        decoder = ConvDecoder(in_features, preset=preset, output=output, image_size=image_size)
    if tuple(decoder.out_shape) != tuple(obs_shape):
        good = [name for name in DECODER_PRESETS if decoder_preset_shape(name)[0] == obs_shape[0]]
        hint = f"use decoder_preset={good[0]!r}" if good and square else "no ConvDecoder preset produces it"
        raise ValueError(
            f"the decoder preset {preset!r} produces images of shape {list(decoder.out_shape)} "
            f"but obs_shape is {list(obs_shape)}: {hint}"
        )
    return decoder
