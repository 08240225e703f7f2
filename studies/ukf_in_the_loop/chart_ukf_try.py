"""The UKF run on a chart of the model's training states, in the closed loop: the feasibility check that became the
loop's ``estimator: {chart: {dims: k}}`` (ssm_ms/inference/chart.py, whose fit this script now calls with the seeds
and steps of the prototype it replaced, so the study's tables stand), kept for its options and diagnosis. An
autoencoder ``x ~ D(E(x))`` with a ``k``-dimensional code is fitted to the model's own states (every shooting node
rolled out under random torques, as the planner's angle readout is distilled); the UKF then estimates
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

from ssm_ms.control.estimators import ChartUKFEstimator
from ssm_ms.control.module import excited_states
from ssm_ms.inference.chart import ChartSettings, StateChart
from ssm_ms.inference.ukf import UnscentedKalmanFilter

S = json.loads(sys.argv[1]) if len(sys.argv) > 1 else {}
K, Q, VAR = int(S.get("k", 3)), float(S.get("q", 1e-3)), float(S.get("var", 0.1))
STEPS, ROLLOUT, WIDTH = int(S.get("steps", 4000)), int(S.get("rollout", 20)), int(S.get("width", 128))


def prepare(loop):
    nodes = loop.ssm.training_states()
    gen = torch.Generator().manual_seed(1)
    limit = max(abs(loop.settings.u_min), abs(loop.settings.u_max))
    states = excited_states(loop.f, nodes, ROLLOUT, limit, loop.frame_dt, gen)
    chart = StateChart.fit(states, ChartSettings(dims=K, steps=STEPS, width=WIDTH), seed=0)
    print(f"chart: k={K}, held-out reconstruction MSE {chart.held_error:.2e} (standardised states)", flush=True)
    with torch.no_grad():  # what the chart costs the planner: its angle readout on D(E(x)) against on x
        sample = states[torch.randperm(len(states), generator=gen)[:4096]]
        back = chart.decode(chart.encode(sample))
        gap = (loop.features(back) - loop.features(sample)).pow(2).mean().sqrt()
        still = torch.zeros(len(sample), 1)
        step = (loop.f(back, still) - loop.f(sample, still)).norm(dim=1).mean()
    print(f"chart: the planner's readout moves by {float(gap):.4f} (RMS), f's unforced step by {step:.4f}", flush=True)
    if S.get("chart_only"):  # the chart's quality alone
        ev = torch.linalg.eigvalsh(torch.cov(((states - chart.x_mean) / chart.x_std).T)).flip(0)
        print("chart: the states' principal variances", [round(float(v), 4) for v in ev / ev.sum()], flush=True)
        sys.exit(0)
    f, g = chart.pulled_back(loop.f, loop.ssm.g)
    loop._chart_ukf = UnscentedKalmanFilter(
        f,
        g,
        process_var=Q,
        measurement_var=VAR,
        init_var=1.0,
        iterations=int(S.get("iterations", 5)),
        state_dim=K,
    )
    loop._chart = chart


if __name__ == "__main__":
    try_estimator(
        prepare, lambda loop: ChartUKFEstimator(loop._chart_ukf, loop._chart, loop.to_frames), S, "chart_ukf_try"
    )
