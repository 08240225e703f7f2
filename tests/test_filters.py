"""UKF and particle filter against closed forms: the exact Kalman filter, quadrature, true Lorenz."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from ssm_ms.inference.particle import ParticleFilter, systematic_resample
from ssm_ms.inference.ukf import CovarianceJitterWarning, UnscentedKalmanFilter

F64 = torch.float64


# ------------------------------------------------------------------------------------------------
# reference: the exact Kalman filter, one trajectory at a time, plain loop
def kalman_filter(y, A, H, Q, R, x0, P0):
    """Posterior means [B, T, d] and covariances [B, T, d, d] of x[t+1] = A x[t] + w, y[t] = H x[t] + v."""
    means, covs = [], []
    for b in range(y.shape[0]):
        m, P = x0.clone(), P0.clone()
        mb, cb = [], []
        for t in range(y.shape[1]):
            S = H @ P @ H.T + R
            K = torch.linalg.solve(S, H @ P).T  # P H^T S^-1 (S, P symmetric)
            m = m + K @ (y[b, t] - H @ m)
            P = (torch.eye(len(m), dtype=F64) - K @ H) @ P
            mb.append(m)
            cb.append(P)
            m, P = A @ m, A @ P @ A.T + Q
        means.append(torch.stack(mb))
        covs.append(torch.stack(cb))
    return torch.stack(means), torch.stack(covs)


def linear_system(d, p, seed=0):
    gen = torch.Generator().manual_seed(seed)
    A = torch.randn(d, d, generator=gen, dtype=F64)
    A = 0.97 * A / torch.linalg.eigvals(A).abs().max()  # stable
    H = torch.randn(p, d, generator=gen, dtype=F64)
    f = nn.Linear(d, d, bias=False).double()
    g = nn.Linear(d, p, bias=False).double()
    with torch.no_grad():
        f.weight.copy_(A)
        g.weight.copy_(H)
    return A, H, f, g


def simulate(A, H, Q, R, x0, P0, B, T, seed=1):
    gen = torch.Generator().manual_seed(seed)
    d, p = A.shape[0], H.shape[0]
    lq, lr, lp = (torch.linalg.cholesky(M) for M in (Q, R, P0))
    x = x0 + torch.randn(B, d, generator=gen, dtype=F64) @ lp.T
    ys = []
    for _ in range(T):
        ys.append(x @ H.T + torch.randn(B, p, generator=gen, dtype=F64) @ lr.T)
        x = x @ A.T + torch.randn(B, d, generator=gen, dtype=F64) @ lq.T
    return torch.stack(ys, 1)


@pytest.mark.parametrize(
    "d, p, innovation, full_r, beta, g_known_linear",
    [
        (4, 2, "auto", False, 2.0, True),  # dense mode with an nn.Linear g: H P H^T, no sigma points
        (4, 2, "auto", False, 2.0, False),  # the same through sigma points
        (4, 2, "low_rank", True, 2.0, True),
        (2, 7, "auto", True, 2.0, True),
        (2, 7, "dense", False, 2.0, True),
        (2, 7, "dense", True, 2.0, False),
        (3, 9, "auto", False, 2.0, True),
        (3, 2, "auto", True, 0.0, True),  # cubature rule: the centre point is dropped
        (3, 2, "auto", True, 0.0, False),
        (3, 9, "auto", False, 0.0, True),
    ],
)
def test_ukf_equals_kalman_filter_on_linear_gaussian_system(d, p, innovation, full_r, beta, g_known_linear):
    A, H, f, g = linear_system(d, p)
    if not g_known_linear:
        g = g.forward  # a plain function: the filter cannot tell it is linear
    q_diag = [0.01 * (i + 1) for i in range(d)]
    Q = torch.diag(torch.tensor(q_diag, dtype=F64))
    if full_r:
        M = torch.randn(p, p, generator=torch.Generator().manual_seed(3), dtype=F64)
        R = 0.2 * M @ M.T / p + 0.3 * torch.eye(p, dtype=F64)
        r_arg = R.tolist()
    else:
        R = 0.4 * torch.eye(p, dtype=F64)
        r_arg = 0.4
    x0 = torch.linspace(-1, 1, d, dtype=F64)
    P0 = 0.1 * torch.eye(d, dtype=F64)
    y = simulate(A, H, Q, R, x0, P0, B=3, T=25)
    ukf = UnscentedKalmanFilter(
        f, g, process_var=q_diag, measurement_var=r_arg, init_var=0.1, innovation=innovation, beta=beta
    )
    means, covs = ukf.filter(y, x0=x0)
    ref_m, ref_c = kalman_filter(y, A, H, Q, R, x0, P0)
    assert means.shape == (3, 25, d) and covs.shape == (3, 25, d, d)
    torch.testing.assert_close(means, ref_m, rtol=0, atol=1e-9)
    torch.testing.assert_close(covs, ref_c, rtol=0, atol=1e-9)
    # the documented one-step prior for time T is the Kalman prediction
    m_next, c_next = ukf.predict(means[:, -1], covs[:, -1])
    torch.testing.assert_close(m_next, ref_m[:, -1] @ A.T, rtol=0, atol=1e-9)
    torch.testing.assert_close(c_next, A @ ref_c[:, -1] @ A.T + Q, rtol=0, atol=1e-9)


def iterated_reference(g, m0, P0, y, R, iterations):
    """The iterated posterior linearisation of one measurement, written plainly (dense p x p matrices, one
    trajectory, the default sigma points alpha=1, beta=2, kappa=0): g linearised by regression over the sigma points
    of the latest posterior, the prior updated with that line, its residual covariance added to R."""
    d = len(m0)
    wm = torch.tensor([0.0] + [0.5 / d] * (2 * d), dtype=F64)
    wc = wm.clone()
    wc[0] = 2.0
    m, P = m0, P0
    for _ in range(iterations):
        L = torch.linalg.cholesky(P)
        points = [m] + [m + math.sqrt(d) * L[:, i] for i in range(d)] + [m - math.sqrt(d) * L[:, i] for i in range(d)]
        Y = torch.stack([g(x[None])[0].reshape(-1) for x in points])
        ybar = (wm[:, None] * Y).sum(0)
        Pxy = sum(wc[i] * torch.outer(points[i] - m, Y[i] - ybar) for i in range(len(points)))
        Pyy = sum(wc[i] * torch.outer(Y[i] - ybar, Y[i] - ybar) for i in range(len(points)))
        H = torch.linalg.solve(P, Pxy).T
        c = ybar - H @ m
        S = H @ P0 @ H.T + (Pyy - H @ P @ H.T) + R
        K = torch.linalg.solve(S, H @ P0).T
        m, P = m0 + K @ (y - H @ m0 - c), P0 - K @ S @ K.T
    return m, P


def bump_camera(x, pixels=24, width=0.8):
    """A 1-D camera of a point at ``x [N, 1]`` (pixel units, 0 the middle): a Gaussian blot, ``[N, pixels]``."""
    centres = torch.arange(pixels, dtype=x.dtype) - pixels / 2
    return torch.exp(-0.5 * ((centres - x) / width) ** 2)


@pytest.mark.parametrize("iterations", [1, 2, 4])
def test_iterated_update_matches_the_plain_posterior_linearisation(iterations):
    gen = torch.Generator().manual_seed(0)
    W = torch.randn(16, 2, generator=gen, dtype=F64)

    def g(x):
        return torch.tanh(3 * x @ W.T + 0.1)  # 16 steep "pixels" of a 2-D state

    m0, P0 = torch.tensor([0.2, -0.4], dtype=F64), torch.tensor([[0.5, 0.1], [0.1, 0.3]], dtype=F64)
    y = g(torch.tensor([[0.9, -0.1]], dtype=F64))[0] + 0.05 * torch.randn(16, generator=gen, dtype=F64)
    r = [0.01 * (1 + i % 3) for i in range(16)]
    ukf = UnscentedKalmanFilter(lambda x: x, g, measurement_var=r, iterations=iterations)
    mean, cov = ukf.update(m0[None], P0[None], y[None])
    ref_m, ref_p = iterated_reference(g, m0, P0, y, torch.diag(torch.tensor(r, dtype=F64)), iterations)
    torch.testing.assert_close(mean[0], ref_m, rtol=0, atol=1e-9)
    torch.testing.assert_close(cov[0], ref_p, rtol=0, atol=1e-9)


def test_iterated_update_of_a_linear_g_is_the_kalman_filter():
    A, H, f, g = linear_system(2, 7)
    Q, R = 0.01 * torch.eye(2, dtype=F64), 0.4 * torch.eye(7, dtype=F64)
    x0, P0 = torch.tensor([0.5, -0.5], dtype=F64), 0.1 * torch.eye(2, dtype=F64)
    y = simulate(A, H, Q, R, x0, P0, B=3, T=20)
    ukf = UnscentedKalmanFilter(f, g.forward, process_var=0.01, measurement_var=0.4, init_var=0.1, iterations=3)
    means, covs = ukf.filter(y, x0=x0)
    ref_m, ref_c = kalman_filter(y, A, H, Q, R, x0, P0)
    torch.testing.assert_close(means, ref_m, rtol=0, atol=1e-9)
    torch.testing.assert_close(covs, ref_c, rtol=0, atol=1e-9)


def test_iterating_follows_a_sharp_camera_to_the_posterior():
    """A wide prior and a sharp, informative frame: the UKF's one update, linearised over the prior, lands far from
    the posterior (a grid's); iterating the linearisation over the posterior reaches it."""
    r = 0.01
    x_true, prior_std = 3.0, 2.0
    y = bump_camera(torch.tensor([[x_true]], dtype=F64))
    grid = torch.linspace(-10, 10, 200001, dtype=F64)
    log_post = -0.5 * ((bump_camera(grid[:, None]) - y) ** 2).sum(-1) / r - 0.5 * (grid / prior_std) ** 2
    post = torch.softmax(log_post, 0)
    post_mean = float((post * grid).sum())
    post_std = float((post * (grid - post_mean) ** 2).sum().sqrt())
    m0, P0 = torch.zeros(1, 1, dtype=F64), torch.full((1, 1, 1), prior_std**2, dtype=F64)
    errors, stds = {}, {}
    for k in (1, 8):
        ukf = UnscentedKalmanFilter(lambda x: x, bump_camera, measurement_var=r, iterations=k)
        mean, cov = ukf.update(m0, P0, y)
        errors[k], stds[k] = abs(float(mean) - post_mean), float(cov.sqrt())
    assert errors[1] > 10 * post_std  # the one update: lost
    assert errors[8] < 0.2 * post_std and 0.8 < stds[8] / post_std < 1.25  # iterated: the posterior and its width


@pytest.mark.parametrize("beta, points", [(2.0, 7), (0.0, 6)])
def test_one_batched_call_of_f_and_g_per_step(beta, points):
    calls = {"f": [], "g": []}

    def f(x):
        calls["f"].append(tuple(x.shape))
        return 0.9 * x

    def g(x):
        calls["g"].append(tuple(x.shape))
        return x[:, :2]

    UnscentedKalmanFilter(f, g, state_dim=3, beta=beta).filter(torch.randn(5, 8, 2, dtype=F64))
    assert calls["f"] == [(5 * points, 3)] * 7  # no prediction after the last step
    assert calls["g"] == [(1, 3)] + [(5 * points, 3)] * 8  # one shape probe, then one call per step


def test_ukf_image_shaped_measurement_and_float32():
    """obs_shape (1, 3, 3) is flattened inside; float32 agrees with the float64 Kalman filter."""
    d, p = 3, 9
    A, H, f, g_flat = linear_system(d, p, seed=5)
    g = nn.Sequential(g_flat, nn.Unflatten(1, (1, 3, 3)))
    Q, R = 1e-3 * torch.eye(d, dtype=F64), 0.5 * torch.eye(p, dtype=F64)
    P0 = 0.1 * torch.eye(d, dtype=F64)
    y = simulate(A, H, Q, R, torch.zeros(d, dtype=F64), P0, B=2, T=20)
    ref_m, ref_c = kalman_filter(y, A, H, Q, R, torch.zeros(d, dtype=F64), P0)
    ukf = UnscentedKalmanFilter(f.float(), g.float(), process_var=1e-3, measurement_var=0.5, state_dim=d)
    means, covs = ukf.filter(y.float().reshape(2, 20, 1, 3, 3))
    assert means.dtype == torch.float32
    torch.testing.assert_close(means.double(), ref_m, rtol=0, atol=1e-4)
    torch.testing.assert_close(covs.double(), ref_c, rtol=0, atol=1e-5)


def test_ukf_batch_equals_each_trajectory_alone():
    torch.manual_seed(0)
    f = nn.Sequential(nn.Linear(3, 16), nn.Tanh(), nn.Linear(16, 3)).double()
    g = nn.Sequential(nn.Linear(3, 2), nn.Sigmoid()).double()
    y = torch.rand(4, 12, 2, dtype=F64)
    x0 = torch.randn(4, 3, dtype=F64)
    ukf = UnscentedKalmanFilter(f, g, process_var=1e-2, measurement_var=0.1, state_dim=3)
    means, covs = ukf.filter(y, x0=x0)
    for b in range(4):
        m, c = ukf.filter(y[b : b + 1], x0=x0[b : b + 1])
        torch.testing.assert_close(means[b : b + 1], m, rtol=0, atol=1e-12)
        torch.testing.assert_close(covs[b : b + 1], c, rtol=0, atol=1e-12)


# ------------------------------------------------------------------------------------------------
# Lorenz: the true dynamics as f, x-component measured with the paper's noise
LORENZ_MEAN = torch.tensor([0.0, 0.0, 23.5], dtype=F64)
LORENZ_STD = torch.tensor([7.9, 9.0, 8.6], dtype=F64)


def lorenz_rk4(x, dt=0.005, sigma=10.0, rho=28.0, beta=8.0 / 3.0):
    def vf(s):
        a, b, c = s.unbind(-1)
        return torch.stack([sigma * (b - a), a * (rho - c) - b, a * b - beta * c], -1)

    k1 = vf(x)
    k2 = vf(x + 0.5 * dt * k1)
    k3 = vf(x + 0.5 * dt * k2)
    k4 = vf(x + dt * k3)
    return x + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)


def normalised_lorenz(z):
    return (lorenz_rk4(z * LORENZ_STD + LORENZ_MEAN) - LORENZ_MEAN) / LORENZ_STD


def lorenz_data(B, T, seed=0):
    gen = torch.Generator().manual_seed(seed)
    x = LORENZ_MEAN + LORENZ_STD * torch.randn(B, 3, generator=gen, dtype=F64)
    for _ in range(1000):  # onto the attractor
        x = lorenz_rk4(x)
    xs = []
    for _ in range(T):
        xs.append(x)
        x = lorenz_rk4(x)
    z = (torch.stack(xs, 1) - LORENZ_MEAN) / LORENZ_STD
    y = z[..., :1] + math.sqrt(0.5) * torch.randn(B, T, 1, generator=gen, dtype=F64)
    return z, y


def test_linear_g_is_not_evaluated_on_sigma_points_and_changes_nothing():
    """Projection / nn.Linear g: the update uses H directly; same result as sigma points through g."""
    from ssm_ms.nets.readout import Projection
    from ssm_ms.nets.transition import LocallyLinearTransition

    class CountingProjection(Projection):
        calls = 0

        def forward(self, x):
            CountingProjection.calls += 1
            return super().forward(x)

    torch.manual_seed(0)
    f = LocallyLinearTransition(3, n_matrices=4, hidden=16).double()
    y = torch.randn(4, 30, 2, dtype=F64)
    lin = nn.Linear(3, 2).double()  # with a bias: g(x) = H x + c
    for g in (CountingProjection([2, 0]), lin):
        CountingProjection.calls = 0
        fast = UnscentedKalmanFilter(f, g, process_var=1e-3).filter(y)
        if isinstance(g, CountingProjection):
            assert CountingProjection.calls == 1  # the shape check only
        slow = UnscentedKalmanFilter(f, g.forward, process_var=1e-3, state_dim=3).filter(y)
        if isinstance(g, CountingProjection):
            assert CountingProjection.calls == 1 + 1 + 30  # + the shape check and one call per update
        torch.testing.assert_close(fast.means, slow.means, rtol=0, atol=1e-10)
        torch.testing.assert_close(fast.covs, slow.covs, rtol=0, atol=1e-10)
    with pytest.raises(ValueError, match="g failed on a state of dimension 3"):
        UnscentedKalmanFilter(f, nn.Linear(4, 2).double()).filter(y)

    class InconsistentLinear(nn.Module):  # says H is 2 x 4, but reads 3 components
        def forward(self, x):
            return x[:, :2]

        def observation_matrix(self, d):
            return torch.zeros(2, 4)

    with pytest.raises(ValueError, match="linear with a \\[2, 4\\] matrix but states have 3"):
        UnscentedKalmanFilter(f, InconsistentLinear()).filter(y)


def test_projection_observation_matrix():
    from ssm_ms.nets.readout import Projection

    x = torch.randn(5, 4)
    proj = Projection([3, 1, 1])
    h = proj.observation_matrix(4)
    torch.testing.assert_close(x @ h.T, torch.stack([x[:, 3], x[:, 1], x[:, 1]], -1), rtol=0, atol=0)
    with pytest.raises(ValueError, match="state has 3"):
        proj.observation_matrix(3)


def test_autocast_runs_f_and_g_in_bfloat16_and_keeps_the_filter_in_float32():
    torch.manual_seed(0)
    f_net = nn.Sequential(nn.Linear(3, 64), nn.Tanh(), nn.Linear(64, 3))
    g_net = nn.Sequential(nn.Linear(3, 8), nn.Tanh(), nn.Linear(8, 2))
    seen = []

    def f(x):
        out = f_net(x)
        seen.append(out.dtype)
        return x + 0.1 * out

    z, _ = lorenz_data(B=3, T=200)
    y = (g_net(z.float()) + 0.1 * torch.randn(3, 200, 2)).detach()
    with torch.no_grad():
        full = UnscentedKalmanFilter(f, g_net, process_var=1e-3, state_dim=3).filter(y)
        assert set(seen) == {torch.float32}
        seen.clear()
        half = UnscentedKalmanFilter(f, g_net, process_var=1e-3, state_dim=3, autocast="bfloat16").filter(y)
    assert set(seen) == {torch.bfloat16}
    assert half.means.dtype == half.covs.dtype == torch.float32
    diff = (half.means - full.means).abs().max()
    assert 0 < diff < 0.05 * full.means.abs().max(), diff  # reduced precision, but the same estimates
    check_covariances(half.covs.double())

    seen.clear()
    pf_half = ParticleFilter(f, g_net, n_particles=30, seed=0, state_dim=3, autocast="bfloat16").filter(y)
    assert set(seen) == {torch.bfloat16} and pf_half.dtype == torch.float32  # (accuracy: the Kalman test)

    for cls in (UnscentedKalmanFilter, ParticleFilter):
        with pytest.raises(ValueError, match="autocast must be null"):
            cls(f, g_net, state_dim=3, autocast="fp8")
        with pytest.raises(ValueError, match=r"g must map \[N, d\] states to a tensor"):
            cls(f, lambda x: x.tolist(), state_dim=3, autocast="bfloat16").filter(y)


def test_ukf_tracks_unobserved_lorenz_components():
    z, y = lorenz_data(B=4, T=2000)
    ukf = UnscentedKalmanFilter(normalised_lorenz, lambda s: s[:, :1], state_dim=3)  # paper's defaults
    means, covs = ukf.filter(y)
    burn = 500
    rmse = (means[:, burn:] - z[:, burn:]).pow(2).mean(dim=(0, 1)).sqrt()
    spread = z[:, burn:].std(dim=(0, 1))  # RMSE of the trivial estimator (the mean)
    assert (rmse[1:] < 0.2 * spread[1:]).all(), f"y, z RMSE {rmse[1:].tolist()} vs std {spread[1:].tolist()}"
    assert rmse[0] < 0.2 * spread[0]
    check_covariances(covs)


def check_covariances(covs):
    torch.testing.assert_close(covs, covs.transpose(-1, -2), rtol=0, atol=0)
    assert torch.isfinite(covs).all()
    assert (torch.linalg.eigvalsh(covs) > 0).all()


def test_covariances_symmetric_positive_definite_nonlinear_float32():
    torch.manual_seed(1)
    f = nn.Sequential(nn.Linear(4, 32), nn.Tanh(), nn.Linear(32, 4))
    g = nn.Sequential(nn.Linear(4, 16), nn.Sigmoid(), nn.Unflatten(1, (1, 4, 4)))
    y = torch.rand(3, 30, 1, 4, 4)
    with torch.no_grad():
        _, covs = UnscentedKalmanFilter(f, g, state_dim=4).filter(y)
    check_covariances(covs.double())


# ------------------------------------------------------------------------------------------------
def test_gradients_reach_f_parameters_gradcheck():
    torch.manual_seed(0)
    y = torch.randn(2, 4, 1, dtype=F64)
    x0 = torch.randn(2, 2, dtype=F64)

    def run(weight, y, x0):
        f = lambda x: x + 0.1 * torch.tanh(x @ weight.T)  # noqa: E731
        g = lambda x: x[:, :1] ** 2 + x[:, 1:]  # noqa: E731
        ukf = UnscentedKalmanFilter(f, g, process_var=0.05, measurement_var=0.3, state_dim=2)
        means, covs = ukf.filter(y, x0=x0)
        return means, covs

    weight = torch.randn(2, 2, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(run, (weight, y.requires_grad_(), x0.requires_grad_()), eps=1e-6, atol=1e-6)


def test_gradients_low_rank_innovation_gradcheck():
    # p = 4 > 2d+1 = 3: the sigma-point-space (Woodbury) update, with a full measurement covariance
    torch.manual_seed(1)
    y = torch.randn(2, 3, 4, dtype=F64)
    proj = torch.randn(4, 1, dtype=F64)
    r = [[0.5, 0.1, 0.0, 0.0], [0.1, 0.5, 0.0, 0.0], [0.0, 0.0, 0.4, 0.0], [0.0, 0.0, 0.0, 0.6]]

    def run(weight, y):
        ukf = UnscentedKalmanFilter(
            lambda x: torch.sin(x * weight),
            lambda x: torch.tanh(x @ proj.T),
            process_var=0.05,
            measurement_var=r,
            state_dim=1,
        )
        assert ukf._setup(1, 4, F64, torch.device("cpu")).mode == "low_rank"
        return ukf.filter(y)

    weight = torch.tensor([1.3], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(run, (weight, y.requires_grad_()), eps=1e-6, atol=1e-6)


def test_gradients_flow_to_module_parameters():
    from ssm_ms.nets.transition import LocallyLinearTransition

    torch.manual_seed(0)
    f = LocallyLinearTransition(3, n_matrices=4, hidden=8)
    means, covs = UnscentedKalmanFilter(f, lambda x: x[:, :1]).filter(torch.randn(2, 6, 1))
    (means.square().sum() + covs.diagonal(dim1=-2, dim2=-1).sum()).backward()
    for name, prm in f.named_parameters():
        assert prm.grad is not None and torch.isfinite(prm.grad).all() and prm.grad.abs().sum() > 0, name


# ------------------------------------------------------------------------------------------------
def test_jitter_path_on_near_singular_covariance_warns():
    # f collapses the state onto a line and there is no process noise: the predicted covariance is
    # rank one, its Cholesky fails and the filter must add jitter, warn, and stay symmetric PSD.
    f = lambda x: x[:, :1].expand(-1, 3).clone()  # noqa: E731
    ukf = UnscentedKalmanFilter(f, lambda x: x[:, :1], process_var=0.0, measurement_var=0.5, state_dim=3)
    y = torch.randn(2, 5, 1, dtype=F64)
    with pytest.warns(CovarianceJitterWarning, match=r"first at step 1 \(prior, 2 trajectories\), largest jitter"):
        means, covs = ukf.filter(y)
    assert torch.isfinite(means).all()
    torch.testing.assert_close(covs, covs.transpose(-1, -2), rtol=0, atol=0)
    assert (torch.linalg.eigvalsh(covs) > -1e-12).all()


def test_jitter_goes_only_to_failing_trajectories():
    ukf = UnscentedKalmanFilter(lambda x: x, lambda x: x, state_dim=2)
    good = torch.tensor([[2.0, 0.5], [0.5, 1.0]], dtype=F64)
    singular = torch.tensor([[1.0, 1.0], [1.0, 1.0]], dtype=F64)
    chol = ukf._cholesky(torch.stack([good, singular, good]), "test", step=7)
    torch.testing.assert_close(chol[0], torch.linalg.cholesky(good), rtol=0, atol=0)
    torch.testing.assert_close(chol[2], torch.linalg.cholesky(good), rtol=0, atol=0)
    torch.testing.assert_close(chol[1] @ chol[1].T, singular, rtol=0, atol=1e-6)
    assert ukf._events and ukf._events[0][0] == 7 and ukf._events[0][3] == 1


def test_unrecoverable_covariance_warns_with_step():
    ukf = UnscentedKalmanFilter(lambda x: x, lambda x: x, state_dim=2, max_jitter_tries=2)
    nan = torch.full((1, 2, 2), float("nan"), dtype=F64)
    with pytest.warns(CovarianceJitterWarning, match=r"UKF step 3: .* jitter"):
        ukf._cholesky(nan, "posterior", step=3)


# ------------------------------------------------------------------------------------------------
def test_iterations_bad_values_and_modes_raise_clear_errors():
    with pytest.raises(ValueError, match="iterations must be a whole number >= 1"):
        UnscentedKalmanFilter(lambda x: x, lambda x: x, iterations=0)
    with pytest.raises(ValueError, match="iterations must be a whole number >= 1"):
        UnscentedKalmanFilter(lambda x: x, lambda x: x, iterations=1.5)
    ukf = UnscentedKalmanFilter(lambda x: x, lambda x: x[:, :1], iterations=2)  # p = 1: dense innovation
    with pytest.raises(ValueError, match="iterations > 1 needs innovation='low_rank'"):
        ukf.update(torch.zeros(1, 2, dtype=F64), torch.eye(2, dtype=F64)[None], torch.zeros(1, 1, dtype=F64))


def test_ukf_bad_inputs_raise_clear_errors():
    f = lambda x: x  # noqa: E731
    g = lambda x: x[:, :2]  # noqa: E731
    ukf = UnscentedKalmanFilter(f, g, state_dim=3)
    with pytest.raises(ValueError, match=r"shape \[2\].*shape \[3\]"):
        ukf.filter(torch.randn(2, 5, 3))
    with pytest.raises(ValueError, match=r"\[B, T, \*obs_shape\]"):
        ukf.filter(torch.randn(5, 2))
    with pytest.raises(ValueError, match="positive definite"):
        ukf.filter(torch.randn(2, 5, 2), P0=torch.diag(torch.tensor([1.0, -1.0, 1.0])))
    with pytest.raises(ValueError, match="symmetric"):
        ukf.filter(torch.randn(2, 5, 2), P0=torch.tensor([[1.0, 0.5, 0], [0, 1, 0], [0, 0, 1]]))
    with pytest.raises(ValueError, match="P0 must be"):
        ukf.filter(torch.randn(2, 5, 2), P0=torch.eye(3)[None].expand(3, 3, 3))
    with pytest.raises(ValueError, match="x0 must be"):
        ukf.filter(torch.randn(2, 5, 2), x0=torch.zeros(4, 3))
    with pytest.raises(ValueError, match="x0 has state dimension 4"):
        ukf.filter(torch.randn(2, 5, 2), x0=torch.zeros(4))
    with pytest.raises(ValueError, match="floating point"):
        ukf.filter(torch.zeros(2, 5, 2, dtype=torch.uint8))
    with pytest.raises(ValueError, match="measurement_var has 3 entries.*2 components"):
        UnscentedKalmanFilter(f, g, measurement_var=[1.0, 1.0, 1.0], state_dim=3).filter(torch.randn(2, 5, 2))
    with pytest.raises(ValueError, match="measurement_var must be positive"):
        UnscentedKalmanFilter(f, g, measurement_var=0.0, state_dim=3)
    with pytest.raises(ValueError, match="process_var must be non-negative"):
        UnscentedKalmanFilter(f, g, process_var=[-1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="positive semi-definite"):
        UnscentedKalmanFilter(f, g, process_var=[[1.0, 2.0], [2.0, 1.0]])
    with pytest.raises(ValueError, match="measurement_var must be positive definite"):
        UnscentedKalmanFilter(f, g, measurement_var=[[1.0, 0.0], [0.0, 0.0]], state_dim=3)
    with pytest.raises(ValueError, match="init_var has 2 entries per side but state_dim is 3"):
        UnscentedKalmanFilter(f, g, init_var=[1.0, 1.0], state_dim=3)
    with pytest.raises(ValueError, match="state dimension is unknown"):
        UnscentedKalmanFilter(f, g).filter(torch.randn(2, 5, 2))
    with pytest.raises(ValueError, match="non-negative covariance weights"):
        UnscentedKalmanFilter(f, g, state_dim=3, alpha=1e-3, innovation="low_rank").filter(torch.randn(2, 5, 2))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_ukf_on_cuda_matches_cpu():
    torch.manual_seed(0)
    f = nn.Sequential(nn.Linear(3, 16), nn.Tanh(), nn.Linear(16, 3)).double()
    g = nn.Sequential(nn.Linear(3, 20), nn.Sigmoid()).double()
    y = torch.rand(5, 10, 20, dtype=F64)
    ukf = UnscentedKalmanFilter(f, g, process_var=1e-3, state_dim=3)
    m_cpu, c_cpu = ukf.filter(y)
    f.cuda(), g.cuda()
    m_gpu, c_gpu = ukf.filter(y.cuda())
    assert m_gpu.is_cuda
    torch.testing.assert_close(m_gpu.cpu(), m_cpu, rtol=0, atol=1e-9)
    torch.testing.assert_close(c_gpu.cpu(), c_cpu, rtol=0, atol=1e-9)


# ------------------------------------------------------------------------------------------------
# particle filter
def test_systematic_resampling_counts_within_floor_and_ceil():
    gen = torch.Generator().manual_seed(0)
    n = 1000
    w = torch.rand(6, n, generator=gen, dtype=F64) ** 4
    w[0, :] = 0.0
    w[0, 17] = 1.0  # all mass on one particle
    w[1, ::2] = 0.0  # zero weights are never picked
    w = w / w.sum(-1, keepdim=True)
    idx = systematic_resample(w, gen)
    assert idx.shape == (6, n)
    counts = torch.stack([torch.bincount(row, minlength=n) for row in idx]).to(F64)
    expected = n * w
    assert (counts >= torch.floor(expected - 1e-9)).all() and (counts <= torch.ceil(expected + 1e-9)).all()
    assert (counts[1, ::2] == 0).all() and counts[0, 17] == n


def test_systematic_resampling_is_unbiased_over_offsets():
    w = torch.tensor([[0.05, 0.15, 0.3, 0.5]], dtype=F64).expand(4000, 4).contiguous()
    idx = systematic_resample(w, torch.Generator().manual_seed(1))
    freq = torch.bincount(idx.flatten(), minlength=4).to(F64) / idx.numel()
    torch.testing.assert_close(freq, w[0], rtol=0, atol=0.01)


@pytest.mark.parametrize("autocast", [None, "bfloat16"])
def test_particle_filter_matches_kalman_filter(autocast):
    d, p, B, T = 2, 1, 3, 12
    A, H, f, g = linear_system(d, p, seed=2)
    q, r = 0.05, 0.3
    Q, R = q * torch.eye(d, dtype=F64), r * torch.eye(p, dtype=F64)
    P0 = 0.1 * torch.eye(d, dtype=F64)
    y = simulate(A, H, Q, R, torch.zeros(d, dtype=F64), P0, B, T)
    ref_m, ref_c = kalman_filter(y, A, H, Q, R, torch.zeros(d, dtype=F64), P0)
    n = 20000
    if autocast:  # float32 filter, f and g in bfloat16: the estimates must stay as close
        f, g, y = f.float(), g.float(), y.float()
    pf = ParticleFilter(
        f,
        g,
        n_particles=n,
        state_dim=d,
        process_std=q**0.5,
        measurement_std=r**0.5,
        init_std=0.1**0.5,
        seed=0,
        autocast=autocast,
    )
    res = pf.filter(y, return_particles=True)
    assert res.means.dtype == y.dtype
    assert res.means.shape == (B, T, d) and res.ess.shape == (B, T)
    # Monte Carlo error of a weighted mean ~ posterior std / sqrt(ESS): with ESS >= 0.1 N = 2000 that is
    # 0.022 std per step; resampling carries earlier steps' error along (a few times more at most). So the
    # worst error must stay below 0.15 std (~7 single-step standard errors) and the RMS below 0.05 std.
    # (A 20% wrong measurement std already gives 0.3 std and 0.11 std.)
    assert (res.ess > 0.1 * n).all(), "too few effective particles for the tolerance below"
    err = (res.means.double() - ref_m).abs() / ref_c.diagonal(dim1=-2, dim2=-1).sqrt()
    rms = err.pow(2).mean().sqrt()
    assert err.max() < 0.15 and rms < 0.05, f"max {err.max():.3f}, RMS {rms:.3f} posterior std"
    # the returned last-step particles and weights carry the last posterior
    torch.testing.assert_close(torch.einsum("bp,bpd->bd", res.weights, res.particles), res.means[:, -1])


def test_particle_filter_bernoulli_likelihood_matches_quadrature():
    # one step, 1-D state, 16-pixel "image" decoder: posterior mean by quadrature on a grid
    w = torch.linspace(-2, 2, 16, dtype=F64)
    b = torch.linspace(0.5, -0.5, 16, dtype=F64)
    g = lambda x: torch.sigmoid(x * w + b).reshape(-1, 1, 4, 4)  # noqa: E731
    x_true = torch.tensor([[0.6], [-0.3]], dtype=F64)
    y = g(x_true).reshape(2, 1, 1, 4, 4)  # soft targets in [0, 1]
    grid = torch.linspace(-4, 4, 20001, dtype=F64)
    prob = g(grid[:, None]).reshape(-1, 16)
    expected = []
    for k in range(2):
        yk = y[k, 0].reshape(16)
        logp = (yk * prob.log() + (1 - yk) * (1 - prob).log()).sum(-1) - 0.5 * grid**2 / 0.1
        post = torch.softmax(logp, 0)
        expected.append((post * grid).sum())
    pf = ParticleFilter(lambda x: x, g, n_particles=20000, likelihood="bernoulli", state_dim=1, seed=0)
    res = pf.filter(y, return_particles=True)
    post_std = 0.1**0.5
    tol = 5 * post_std / res.ess[:, 0].sqrt()
    assert ((res.means[:, 0, 0] - torch.stack(expected)).abs() < tol).all()


def test_particle_filter_reproducible_with_generator_and_seed():
    A, H, f, g = linear_system(2, 1)
    y = torch.randn(2, 6, 1, dtype=F64)
    pf = ParticleFilter(f, g, n_particles=200, state_dim=2, resample_threshold=1.0)
    a = pf.filter(y, generator=torch.Generator().manual_seed(3))
    b = pf.filter(y, generator=torch.Generator().manual_seed(3))
    c = pf.filter(y, generator=torch.Generator().manual_seed(4))
    assert torch.equal(a, b) and not torch.equal(a, c)
    seeded = ParticleFilter(f, g, n_particles=200, state_dim=2, seed=9)
    assert torch.equal(seeded.filter(y), seeded.filter(y))


def test_particle_filter_bad_inputs():
    g = lambda x: x[:, :1]  # noqa: E731
    pf = ParticleFilter(lambda x: x, g, n_particles=10, state_dim=2)
    with pytest.raises(ValueError, match=r"shape \[1\].*shape \[3\]"):
        pf.filter(torch.randn(2, 4, 3))
    with pytest.raises(ValueError, match=r"\[B, T, \*obs_shape\]"):
        pf.filter(torch.randn(4, 1))
    with pytest.raises(ValueError, match="x0 must be"):
        pf.filter(torch.randn(2, 4, 1), x0=torch.zeros(3, 2))
    with pytest.raises(ValueError, match=r"measurements in \[0, 1\]"):
        ParticleFilter(lambda x: x, torch.sigmoid, likelihood="bernoulli", state_dim=1).filter(torch.randn(1, 3, 1))
    with pytest.raises(ValueError, match="probabilities"):
        ParticleFilter(lambda x: x, lambda x: x * 10, likelihood="bernoulli", state_dim=1, seed=0).filter(
            torch.rand(1, 3, 1)
        )
    with pytest.raises(ValueError, match="likelihood must be"):
        ParticleFilter(lambda x: x, g, likelihood="poisson")
    with pytest.raises(ValueError, match="measurement_std must be a positive"):
        ParticleFilter(lambda x: x, g, measurement_std=-1.0)
    with pytest.raises(ValueError, match="resample_threshold"):
        ParticleFilter(lambda x: x, g, resample_threshold=2.0)
    with pytest.raises(ValueError, match=r"systematic|weights must be \[B, P\]"):
        systematic_resample(torch.ones(5))
