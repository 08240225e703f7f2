"""The UKF with its mean moved onto the model's training states after each update, in the closed loop (a feasibility
check, not a library estimator). The posterior ``N(m, P)`` weighs the shooting nodes ``x_i`` by
``exp(-|L^-1 (x_i - m)|^2 / (2 s))`` (``L L^T = P``) and the mean becomes their weighted mean: the directions the frames
pin down (small variance) choose the nodes, the ones they leave open (the latent directions f's predictions depend on
and g does not show) take the nodes' values there. Run from the repository root:
    python studies/ukf_in_the_loop/manifold_try.py '{"s": 1.0, "episodes": 20}'
s widens the weights (s * P)."""

import json
import sys

import torch
from estimator_try import try_estimator

from ssm_ms.control.estimators import UKFEstimator

S = json.loads(sys.argv[1]) if len(sys.argv) > 1 else {}
SCALE = float(S.get("s", 1.0))


class ProjectedUKF(UKFEstimator):
    def __init__(self, ukf, prior, to_frames, nodes):
        super().__init__(ukf, prior, to_frames)
        self.nodes = nodes

    def _project(self) -> torch.Tensor:
        d = self.mean.shape[-1]
        eye = torch.eye(d, dtype=self.cov.dtype)
        chol = torch.linalg.cholesky(SCALE * self.cov + 1e-9 * eye)
        diff = (self.nodes[None] - self.mean[:, None]).transpose(-1, -2)  # [B, d, N]
        z = torch.linalg.solve_triangular(chol, diff, upper=False)
        w = torch.softmax(-0.5 * (z**2).sum(1), -1)  # [B, N]
        self.mean = w @ self.nodes
        return self.mean

    def start(self, y):
        super().start(y)
        return self._project()

    def next(self, u, y):
        super().next(u, y)
        return self._project()


def prepare(loop):
    loop._nodes = loop.ssm.training_states()


if __name__ == "__main__":
    try_estimator(
        prepare,
        lambda loop: ProjectedUKF(loop.ukf, loop.prior, loop.to_frames, loop._nodes),
        S,
        "manifold_try",
    )
