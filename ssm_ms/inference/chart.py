"""A chart of the states a learned model visits: a small autoencoder ``x ~ D(E(x))`` whose code has ``dims`` numbers.

A learned SSM's state has more dimensions than its system (ten for a pendulum's two), and the trained ``f`` and ``g``
are only meaningful near the states training gave them. A filter over the whole state can move its estimate off that
set along directions no frame pins, where ``f`` predicts nonsense; a filter over the chart's code ``z``, with
transition ``E(f(D(z), u))`` and measurement ``g(D(z))``, cannot: every estimate ``D(z)`` is a state of the kind
training produced, and the frames have only ``dims`` directions to pin (studies/ukf_in_the_loop, point 14).

The code is standardised (mean 0, standard deviation 1 over the fitted states, per dimension), so a filter's
variances on it are in units of the states' own spread.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import torch
from torch import nn


@dataclass(frozen=True)
class ChartSettings:
    """``dims``: the code's size; ``steps``, ``batch``, ``lr``: the autoencoder's Adam fit (its learning rate
    annealed to zero on a cosine); ``width``: its two hidden layers (tanh) on each side."""

    dims: int
    steps: int = 4000
    batch: int = 1024
    lr: float = 1e-3
    width: int = 128

    @classmethod
    def parse(cls, given: dict, state_dim: int | None = None) -> ChartSettings:
        """From a config's mapping, with one message for an unknown key or a size out of range (``dims`` at most
        ``state_dim`` where given: a chart has no more directions than the state)."""
        names = [f.name for f in fields(cls)]
        if not isinstance(given, dict) or set(given) - set(names) or "dims" not in given:
            raise ValueError(f"a chart takes {', '.join(names)} (dims required), got {given!r}")
        for name, value in given.items():
            whole = name != "lr"
            kinds = (int,) if whole else (int, float)
            if isinstance(value, bool) or not isinstance(value, kinds) or (not whole and value <= 0):
                raise ValueError(f"a chart's {name} is {'a whole number' if whole else 'a number > 0'}, got {value!r}")
        settings = cls(**given)
        top = state_dim if state_dim is not None else settings.dims
        if not (1 <= settings.dims <= top and settings.steps >= 1 and settings.batch >= 1 and settings.width >= 1):
            limit = f" (the state has {state_dim})" if state_dim is not None else ""
            raise ValueError(
                f"a chart needs 1 <= dims <= the state's size{limit} and steps, batch, width >= 1: {given}"
            )
        return settings

    def as_dict(self) -> dict:
        return asdict(self)


def _mlp(n_in: int, n_out: int, width: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(n_in, width), nn.Tanh(), nn.Linear(width, width), nn.Tanh(), nn.Linear(width, n_out))


class StateChart(nn.Module):
    """``encode``: states ``[N, d]`` to standardised codes ``[N, dims]``; ``decode``: back. Build with :meth:`fit`."""

    def __init__(self, state_dim: int, settings: ChartSettings):
        super().__init__()
        self.dims = settings.dims
        self.enc, self.dec = _mlp(state_dim, self.dims, settings.width), _mlp(self.dims, state_dim, settings.width)
        for name, size in (("x_mean", state_dim), ("x_std", state_dim), ("z_mean", self.dims), ("z_std", self.dims)):
            self.register_buffer(name, torch.zeros(size))
        self.held_error = float("nan")

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        return (self.enc((x - self.x_mean) / self.x_std) - self.z_mean) / self.z_std

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        return self.dec(z * self.z_std + self.z_mean) * self.x_std + self.x_mean

    def pulled_back(self, f, g):
        """A model ``f(x, u)``, ``g(x)`` on the chart's codes: ``E(f(D(z), u))`` and ``g(D(z))``."""
        return (lambda z, u: self.encode(f(self.decode(z), u))), (lambda z: g(self.decode(z)))

    @classmethod
    def fit(cls, states: torch.Tensor, settings: ChartSettings, seed: int = 0) -> StateChart:
        """Fitted to ``states [N, d]`` (standardised per dimension) by the mean squared reconstruction error; every
        tenth state (a seeded draw) is held out and its error, in standardised units, is ``held_error``."""
        generator = torch.Generator().manual_seed(seed)
        torch.manual_seed(seed)
        states = states.detach().float()
        chart = cls(states.shape[1], settings)
        chart.x_mean.copy_(states.mean(0))
        chart.x_std.copy_(states.std(0).clamp_min(1e-6))
        xs = (states - chart.x_mean) / chart.x_std
        order = torch.randperm(len(xs), generator=generator)
        held, train = xs[order[: len(xs) // 10]], xs[order[len(xs) // 10 :]]
        params = [*chart.enc.parameters(), *chart.dec.parameters()]
        optimizer = torch.optim.Adam(params, lr=settings.lr)
        schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, settings.steps)
        with torch.enable_grad():
            for _ in range(settings.steps):
                batch = train[torch.randint(len(train), (settings.batch,), generator=generator)]
                loss = (chart.dec(chart.enc(batch)) - batch).pow(2).mean()
                optimizer.zero_grad()
                loss.backward()
                optimizer.step()
                schedule.step()
        with torch.no_grad():
            chart.held_error = float((chart.dec(chart.enc(held)) - held).pow(2).mean()) if len(held) else float("nan")
            codes = chart.enc(xs)
            chart.z_mean.copy_(codes.mean(0))
            chart.z_std.copy_(codes.std(0).clamp_min(1e-6))
        return chart.eval().requires_grad_(False)
