"""The UKF run on a chart of the model's training states, in the closed loop (a feasibility check, not a library
estimator). An autoencoder ``x ~ D(E(x))`` with a ``k``-dimensional code is fitted to the model's own states (every
shooting node rolled out under random torques, as the planner's angle readout is distilled); the UKF then estimates
the code ``z`` with transition ``E(f(D(z), u))`` and measurement ``g(D(z))``, and the planner gets ``D(z)``. So the
estimate cannot leave the set of states the model was trained on (what every window fit of this study did), and has
only ``k`` directions for the frames to pin (the pendulum has two), while ``f`` and ``g`` stay the ten-dimensional
model's. Run from the repository root:
    python studies/ukf_in_the_loop/chart_ukf_try.py '{"k": 3, "q": 1e-3, "episodes": 20}'
    python studies/ukf_in_the_loop/chart_ukf_try.py '{"k": 3, "diagnose": "/tmp/chart_diag.md"}'
k: the code's size; q: the process variance in the code's standardised units; var: the pixel variance (the shipped
UKF's 0.1); steps, rollout: the autoencoder's Adam steps and the rollout length of its training states."""

import json
import sys

import torch
from estimator_try import try_estimator

from ssm_ms.control.estimators import UKFEstimator
from ssm_ms.control.module import excited_states
from ssm_ms.inference.ukf import UnscentedKalmanFilter

S = json.loads(sys.argv[1]) if len(sys.argv) > 1 else {}
K, Q, VAR = int(S.get("k", 3)), float(S.get("q", 1e-3)), float(S.get("var", 0.1))
STEPS, ROLLOUT, WIDTH = int(S.get("steps", 4000)), int(S.get("rollout", 20)), int(S.get("width", 128))


def mlp(n_in: int, n_out: int) -> torch.nn.Sequential:
    return torch.nn.Sequential(
        torch.nn.Linear(n_in, WIDTH),
        torch.nn.Tanh(),
        torch.nn.Linear(WIDTH, WIDTH),
        torch.nn.Tanh(),
        torch.nn.Linear(WIDTH, n_out),
    )


class Chart:
    """``E``: states to standardised codes, ``D``: back; fitted on ``states [N, d]``."""

    def __init__(self, states: torch.Tensor):
        gen = torch.Generator().manual_seed(0)
        torch.manual_seed(0)
        self.mu, self.sd = states.mean(0), states.std(0).clamp_min(1e-6)
        xs = (states - self.mu) / self.sd
        perm = torch.randperm(len(xs), generator=gen)
        held, train = xs[perm[: len(xs) // 10]], xs[perm[len(xs) // 10 :]]
        self.enc, self.dec = mlp(xs.shape[1], K), mlp(K, xs.shape[1])
        params = [*self.enc.parameters(), *self.dec.parameters()]
        opt = torch.optim.Adam(params, lr=1e-3)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, STEPS)
        with torch.enable_grad():
            for _ in range(STEPS):
                batch = train[torch.randint(len(train), (1024,), generator=gen)]
                loss = ((self.dec(self.enc(batch)) - batch) ** 2).mean()
                opt.zero_grad()
                loss.backward()
                opt.step()
                sched.step()
        with torch.no_grad():
            self.held_mse = float(((self.dec(self.enc(held)) - held) ** 2).mean())
            z = self.enc(xs)
            self.zmu, self.zsd = z.mean(0), z.std(0).clamp_min(1e-6)
        print(f"chart: k={K}, held-out reconstruction MSE {self.held_mse:.2e} (standardised states)", flush=True)

    def E(self, x: torch.Tensor) -> torch.Tensor:
        return (self.enc((x - self.mu) / self.sd) - self.zmu) / self.zsd

    def D(self, z: torch.Tensor) -> torch.Tensor:
        return self.dec(z * self.zsd + self.zmu) * self.sd + self.mu


class ChartUKF(UKFEstimator):
    """The UKF over codes; returns decoded states."""

    def __init__(self, ukf, to_frames, chart):
        super().__init__(ukf, torch.zeros(K), to_frames)
        self.chart = chart

    def start(self, y):
        return self.chart.D(super().start(y))

    def next(self, u, y):
        return self.chart.D(super().next(u, y))


def prepare(loop):
    nodes = loop.ssm.training_states()
    gen = torch.Generator().manual_seed(1)
    limit = max(abs(loop.settings.u_min), abs(loop.settings.u_max))
    states = excited_states(loop.f, nodes, ROLLOUT, limit, loop.frame_dt, gen)
    chart = Chart(states)
    with torch.no_grad():  # what the chart costs the planner: its angle readout on D(E(x)) against on x
        sample = states[torch.randperm(len(states), generator=gen)[:4096]]
        back = chart.D(chart.E(sample))
        gap = (loop.features(back) - loop.features(sample)).pow(2).mean().sqrt()
        still = torch.zeros(len(sample), 1)
        step = (loop.f(back, still) - loop.f(sample, still)).norm(dim=1).mean()
    print(f"chart: the planner's readout moves by {float(gap):.4f} (RMS), f's unforced step by {step:.4f}", flush=True)
    if S.get("chart_only"):  # the chart's quality alone
        ev = torch.linalg.eigvalsh(torch.cov(((states - chart.mu) / chart.sd).T)).flip(0)
        print("chart: the states' principal variances", [round(float(v), 4) for v in ev / ev.sum()], flush=True)
        sys.exit(0)
    g = loop.ssm.g
    loop._chart_ukf = UnscentedKalmanFilter(
        lambda z, u: chart.E(loop.f(chart.D(z), u)),
        lambda z: g(chart.D(z)),
        process_var=Q,
        measurement_var=VAR,
        init_var=1.0,
        iterations=int(S.get("iterations", 5)),
        state_dim=K,
    )
    loop._chart = chart


if __name__ == "__main__":
    try_estimator(prepare, lambda loop: ChartUKF(loop._chart_ukf, loop.to_frames, loop._chart), S, "chart_ukf_try")
