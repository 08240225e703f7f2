"""The swing-up task's cost, on the angle a state shows: up, and still once up.

For states ``[B, K, H + 1, d]`` of sampled rollouts and their inputs ``[B, K, H, m]``, with ``(sin phi, cos phi)``
read from each state by ``features`` (the true angle for the true model; for a learned model what its decoder
draws, :mod:`ssm_ms.control.goals`)::

    cost = mean_t (1 + cos phi_t) / 2                                      0 upright, 1 hanging
         + w_velocity * mean_t (1 - cos phi_t) / 2 * (dphi_t / dt)^2       motion, counted near the top only
         + w_input * mean_t u_t^2
         + w_energy * mean_t max(0, E_t - max_energy)^2,   E_t = (dphi_t / dt)^2 / 2 + g (1 - cos phi_t)

Height alone rewards pumping energy into the swing (a higher swing lowers the mean); the velocity term, weighted by
how high the chain is, makes staying up better than spinning through the top, without fighting the swing below.
The energy term (off unless ``max_energy`` is given) keeps plans within the energies a learned model saw in its
data (``E`` per unit mass on a unit link, 0 hanging at rest, ``2 g`` upright at rest): a plan that spins through the
top leaves the data, where the model's predictions are not to be trusted.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

GRAVITY = 9.81


class SwingUpCost:
    """``cost(states, inputs) -> [B, K]`` of sampled rollouts (see the module doc)."""

    def __init__(
        self,
        features: Callable[[torch.Tensor], torch.Tensor],
        dt: float,
        w_velocity: float = 0.05,
        w_input: float = 1e-3,
        max_energy: float | None = None,
        w_energy: float = 0.01,
    ):
        self.features, self.dt, self.w_velocity, self.w_input = features, float(dt), float(w_velocity), float(w_input)
        self.max_energy, self.w_energy = (None if max_energy is None else float(max_energy)), float(w_energy)

    def __call__(self, states: torch.Tensor, inputs: torch.Tensor) -> torch.Tensor:
        b, k, t, d = states.shape
        sc = self.features(states[:, :, 1:].reshape(-1, d)).view(b, k, t - 1, 2)
        s, c = sc[..., 0], sc[..., 1]
        height = (1 + c) / 2
        s0, c0 = s[..., :-1], c[..., :-1]
        turn = torch.atan2(s[..., 1:] * c0 - c[..., 1:] * s0, c[..., 1:] * c0 + s[..., 1:] * s0) / self.dt
        near_top = (1 - c[..., 1:]) / 2
        cost = (
            height.mean(-1)
            + self.w_velocity * (near_top * turn.pow(2)).mean(-1)
            + self.w_input * inputs.pow(2).mean(dim=(-1, -2))
        )
        if self.max_energy is not None:
            energy = 0.5 * turn.pow(2) + GRAVITY * (1 - c[..., 1:])
            cost = cost + self.w_energy * (energy - self.max_energy).clamp_min(0).pow(2).mean(-1)
        return cost


def upright_error(angle: torch.Tensor) -> torch.Tensor:
    """``|angle - pi|`` wrapped to [0, pi] (0: upright), for angles with 0 hanging."""
    return torch.atan2(torch.sin(angle - torch.pi), torch.cos(angle - torch.pi)).abs()
