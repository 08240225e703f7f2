"""What the baselines share: their networks map a measurement sequence and an "observed" mask to an
estimate of every measurement, filtering where the mask is set and predicting where it is not."""

from __future__ import annotations

from typing import NamedTuple, Optional

from torch import Tensor


class SequenceOutput(NamedTuple):
    """A baseline network's estimate of each measurement ``y[t]`` given ``y[s]`` for observed ``s <= t``.

    ``mean [B, T, *obs_shape]``: the estimate (pixels in [0, 1] for images); ``var``: its variance,
    same shape, for networks with a Gaussian output (``None`` otherwise).
    """

    mean: Tensor
    var: Optional[Tensor] = None
