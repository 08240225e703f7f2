"""``NarrowLinear``: ``nn.Linear`` for a narrow input (a state), its weight gradient formed in the fast layout.

Autograd forms ``nn.Linear``'s weight gradient in the weight's own layout, ``dy^T x``: ``[out, rows] @ [rows,
in]``. With a narrow input (``in`` = 3, ``rows`` in the thousands: a batch of states through SSM-LL's first beta
layer) MKL runs that product several times slower than ``x^T dy`` (``[in, rows] @ [rows, out]``), the same numbers
transposed. Multiplying by a contiguous copy of ``W^T`` (``in x out`` floats, copied per call) makes autograd form
``x^T dy``. The bias rides in the same product, as one more row of that copy against a column of ones beside ``x``
(``[x, 1] @ [W^T; b]``): ``addmm`` would first copy the broadcast bias into the ``rows x out`` output and its backward
sum ``dy`` over the rows, two passes over the layer's largest tensor that cost more than the narrow product itself.
The same ``x W^T + b`` up to rounding; same parameters and state dict as ``nn.Linear``: checkpoints load either way.
Where it pays, and where not: benchmarks/results/narrow_linear.md."""

from __future__ import annotations

import torch
from torch import nn


class NarrowLinear(nn.Linear):
    """``nn.Linear`` whose weight gradient autograd forms as ``x^T dy`` (fast when ``in_features`` is small)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # a contiguous [in (+ 1), out] factor: autograd forms its gradient as [x, 1]^T dy, dW^T and db in one product
        if self.bias is None:
            return x @ self.weight.t().contiguous()
        w = torch.cat([self.weight.t(), self.bias.unsqueeze(0)])
        return torch.cat([x, x.new_ones(*x.shape[:-1], 1)], dim=-1) @ w
