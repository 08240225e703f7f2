"""Vector read-outs ``g``: states ``[N, state_dim]`` -> measurement vectors ``[N, p]`` (Lorenz's x, a user's
channels)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from ssm_ms.nets.transition import mlp


class Projection(nn.Module):
    """``g(x) = x[..., indices]``: the measurement reads components of the state (e.g. Lorenz's x)."""

    def __init__(self, indices: Sequence[int]):
        super().__init__()
        if len(indices) == 0:
            raise ValueError("Projection needs at least one state index")
        if min(indices) < 0:
            raise ValueError(f"Projection indices must be >= 0, got {list(indices)}")
        self.max_index = max(indices)
        self.register_buffer("indices", torch.as_tensor(list(indices), dtype=torch.long), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.max_index >= x.shape[-1]:
            raise ValueError(
                f"Projection reads state components {self.indices.tolist()} but the state has {x.shape[-1]}"
            )
        return x.index_select(-1, self.indices)

    def observation_matrix(self, state_dim: int) -> torch.Tensor:
        """``H [p, state_dim]`` with ``g(x) = H x`` (one 1 per row): lets a Kalman update skip sigma points."""
        if self.max_index >= state_dim:
            raise ValueError(f"Projection reads state components {self.indices.tolist()} but the state has {state_dim}")
        return torch.eye(state_dim, device=self.indices.device)[self.indices]


class LinearReadout(nn.Linear):
    """``g(x) = W x + b`` for vector measurements, its size taken from the data unless given.

    With ``out_features=None`` the layer has no parameters until the model hands it the data's
    measurement shape (:meth:`adopt_measurement_shape`, called by ``MultipleShootingModule.setup``
    before the optimizer exists); the model then records the size in its hyperparameters, so the run's
    ``hparams.yaml`` and checkpoints name it and reload without the data. It is an ``nn.Linear``: the
    Kalman filters use its matrix for an exact update.

    Args:
        state_dim: input dimension.
        out_features: number of measured channels; ``None``: the data's.
        bias: learn ``b``.
    """

    def __init__(self, state_dim: int, out_features: int | None = None, bias: bool = True):
        if out_features is not None and out_features < 1:
            raise ValueError(f"LinearReadout out_features must be >= 1 (or null: the data's), got {out_features}")
        super().__init__(state_dim, out_features or 1, bias)
        self.sized = out_features is not None
        if not self.sized:  # no parameters to train or save until the data say how many channels
            self.out_features = 0
            self.weight = nn.Parameter(self.weight.new_empty(0, state_dim))
            if bias:
                self.bias = nn.Parameter(self.bias.new_empty(0))

    def adopt_measurement_shape(self, obs_shape: Sequence[int]) -> dict[str, int]:
        """Size the layer for measurements of ``obs_shape`` if it was left unsized; returns the init
        arguments it fixed (``{}`` if none)."""
        obs_shape = tuple(int(s) for s in obs_shape)
        if len(obs_shape) != 1:
            raise ValueError(
                f"LinearReadout draws vectors, but the measurements have shape {list(obs_shape)}: use a ConvDecoder "
                "for images"
            )
        if self.sized:
            return {}
        self.out_features, self.sized = obs_shape[0], True
        self.weight = nn.Parameter(self.weight.new_empty(self.out_features, self.in_features))
        if self.bias is not None:
            self.bias = nn.Parameter(self.bias.new_empty(self.out_features))
        self.reset_parameters()
        return {"out_features": self.out_features}

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.sized:
            raise ValueError(
                "LinearReadout has out_features null (the data's) but has not seen the data yet: train it with a "
                "DataModule, or give out_features"
            )
        return super().forward(x)


class AngleReadout(nn.Module):
    """``g(x)``: the ``(sin q, cos q)`` of ``joints`` angles, as joint encoders give them (``[sin q_1, ..., sin q_n,
    cos q_1, ..., cos q_n]``: :func:`datamodules.pendulum_render.angle_reading`'s order): a linear map of the state to
    one 2-vector per joint, each scaled onto the unit circle. Bounded whatever the state (a linear readout's
    reading grows with a state that leaves the data's range), and every reading a possible one.

    Not an ``nn.Linear``: the Kalman filters evaluate it on sigma points.

    Args:
        state_dim: input dimension.
        joints: angles read (outputs ``2 * joints``).
    """

    def __init__(self, state_dim: int, joints: int = 1):
        super().__init__()
        if joints < 1:
            raise ValueError(f"AngleReadout reads at least one joint, got joints={joints}")
        self.joints = int(joints)
        self.linear = nn.Linear(state_dim, 2 * self.joints)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        v = self.linear(x).unflatten(-1, (2, self.joints))  # [..., (sin, cos), joints]
        v = v / v.norm(dim=-2, keepdim=True).clamp_min(1e-6)
        return v.flatten(-2)


class MLPReadout(nn.Module):
    """``g(x) = W x + b + MLP(x)``: a linear readout with a network beside it, the form of deepSI SUBNET's output map
    ``h``. The network's last layer starts at zero, so at initialisation ``g`` is the linear readout ``W x + b``;
    the network then learns what a linear map of the state cannot read (a sensor's saturation, an output
    nonlinearity), so the state need not carry it.

    Not an ``nn.Linear``: the Kalman filters evaluate it on sigma points.

    Args:
        state_dim: input dimension.
        out_features: number of measured channels.
        hidden: the network's hidden widths.
        activation: ``"tanh"`` or ``"relu"``.
    """

    def __init__(self, state_dim: int, out_features: int, hidden: Sequence[int] = (64, 64), activation: str = "tanh"):
        super().__init__()
        if state_dim < 1 or out_features < 1 or not hidden or any(h < 1 for h in hidden):
            raise ValueError(
                f"MLPReadout needs state_dim, out_features and at least one hidden width >= 1, got {state_dim}, "
                f"{out_features}, {list(hidden)}"
            )
        self.linear = nn.Linear(state_dim, out_features)
        self.mlp = mlp(state_dim, hidden, out_features, activation)
        nn.init.zeros_(self.mlp[-1].weight)
        nn.init.zeros_(self.mlp[-1].bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.linear(x) + self.mlp(x)
