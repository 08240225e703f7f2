"""A moving-horizon estimate in place of the UKF in the closed loop: the state `window` frames back fitted through
f(x, u) and g to the frames since (Adam, warm-started from the last solution moved one step by f), the current state
f's roll-out from it; the first state the shooting node whose g(node) best matches the first frame. 20 episodes from
pretrained/pendulum_torque.ckpt (a feasibility check, not a library estimator). Run from the repository root:
    python studies/ukf_in_the_loop/moving_horizon_try.py '{"window": 8, "steps": 20, "lr": 0.05}'
With "solver": "lm" the window is fitted by Levenberg-Marquardt (Gauss-Newton steps on the frames' residuals, the
Jacobian by forward differences, "steps" iterations) in place of Adam; with "solver": "ms" every state of the window is
free (multiple shooting inside the estimator: the frames' squared error plus "gap" times |x[k+1] - f(x[k], u[k])|^2,
by "steps" Adam steps at "lr", warm-started from the last window's states), the current state the window's last.
With "diagnose": "<file.md>" it scores the estimates instead (studies/control_diagnosis's table: the angle error of
the estimate and of f's predictions from it, along the true-model controller's swing-ups)."""

import json
import sys

import torch
from estimator_try import try_estimator

S = json.loads(sys.argv[1]) if len(sys.argv) > 1 else {}
WINDOW, STEPS, LR = S.get("window", 8), S.get("steps", 20), S.get("lr", 0.05)
SOLVER, EPS, DAMPING = S.get("solver", "adam"), S.get("eps", 1e-3), S.get("damping", 1e-2)
ACCEPTED = [0, 0]  # lm: steps accepted, steps tried (over every episode and period)
GAP = S.get("gap", 100.0)  # ms: the weight of f's gaps against the frames' error (pixel variance / process variance)
PRIOR = S.get("prior", 0.0)  # lm: weight of the arrival cost |x - x_prior|^2 (x_prior: the last solution moved by f)


class MovingHorizon:
    def __init__(self, f, g, nodes, decoded, to_frames):
        self.f, self.g, self.nodes, self.decoded, self.to_frames = f, g, nodes, decoded, to_frames

    def _roll(self, x):
        states = [x]
        for u in self.us:
            states.append(self.f(states[-1], u))
        return states

    def _residuals(self, x, y):
        states = torch.stack(self._roll(x), 1)  # [B, k, d]
        b, k, d = states.shape
        r = self.g(states.reshape(b * k, d)).reshape(b, -1) - y
        return torch.cat([r, PRIOR**0.5 * (x - self.x0)], 1) if PRIOR else r

    @torch.no_grad()
    def _fit_lm(self):
        y = torch.stack(self.ys, 1).reshape(len(self.x0), -1)  # [B, k P]
        x = self.x0.clone()
        r = self._residuals(x, y)
        cost, damping = (r**2).sum(1), torch.full((len(x),), DAMPING)
        eye = torch.eye(x.shape[1])
        for _ in range(STEPS):
            jac = torch.stack([(self._residuals(x + EPS * e, y) - r) / EPS for e in eye], 2)  # [B, k P, d]
            a = jac.transpose(1, 2) @ jac
            grad = jac.transpose(1, 2) @ r.unsqueeze(-1)
            scaled = torch.diag_embed(torch.diagonal(a, dim1=1, dim2=2) + 1e-9)
            step = torch.linalg.solve(a + damping[:, None, None] * scaled, -grad).squeeze(-1)
            r_new = self._residuals(x + step, y)
            cost_new = (r_new**2).sum(1)
            better = cost_new < cost
            ACCEPTED[0] += int(better.sum())
            ACCEPTED[1] += len(better)
            x = torch.where(better[:, None], x + step, x)
            r = torch.where(better[:, None], r_new, r)
            cost = torch.where(better, cost_new, cost)
            damping = torch.where(better, damping / 3, damping * 5).clamp(1e-6, 1e6)
        self.x0 = x
        return self._roll(self.x0)[-1]

    def _fit_ms(self):
        y = torch.stack(self.ys, 1)  # [B, k, P]
        x = self.X.detach().clone().requires_grad_(True)  # [B, k, d]
        opt = torch.optim.Adam([x], lr=LR)
        b, k, d = x.shape
        u = torch.stack(self.us, 1).flatten(0, 1) if self.us else None  # [B (k - 1), ...]
        for _ in range(STEPS):
            with torch.enable_grad():
                loss = ((self.g(x.reshape(b * k, d)).reshape(b, k, -1) - y) ** 2).sum()
                if k > 1:
                    ahead = self.f(x[:, :-1].reshape(b * (k - 1), d), u).reshape(b, k - 1, d)
                    loss = loss + GAP * ((x[:, 1:] - ahead) ** 2).sum()
                opt.zero_grad()
                loss.backward()
            opt.step()
        self.X = x.detach()
        return self.X[:, -1]

    def _fit(self):
        if SOLVER == "lm":
            return self._fit_lm()
        if SOLVER == "ms":
            return self._fit_ms()
        x = self.x0.detach().clone().requires_grad_(True)
        opt = torch.optim.Adam([x], lr=LR)
        y = torch.stack(self.ys, 1)  # [B, k, P]
        for _ in range(STEPS):
            with torch.enable_grad():
                states = torch.stack(self._roll(x), 1)  # [B, k, d]
                b, k, d = states.shape
                pred = self.g(states.reshape(b * k, d)).reshape(b, k, -1)
                loss = ((pred - y) ** 2).sum()
                opt.zero_grad()
                loss.backward()
            opt.step()
        self.x0 = x.detach()
        with torch.no_grad():
            return self._roll(self.x0)[-1]

    def start(self, y):
        frames = self.to_frames(y).reshape(len(y), -1)
        self.ys, self.us = [frames], []
        self.x0 = self.nodes[torch.cdist(frames, self.decoded).argmin(1)]
        self.X = self.x0[:, None]
        return self._fit()

    def next(self, u, y):
        self.ys.append(self.to_frames(y).reshape(len(y), -1))
        self.us.append(u)
        with torch.no_grad():
            self.X = torch.cat([self.X, self.f(self.X[:, -1], u)[:, None]], 1)
        if len(self.ys) > WINDOW:
            with torch.no_grad():
                self.x0 = self.f(self.x0, self.us[0])
            self.ys, self.us, self.X = self.ys[1:], self.us[1:], self.X[:, 1:]
        return self._fit()


def prepare(loop):
    nodes = loop.ssm.training_states()
    with torch.no_grad():
        decoded = torch.cat([loop.ssm.g(c).reshape(len(c), -1) for c in nodes.split(1000)])
    loop._mhe = (nodes, decoded)


if __name__ == "__main__":
    try_estimator(
        prepare, lambda loop: MovingHorizon(loop.f, loop.ssm.g, *loop._mhe, loop.to_frames), S, "moving_horizon_try"
    )
    if SOLVER == "lm":
        print(f"lm steps accepted: {ACCEPTED[0]} of {ACCEPTED[1]}")
