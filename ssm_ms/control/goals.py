"""What the controller wants, read from images: the pendulum's angle from where its ink is.

The camera looks at a chain hanging from a fixed pivot; a frame's ink (its pixel intensities above the background)
has its centroid on the chain, at half the length of a straight single link. The angle of that centroid about the
pivot, ``phi = atan2(x - x_pivot, y - y_pivot)`` (image x right, y down: 0 hanging, +-pi upright), is the
pendulum's angle for one link, and for a chain the angle of its centre of ink. :func:`ink_angle_features` computes
``(sin phi, cos phi)`` from frames. A learned model's states are scored through its decoder: ``g(x)`` is the
frame the model expects the camera to see. Decoding every sampled state of every planned rollout is the planner's
largest cost, so :class:`DistilledFeatures` fits a small network ``x -> (sin phi, cos phi)`` of ``g(x)``'s
features once, on states the model itself produces, and the planner scores states with it.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn


def ink_angle_features(frames: torch.Tensor, pivot: tuple[float, float], floor: float = 0.1) -> torch.Tensor:
    """``(sin phi, cos phi)`` ``[N, 2]`` of frames ``[N, 1, H, W]`` (or ``[N, H, W]``) in [0, 1]: ``phi`` the angle
    about ``pivot = (x, y)`` (pixel units, pixel ``(i, j)`` centred at ``(j + 0.5, i + 0.5)``) of the centroid of
    the ink above ``floor`` (the background and the decoder's haze below it do not pull the centroid)."""
    img = frames.reshape(frames.shape[0], frames.shape[-2], frames.shape[-1])
    ink = (img - floor).clamp_min(0)
    h, w = img.shape[-2:]
    ys = torch.arange(h, dtype=img.dtype, device=img.device) + 0.5
    xs = torch.arange(w, dtype=img.dtype, device=img.device) + 0.5
    total = ink.sum(dim=(-1, -2)).clamp_min(1e-6)
    cx = (ink.sum(-2) * xs).sum(-1) / total - pivot[0]
    cy = (ink.sum(-1) * ys).sum(-1) / total - pivot[1]
    radius = torch.sqrt(cx * cx + cy * cy).clamp_min(1e-6)
    return torch.stack([cx / radius, cy / radius], dim=-1)


class DistilledFeatures(nn.Module):
    """A small MLP ``x [N, d] -> features [N, k]`` fitted to ``features(g(x))`` on states a model produces.

    It reads the states standardised by their mean and spread on the fitting states (buffers, set by :meth:`fit`):
    a model's states have whatever scale training gave them (the amortised pendulum's shrink to a spread of ~0.003
    per coordinate once the gap term's weight is raised), and a fixed-scale network on raw states then resolves them
    coarsely or not at all."""

    def __init__(self, state_dim: int, out_features: int = 2, hidden: int = 128):
        super().__init__()
        self.register_buffer("mean", torch.zeros(state_dim))
        self.register_buffer("scale", torch.ones(state_dim))
        self.net = nn.Sequential(
            nn.Linear(state_dim, hidden),
            nn.Tanh(),
            nn.Linear(hidden, hidden),
            nn.Tanh(),
            nn.Linear(hidden, out_features),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.net((x - self.mean) / self.scale)
        return out / out.norm(dim=-1, keepdim=True).clamp_min(1e-6)  # a point on the circle: (sin, cos)

    @classmethod
    def fit(
        cls,
        states: torch.Tensor,
        target: Callable[[torch.Tensor], torch.Tensor],
        steps: int = 2000,
        batch: int = 512,
        lr: float = 3e-3,
        seed: int = 0,
    ) -> tuple[DistilledFeatures, float]:
        """Fit to ``target(states)`` (e.g. ``ink_angle_features(g(states))``), computed once, on the states
        standardised by their own mean and spread; returns the network and its mean squared error on the states (held
        out: every fifth state)."""
        generator = torch.Generator().manual_seed(seed)
        with torch.no_grad():
            y = torch.cat([target(part) for part in states.split(4096)])
        held = torch.arange(len(states)) % 5 == 0
        torch.manual_seed(seed)
        net = cls(states.shape[1], y.shape[1])
        net.mean.copy_(states.mean(0))
        net.scale.copy_(states.std(0).clamp_min(1e-12))
        optimizer = torch.optim.Adam(net.parameters(), lr=lr)
        x_train, y_train = states[~held], y[~held]
        for step in range(steps):
            pick = torch.randint(len(x_train), (batch,), generator=generator)
            loss = (net(x_train[pick]) - y_train[pick]).pow(2).mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            if step == steps // 2:
                for group in optimizer.param_groups:
                    group["lr"] = lr / 10
        with torch.no_grad():
            error = float((net(states[held]) - y[held]).pow(2).mean())
        return net.eval().requires_grad_(False), error
