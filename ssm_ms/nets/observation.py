"""Observation models ``g``: states ``[N, state_dim]`` -> measurements ``[N, *obs_shape]``.

Any ``nn.Module`` with that contract works as ``g``. The image decoder lives in :mod:`ssm_ms.nets.decoder`, the
vector read-outs in :mod:`ssm_ms.nets.readout`; this module keeps the names that configs and checkpoints of earlier
versions recorded (``ssm_ms.nets.observation.ConvDecoder``, ...) importable.
"""

from ssm_ms.nets.decoder import PRESETS, ConvDecoder, drawn_size, stem_for_image_size
from ssm_ms.nets.readout import LinearReadout, Projection

__all__ = ["PRESETS", "ConvDecoder", "LinearReadout", "Projection", "drawn_size", "stem_for_image_size"]
