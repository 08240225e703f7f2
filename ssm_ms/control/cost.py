"""The swing-up task's cost, on the angle a state shows: up, and still once up.

For states ``[B, K, H + 1, d]`` of sampled rollouts and their inputs ``[B, K, H, m]``, with ``(sin phi, cos phi)``
read from each state by ``features`` (the true angle for the true model; for a learned model what its decoder
draws, :mod:`ssm_ms.control.goals`)::

    cost = mean_t (1 + cos phi_t) / 2                                      0 upright, 1 hanging
         + w_velocity * mean_t (1 - cos phi_t) / 2 * (dphi_t / dt)^2       motion, counted near the top only
         + w_input * mean_t u_t^2

Height alone rewards pumping energy into the swing (a higher swing lowers the mean); the velocity term, weighted by
how high the chain is, makes staying up better than spinning through the top, without fighting the swing below.
"""

from __future__ import annotations

from collections.abc import Callable

import torch


class SwingUpCost:
    """``cost(states, inputs) -> [B, K]`` of sampled rollouts (see the module doc)."""

    def __init__(
        self,
        features: Callable[[torch.Tensor], torch.Tensor],
        dt: float,
        w_velocity: float = 0.05,
        w_input: float = 1e-3,
    ):
        self.features, self.dt, self.w_velocity, self.w_input = features, float(dt), float(w_velocity), float(w_input)

    def __call__(self, states: torch.Tensor, inputs: torch.Tensor) -> torch.Tensor:
        b, k, t, d = states.shape
        sc = self.features(states[:, :, 1:].reshape(-1, d)).view(b, k, t - 1, 2)
        s, c = sc[..., 0], sc[..., 1]
        height = (1 + c) / 2
        s0, c0 = s[..., :-1], c[..., :-1]
        turn = torch.atan2(s[..., 1:] * c0 - c[..., 1:] * s0, c[..., 1:] * c0 + s[..., 1:] * s0) / self.dt
        near_top = (1 - c[..., 1:]) / 2
        return (
            height.mean(-1)
            + self.w_velocity * (near_top * turn.pow(2)).mean(-1)
            + self.w_input * inputs.pow(2).mean(dim=(-1, -2))
        )


def upright_error(angle: torch.Tensor) -> torch.Tensor:
    """``|angle - pi|`` wrapped to [0, pi] (0: upright), for angles with 0 hanging."""
    return torch.atan2(torch.sin(angle - torch.pi), torch.cos(angle - torch.pi)).abs()
