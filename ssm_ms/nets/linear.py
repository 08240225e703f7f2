"""``NarrowLinear``: ``nn.Linear`` for a narrow input (a state), its weight gradient formed in the fast layout.

Autograd forms ``nn.Linear``'s weight gradient in the weight's own layout, ``dy^T x``: ``[out, rows] @ [rows,
in]``. With a narrow input (``in`` = 3, ``rows`` in the thousands: a batch of states through SSM-LL's first beta
layer) MKL runs that product several times slower than ``x^T dy`` (``[in, rows] @ [rows, out]``), the same numbers
transposed. Multiplying by a contiguous copy of ``W^T`` (``in x out`` floats, copied per call) makes autograd form
``x^T dy``; the forward product is the same ``x W^T + b``. Same parameters and state dict as ``nn.Linear``:
checkpoints load either way. Where it pays, and where not: benchmarks/results/narrow_linear.md."""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F


class NarrowLinear(nn.Linear):
    """``nn.Linear`` whose weight gradient autograd forms as ``x^T dy`` (fast when ``in_features`` is small)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # W stored transposed ([in, out] contiguous, viewed as [out, in]): F.linear multiplies by that storage,
        # and autograd forms the gradient of a contiguous [in, out] factor as x^T dy.
        return F.linear(x, self.weight.t().contiguous().t(), self.bias)
