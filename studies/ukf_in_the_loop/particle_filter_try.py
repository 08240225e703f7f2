"""A bootstrap particle filter started on the shooting nodes in place of the UKF, in the closed loop: 20 episodes
from pretrained/pendulum_torque.ckpt (a feasibility check, not a library estimator). Run from the repository root:
    python studies/ukf_in_the_loop/particle_filter_try.py '{"n": 512, "var": 0.1, "q": 0.1}'
n particles drawn from the nodes, pixel variance var, process noise q times the nodes' spread per dimension."""

import json
import sys

import torch
from estimator_try import try_estimator

from ssm_ms.inference.particle import systematic_resample

S = json.loads(sys.argv[1]) if len(sys.argv) > 1 else {}
N, VAR, Q = S.get("n", 512), S.get("var", 0.1), S.get("q", 0.1)


class PFEstimator:
    def __init__(self, f, g, nodes, to_frames):
        self.f, self.g, self.nodes, self.to_frames = f, g, nodes, to_frames
        self.std = Q * nodes.std(0)
        self.gen = torch.Generator().manual_seed(0)

    def _weigh(self, y):
        b, p, d = self.x.shape
        yb = self.to_frames(y).reshape(b, -1)
        pred = self.g(self.x.reshape(b * p, d)).reshape(b, p, -1)
        logw = -0.5 * ((pred - yb[:, None]) ** 2).sum(-1) / VAR
        w = torch.softmax(logw, -1)
        mean = (w[..., None] * self.x).sum(1)
        idx = systematic_resample(w, self.gen)
        self.x = torch.gather(self.x, 1, idx[..., None].expand(-1, -1, d))
        return mean

    def start(self, y):
        idx = torch.randint(len(self.nodes), (len(y), N), generator=self.gen)
        self.x = self.nodes[idx]
        return self._weigh(y)

    def next(self, u, y):
        b, p, d = self.x.shape
        uu = u[:, None].expand(b, p, u.shape[-1]).reshape(b * p, -1)
        self.x = self.f(self.x.reshape(b * p, d), uu).reshape(b, p, d)
        self.x = self.x + self.std * torch.randn(self.x.shape, generator=self.gen)
        return self._weigh(y)


def prepare(loop):
    loop._nodes = loop.ssm.training_states()


if __name__ == "__main__":
    try_estimator(
        prepare, lambda loop: PFEstimator(loop.f, loop.ssm.g, loop._nodes, loop.to_frames), S, "particle_filter_try"
    )
