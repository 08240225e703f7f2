"""Model-predictive control by sampling (MPPI, Williams et al. 2017) on a transition ``x[t+1] = f(x[t], u[t])``.

Pure tensor functions, batched over independent problems (episodes): each plans ``K`` perturbed input sequences of
``H`` steps around its nominal plan, rolls them out through ``f`` in one batch of ``B * K`` states per step, scores
them with ``cost(states, inputs)``, and moves the nominal plan to the exponentially weighted mean of the samples
(weights ``exp(-(c - min c) / (temperature * std c))``: the temperature is relative to the spread of the costs, so
one setting fits costs of any scale). Inputs stay within ``[u_min, u_max]`` (clipped), the nominal plan is sample 0
of every iteration (a plan never gets worse by resampling), and :class:`RecedingHorizon` applies the first input
and shifts the plan by one step for the next control step.

Offset-free planning (``offset_gain`` > 0, the disturbance estimate of offset-free MPC): a learned ``f`` that is
slightly wrong where the system is held (near an unstable equilibrium, say) makes a planner hold it a little off
its goal, where the error grows until the actuator's limits cannot catch it. :class:`RecedingHorizon` therefore
compares each new state with what ``f`` predicted for it from the previous state and input, keeps a filtered
estimate of the difference, ``d <- (1 - gain) d + gain (x[t] - f(x[t-1], u[t-1]))``, and plans on
``f(x, u) + d``: a constant error of ``f`` is then cancelled after one step (``gain`` 1) and the hold has no
steady offset, like a controller's integral action.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from ssm_ms.training.shooting import rollout

Cost = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]  # (states [B, K, H+1, d], inputs [B, K, H, m]) -> [B, K]


@dataclass
class MPPISettings:
    """Settings of :func:`mppi`.

    Attributes:
        horizon: planned steps ``H``.
        samples: input sequences ``K`` sampled per problem and iteration (the nominal plan among them).
        iterations: refinements of the plan per control step.
        noise_std: standard deviation of the input perturbations, in input units.
        temperature: softness of the weighting, relative to the standard deviation of the sampled costs.
        u_min, u_max: bounds of every input component (the actuator's limits).
        smoothing: correlation of consecutive perturbations (0: white; 0.5: each step half the previous one's).
    """

    horizon: int = 20
    samples: int = 256
    iterations: int = 2
    noise_std: float = 1.0
    temperature: float = 0.1
    u_min: float = -1.0
    u_max: float = 1.0
    smoothing: float = 0.5

    def __post_init__(self) -> None:
        for name in ("horizon", "samples", "iterations"):
            value = getattr(self, name)
            if int(value) != value:
                raise ValueError(f"MPPI {name} must be a whole number, got {value}")
            setattr(self, name, int(value))
            if getattr(self, name) < 1:
                raise ValueError(f"MPPI {name} must be >= 1, got {getattr(self, name)}")
        if not (self.noise_std > 0 and self.temperature > 0 and self.u_min < self.u_max and 0 <= self.smoothing < 1):
            raise ValueError(
                f"MPPI needs noise_std > 0, temperature > 0, u_min < u_max and 0 <= smoothing < 1, got {self.noise_std}, "
                f"{self.temperature}, {self.u_min}, {self.u_max}, {self.smoothing}"
            )


def mppi(
    f: Callable[..., torch.Tensor],
    cost: Cost,
    x0: torch.Tensor,
    plan: torch.Tensor,
    settings: MPPISettings,
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Refine the nominal input sequences ``plan [B, H, m]`` from the states ``x0 [B, d]``.

    Returns ``(plan [B, H, m], cost [B])``: the new nominal plan and the cost of the best sample of the last
    iteration (for monitoring).
    """
    b, h, m = plan.shape
    k, d = settings.samples, x0.shape[-1]
    best = plan.new_zeros(b)
    for _ in range(settings.iterations):
        white = torch.randn(b, k, h, m, generator=generator, dtype=plan.dtype, device=plan.device)
        noise = torch.empty_like(white)
        noise[:, :, 0] = white[:, :, 0]
        a = settings.smoothing
        for t in range(1, h):  # AR(1) perturbations of unit variance: smoother pushes than white noise
            noise[:, :, t] = a * noise[:, :, t - 1] + (1 - a * a) ** 0.5 * white[:, :, t]
        noise[:, 0] = 0.0  # sample 0: the nominal plan itself
        inputs = (plan.unsqueeze(1) + settings.noise_std * noise).clamp(settings.u_min, settings.u_max)
        states = rollout(f, x0.repeat_interleave(k, dim=0), h + 1, inputs.reshape(b * k, h, m))
        costs = cost(states.view(b, k, h + 1, d), inputs)  # [B, K]
        spread = costs.std(dim=1, keepdim=True).clamp_min(1e-9)
        weights = torch.softmax(-(costs - costs.min(dim=1, keepdim=True).values) / (settings.temperature * spread), 1)
        plan = (weights[..., None, None] * inputs).sum(dim=1)
        best = costs.min(dim=1).values
    return plan, best


def checked_offset_gain(gain: float) -> float:
    """``gain`` as a float where it is a valid offset gain (0: off, up to 1); otherwise one :class:`ValueError`."""
    if not 0.0 <= gain <= 1.0:
        raise ValueError(
            f"offset_gain weighs the newest model error in the planner's running estimate: 0 (off) to 1, got {gain}"
        )
    return float(gain)


class RecedingHorizon:
    """The control loop's planner: keeps a nominal plan per problem, refines it every step with :func:`mppi`,
    applies its first input and shifts it by one step (the last input repeated).

    With ``offset_gain`` in (0, 1], it plans on ``f(x, u) + offset``, ``offset [B, d]`` the filtered difference
    between each state it is given and ``f``'s prediction of it from the previous call's state and input (see the
    module doc; 0: plain ``f``)."""

    def __init__(
        self,
        f: Callable[..., torch.Tensor],
        cost: Cost,
        settings: MPPISettings,
        batch: int,
        input_dim: int,
        seed: int = 0,
        dtype: torch.dtype = torch.float32,
        offset_gain: float = 0.0,
    ):
        self.f, self.cost, self.settings, self.offset_gain = f, cost, settings, checked_offset_gain(offset_gain)
        self.plan = torch.zeros(batch, settings.horizon, input_dim, dtype=dtype)
        self.generator = torch.Generator().manual_seed(seed)
        self.offset: torch.Tensor | None = None
        self._last: tuple[torch.Tensor, torch.Tensor] | None = None  # the previous call's state and input

    @torch.no_grad()
    def __call__(self, x: torch.Tensor, applied: torch.Tensor | None = None) -> torch.Tensor:
        """The inputs ``[B, m]`` to apply now, from the current state estimates ``x [B, d]``; ``applied``: the inputs
        applied since the previous call where they differ from the ones it returned (e.g. with exploration noise)."""
        x = x.to(self.plan.dtype)
        f = self.f
        if self.offset_gain > 0:
            if self._last is not None:
                previous, u = self._last
                u = u if applied is None else applied.to(u.dtype)
                error = x - self.f(previous, u)
                gain = self.offset_gain
                self.offset = gain * error if self.offset is None else (1 - gain) * self.offset + gain * error
            if self.offset is not None:
                samples = self.offset.repeat_interleave(self.settings.samples, dim=0)

                def f(z: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
                    return self.f(z, u) + samples

        self.plan, self.last_cost = mppi(f, self.cost, x, self.plan, self.settings, self.generator)
        u = self.plan[:, 0].clone()
        self.plan = torch.cat([self.plan[:, 1:], self.plan[:, -1:]], dim=1)
        self._last = (x, u)
        return u
