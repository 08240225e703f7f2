"""The true model of the simulated pendulum, for the planner's upper bound (``ClosedLoop(true_model=True)``)."""

from __future__ import annotations

import torch
from torch import nn

from ssm_ms.control.cost import GRAVITY


class TruePendulum(nn.Module):
    """The simple pendulum's own equations, ``theta'' = -g sin(theta) - damping theta' + u`` (unit mass on a unit
    massless link: Pinocchio's model of the data), integrated by RK4 over one frame period: the planner's true model.
    State ``(theta, theta')``, input the joint torque."""

    input_dim, state_dim = 1, 2

    def __init__(self, frame_dt: float, damping: float = 0.0, substeps: int = 5):
        super().__init__()
        self.h, self.substeps, self.damping = frame_dt / substeps, int(substeps), float(damping)

    def forward(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        theta, omega, tau = x[:, 0], x[:, 1], u[:, 0]

        def acc(th: torch.Tensor, om: torch.Tensor) -> torch.Tensor:
            return -GRAVITY * torch.sin(th) - self.damping * om + tau

        h = self.h
        for _ in range(self.substeps):
            k1t, k1w = omega, acc(theta, omega)
            k2t, k2w = omega + 0.5 * h * k1w, acc(theta + 0.5 * h * k1t, omega + 0.5 * h * k1w)
            k3t, k3w = omega + 0.5 * h * k2w, acc(theta + 0.5 * h * k2t, omega + 0.5 * h * k2w)
            k4t, k4w = omega + h * k3w, acc(theta + h * k3t, omega + h * k3w)
            theta = theta + h / 6 * (k1t + 2 * k2t + 2 * k3t + k4t)
            omega = omega + h / 6 * (k1w + 2 * k2w + 2 * k3w + k4w)
        return torch.stack([theta, omega], dim=1)


def angle_of_state(x: torch.Tensor) -> torch.Tensor:
    """``(sin theta, cos theta)`` of true states ``(theta, theta')``."""
    return torch.stack([torch.sin(x[:, 0]), torch.cos(x[:, 0])], dim=1)
