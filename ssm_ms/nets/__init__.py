"""Networks: residual transitions ``f``, observation models ``g``, state encoders, node encoders."""

from ssm_ms.nets.decoder import ConvDecoder
from ssm_ms.nets.encoder import FrameEncoder, StateEncoder
from ssm_ms.nets.history import HistoryEncoder
from ssm_ms.nets.readout import AngleReadout, LinearReadout, MLPReadout, Projection
from ssm_ms.nets.sensors import SensorHeads
from ssm_ms.nets.sprites import SpriteDecoder
from ssm_ms.nets.transition import FullyConnectedTransition, LocallyLinearTransition

__all__ = [
    "AngleReadout",
    "ConvDecoder",
    "FrameEncoder",
    "FullyConnectedTransition",
    "HistoryEncoder",
    "LinearReadout",
    "LocallyLinearTransition",
    "MLPReadout",
    "Projection",
    "SensorHeads",
    "SpriteDecoder",
    "StateEncoder",
]
