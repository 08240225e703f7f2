"""The reference implementation's structure, written for timing it beside ssm-ms (not for training).

The structure is that of the paper's code (machines-in-motion/ssm_multiple_shooting, ``ssm_ms/ssm.py``,
``ssm_ms/pendulum.py``, ``ssm_ms/inference_tools/ukf.py``), re-written here so that the benchmarks can
run it in the same process family and on the same data as ours:

* SSM-LL transition: ``beta = softmax(MLP(x))``, the outer product ``x beta^T`` flattened to ``K d`` and
  one ``Linear(K d -> d, bias=False)``, residual;
* SSM-FC transition: residual MLP with three 512-wide ReLU layers;
* decoder: ``Linear(d -> 32*3*3)``, ReLU, NCHW ``ConvTranspose2d`` blocks with ``LayerNorm((C, H, W))``,
  sigmoid of the flattened image;
* ``loss_function``: the sub-trajectories stacked along the batch, ``g`` called once per time step on
  the ``B m`` states and the per-step losses summed (divided by ``n``); the gap is the mean squared
  difference between ``f^n`` of each node and the next node;
* Adam over ``f``, ``g`` and a dense node tensor ``[N_train, m, d]`` (rows picked by index);
* UKF: per trajectory ``scipy.linalg.sqrtm(d P)``, ``2d`` sigma points ``x +- columns``, ``f`` and ``g``
  called once per sigma point (each on the batch), dense ``inverse`` of the innovation covariance.

The process that runs these must not call ``ssm_ms.runtime.perf.configure_allocator`` (the reference runs with
glibc's default allocator): import nothing from ``ssm_ms`` here.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn


class RefLocallyLinear(nn.Module):
    """``x + Linear_{K d -> d}(vec(x beta(x)^T))``."""

    def __init__(self, d: int, k: int = 32, hidden: int = 1024):
        super().__init__()
        self.d, self.k = d, k
        self.alpha = nn.Sequential(nn.Linear(d, hidden), nn.ReLU(), nn.Linear(hidden, k), nn.Softmax(dim=1))
        self.matrix = nn.Linear(d * k, d, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        outer = x.unsqueeze(2) @ self.alpha(x).unsqueeze(1)  # [N, d, K]
        return x + self.matrix(outer.reshape(-1, self.k * self.d))


class RefFullyConnected(nn.Module):
    def __init__(self, d: int, hidden: int = 512, layers: int = 3):
        super().__init__()
        mods: list[nn.Module] = []
        width = d
        for _ in range(layers):
            mods += [nn.Linear(width, hidden), nn.ReLU()]
            width = hidden
        self.fc = nn.Sequential(*mods, nn.Linear(width, d))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.fc(x)


class RefDecoder(nn.Module):
    """The pendulum decoder in NCHW: 3x3 stem -> 11 -> 23 -> 24, flattened sigmoid output."""

    def __init__(self, d: int, image: int = 24, stem: int = 32):
        super().__init__()
        if image != 24:
            raise ValueError("the reference pendulum decoder makes 24x24 images")
        self.stem = stem
        self.fc_obs = nn.Linear(d, stem * 9)
        self.conv_layers = nn.Sequential(
            nn.ConvTranspose2d(stem, 16, 5, stride=3),
            nn.LayerNorm((16, 11, 11)),
            nn.ReLU(),
            nn.ConvTranspose2d(16, 12, 3, stride=2),
            nn.LayerNorm((12, 23, 23)),
            nn.ReLU(),
            nn.ConvTranspose2d(12, 1, 2, stride=1),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = F.relu(self.fc_obs(x)).view(-1, self.stem, 3, 3)
        return torch.sigmoid(self.conv_layers(h).view(len(x), -1))


class RefTrainer:
    """One optimizer step of the reference ``SSM.loss_function`` + Adam on a fixed batch."""

    def __init__(self, f: nn.Module, g: nn.Module, n_train: int, m: int, d: int, lr: float = 1e-3, device="cpu"):
        self.f, self.g, self.m = f.to(device), g.to(device), m
        self.nodes = (0.1 * torch.randn(n_train, m, d)).to(device).requires_grad_(True)
        self.optimizer = torch.optim.Adam([*f.parameters(), *g.parameters(), self.nodes], lr)

    def loss_function(self, index: np.ndarray, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``y [B, T, p]`` flat measurements of the trajectories ``index``."""
        n = y.shape[1] // self.m
        flat_y = torch.cat([y[:, i * n : (i + 1) * n] for i in range(self.m)])  # [m B, n, p], node-major
        node_of = np.repeat(np.arange(self.m), len(index))
        traj_of = np.tile(index, self.m)
        x = self.nodes[traj_of, node_of]
        score = F.mse_loss(self.g(x), flat_y[:, 0])
        for k in range(n - 1):
            x = self.f(x)
            score = score + F.mse_loss(self.g(x), flat_y[:, k + 1])
        if self.m > 1:
            x = self.f(x)
            keep = node_of < self.m - 1
            gap = F.mse_loss(x[keep], self.nodes[traj_of[keep], node_of[keep] + 1])
        else:
            gap = torch.tensor(0.0)
        return score / n, gap

    def step(self, index: np.ndarray, y: torch.Tensor, alpha: float = 1000.0) -> float:
        self.optimizer.zero_grad()
        fit, gap = self.loss_function(index, y)
        loss = fit + alpha * gap
        loss.backward()
        self.optimizer.step()
        return float(loss.detach())


def ref_ukf_step(f, g, x: torch.Tensor, p: np.ndarray, y: torch.Tensor, r: torch.Tensor, q: torch.Tensor):
    """One step of the reference UKF: ``x [B, d]``, ``p`` a NumPy ``[B, d, d]``, ``y [B, p]``.

    Returns ``(x, p, failed)``; ``failed`` when a matrix square root came out complex.
    """
    from scipy.linalg import sqrtm

    d = x.shape[1]
    roots = np.array([sqrtm(d * pi) for pi in p])
    if np.iscomplexobj(roots) and np.any(np.iscomplex(roots)):
        return x, p, True
    s = x.new_tensor(np.real(roots))
    xc = x.unsqueeze(1)
    sigma = torch.cat((xc + s, xc - s), dim=1)  # [B, 2d, d]: x +- rows of the root (symmetric)
    xs = x.new_zeros(sigma.shape)
    for i in range(sigma.shape[1]):
        xs[:, i] = f(sigma[:, i])
    x_mean = xs.mean(1, keepdim=True)
    ys = x.new_zeros(sigma.shape[0], sigma.shape[1], y.shape[1])
    for i in range(sigma.shape[1]):
        ys[:, i] = g(xs[:, i])
    y_mean = ys.mean(1, keepdim=True)
    dx, dy = xs - x_mean, ys - y_mean
    pxx = dx.transpose(1, 2) @ dx / (2 * d) + q
    pxy = dx.transpose(1, 2) @ dy / (2 * d)
    pyy = dy.transpose(1, 2) @ dy / (2 * d) + r
    gain = pxy @ torch.inverse(pyy)
    x_new = x_mean.squeeze(1) + (gain @ (y.unsqueeze(-1) - y_mean.transpose(1, 2))).squeeze(-1)
    p_new = pxx - gain @ pyy @ gain.transpose(1, 2)
    return x_new, p_new.cpu().numpy(), False


def ref_ukf(f, g, y: torch.Tensor, p0: float, r: float, q: float) -> torch.Tensor:
    """Filter ``y [B, T, p]`` from ``x0 = [y0, 0, ...]``, ``P0 = p0 I``: posterior means ``[B, T, d]``."""
    b, t, obs = y.shape
    d = f.d if hasattr(f, "d") else 3
    x = y.new_zeros(b, d)
    x[:, :obs] = y[:, 0]
    p = np.stack([p0 * np.eye(d)] * b)
    rr = y.new_tensor(r * np.eye(obs))
    qq = y.new_tensor(q * np.eye(d))
    means = y.new_zeros(b, t, d)
    for i in range(t):
        x, p, failed = ref_ukf_step(f, g, x, p, y[:, i], rr, qq)
        if failed:
            raise FloatingPointError(f"reference UKF: complex matrix square root at step {i}")
        means[:, i] = x
    return means
