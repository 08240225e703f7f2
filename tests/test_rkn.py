"""Recurrent Kalman Network against dense Kalman algebra, hand-written loops and tiny training runs."""

from __future__ import annotations

import math

import pytest
import torch

from ssm_ms.baselines.common import SequenceOutput
from ssm_ms.baselines.rkn import (
    FactorizedCovariance,
    RecurrentKalmanNetwork,
    RKNTransition,
    rkn_predict,
    rkn_update,
)

F64 = torch.float64


@pytest.fixture(autouse=True)
def one_thread():
    """The filter loop is many tiny ops: one thread is much faster than two on a busy machine."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


# ------------------------------------------------------------------------------------------------
# dense references
def dense_cov(cov: FactorizedCovariance, b: int) -> torch.Tensor:
    """The full ``2m x 2m`` covariance of sample ``b``."""
    u, low, s = (torch.diag(x[b]) for x in cov)
    return torch.cat([torch.cat([u, s], 1), torch.cat([s, low], 1)], 0)


def blocks(p: torch.Tensor, m: int):
    return p[:m, :m], p[m:, m:], p[m:, :m], p[:m, m:]


def random_state(batch: int, m: int, seed: int):
    gen = torch.Generator().manual_seed(seed)
    mean = torch.randn(batch, 2 * m, generator=gen, dtype=F64)
    upper = 0.1 + torch.rand(batch, m, generator=gen, dtype=F64) * 3
    lower = 0.1 + torch.rand(batch, m, generator=gen, dtype=F64) * 3
    corr = torch.rand(batch, m, generator=gen, dtype=F64) * 1.8 - 0.9  # |corr| < 1: positive definite
    side = corr * (upper * lower).sqrt()
    return mean, FactorizedCovariance(upper, lower, side), gen


def off_diagonal(x: torch.Tensor) -> torch.Tensor:
    return x - torch.diag(torch.diagonal(x))


# ------------------------------------------------------------------------------------------------
def test_update_is_the_exact_kalman_update():
    batch, m = 5, 6
    mean, cov, gen = random_state(batch, m, seed=0)
    w = torch.randn(batch, m, generator=gen, dtype=F64)
    w_var = 0.05 + torch.rand(batch, m, generator=gen, dtype=F64)
    new_mean, new_cov = rkn_update(mean, cov, w, w_var)
    h = torch.cat([torch.eye(m, dtype=F64), torch.zeros(m, m, dtype=F64)], 1)
    for b in range(batch):
        p = dense_cov(cov, b)
        s = h @ p @ h.T + torch.diag(w_var[b])
        k = p @ h.T @ torch.linalg.inv(s)
        ref_mean = mean[b] + k @ (w[b] - h @ mean[b])
        ref_p = (torch.eye(2 * m, dtype=F64) - k @ h) @ p
        torch.testing.assert_close(new_mean[b], ref_mean, rtol=0, atol=1e-10)
        uu, ll, ls, us = blocks(ref_p, m)
        torch.testing.assert_close(new_cov.upper[b], torch.diagonal(uu), rtol=0, atol=1e-10)
        torch.testing.assert_close(new_cov.lower[b], torch.diagonal(ll), rtol=0, atol=1e-10)
        torch.testing.assert_close(new_cov.side[b], torch.diagonal(ls), rtol=0, atol=1e-10)
        torch.testing.assert_close(new_cov.side[b], torch.diagonal(us), rtol=0, atol=1e-10)
        for block in (uu, ll, ls, us):  # the posterior keeps the structure: the factorisation is exact
            assert off_diagonal(block).abs().max() < 1e-12


def test_update_skips_invalid_samples_exactly():
    batch, m = 6, 4
    mean, cov, gen = random_state(batch, m, seed=1)
    w = torch.randn(batch, m, generator=gen, dtype=F64)
    w_var = 0.05 + torch.rand(batch, m, generator=gen, dtype=F64)
    valid = torch.tensor([True, False, True, False, False, True])
    new_mean, new_cov = rkn_update(mean, cov, w, w_var, valid)
    all_mean, all_cov = rkn_update(mean, cov, w, w_var)
    assert torch.equal(new_mean[~valid], mean[~valid])
    assert torch.equal(new_mean[valid], all_mean[valid])
    for new, old, full in zip(new_cov, cov, all_cov):
        assert torch.equal(new[~valid], old[~valid])
        assert torch.equal(new[valid], full[valid])
    # garbage at invalid samples reaches neither the result nor the gradients
    w_bad = w.clone().requires_grad_(True)
    with torch.no_grad():
        w_bad[~valid] = float("nan")
    out_mean, out_cov = rkn_update(mean, cov, w_bad, w_var, valid)
    assert torch.equal(out_mean, new_mean)
    (out_mean.sum() + out_cov.upper.sum()).backward()
    assert torch.isfinite(w_bad.grad).all() and (w_bad.grad[~valid] == 0).all()


def test_predict_matches_dense_a_p_at_plus_q():
    batch, m, bandwidth = 4, 7, 2
    mean, cov, gen = random_state(batch, m, seed=2)
    idx = torch.arange(m)
    band = ((idx[:, None] - idx[None, :]).abs() <= bandwidth).to(F64)
    a11, a12, a21, a22 = (torch.randn(batch, m, m, generator=gen, dtype=F64) * band for _ in range(4))
    q_u = 0.01 + torch.rand(m, generator=gen, dtype=F64)
    q_l = 0.01 + torch.rand(m, generator=gen, dtype=F64)
    new_mean, new_cov = rkn_predict(mean, cov, a11, a12, a21, a22, q_u, q_l)
    for b in range(batch):
        a = torch.cat([torch.cat([a11[b], a12[b]], 1), torch.cat([a21[b], a22[b]], 1)], 0)
        ref_p = a @ dense_cov(cov, b) @ a.T + torch.diag(torch.cat([q_u, q_l]))
        torch.testing.assert_close(new_mean[b], a @ mean[b], rtol=0, atol=1e-10)
        uu, ll, ls, us = blocks(ref_p, m)
        torch.testing.assert_close(new_cov.upper[b], torch.diagonal(uu), rtol=0, atol=1e-10)
        torch.testing.assert_close(new_cov.lower[b], torch.diagonal(ll), rtol=0, atol=1e-10)
        torch.testing.assert_close(new_cov.side[b], torch.diagonal(ls), rtol=0, atol=1e-10)


def test_transition_mixes_band_basis_by_softmax_of_the_mean():
    torch.manual_seed(0)
    m, k, bw = 5, 4, 1
    trans = RKNTransition(m, n_basis=k, bandwidth=bw, coeff_hidden=(8,)).double()
    mean, cov, _ = random_state(3, m, seed=3)
    # initialisation of the RKN code: A = [[I, 0.2 I], [-0.2 I, I]] whatever the coefficients
    eye = torch.eye(m, dtype=F64)
    for got, ref in zip(trans.transition_matrices(mean), (eye, 0.2 * eye, -0.2 * eye, eye)):
        torch.testing.assert_close(got, ref.expand(3, m, m), rtol=0, atol=1e-7)  # initialised in float32
    q0 = torch.cat(trans.noise())
    torch.testing.assert_close(q0, torch.full((2 * m,), 0.1, dtype=F64), rtol=0, atol=1e-7)
    # perturb every raw parameter, then rebuild A by hand: alpha = softmax(net(z)), A = sum alpha_k band(A_k)
    with torch.no_grad():
        for p in trans.parameters():
            p.add_(0.3 * torch.randn_like(p))
    net = trans.coefficient_net[0]
    hidden = torch.tanh(mean @ net[0].weight.T + net[0].bias)
    alpha = torch.softmax(hidden @ net[2].weight.T + net[2].bias, dim=-1)
    torch.testing.assert_close(alpha.sum(-1), torch.ones(3, dtype=F64))
    band = torch.tensor([[float(abs(i - j) <= bw) for j in range(m)] for i in range(m)], dtype=F64)
    raw = (trans.b11, trans.b12, trans.b21, trans.b22)
    identity = (eye, 0 * eye, 0 * eye, eye)
    got = trans.transition_matrices(mean)
    for blk in range(4):
        for b in range(3):
            ref = identity[blk] + sum(alpha[b, j] * raw[blk][j] * band for j in range(k))
            torch.testing.assert_close(got[blk][b], ref, rtol=0, atol=1e-12)
    new_mean, new_cov = trans(mean, cov)
    ref_mean, ref_cov = rkn_predict(mean, cov, *got, *trans.noise())
    torch.testing.assert_close(new_mean, ref_mean, rtol=0, atol=0)
    assert all(torch.equal(x, y) for x, y in zip(new_cov, ref_cov))
    assert all((q > 0).all() for q in trans.noise())


def test_band_structure_survives_optimiser_steps():
    torch.manual_seed(0)
    m, bw = 6, 1
    net = RecurrentKalmanNetwork([3], latent_state_dim=2 * m, n_basis=3, bandwidth=bw).double()
    trans = net.transition
    outside = torch.tensor([[abs(i - j) > bw for j in range(m)] for i in range(m)])
    before = [p.detach().clone() for p in trans.basis()]
    opt = torch.optim.Adam(net.parameters(), lr=0.05)
    y = torch.randn(4, 6, 3, dtype=F64)
    for _ in range(3):
        opt.zero_grad()
        out = net(y)
        (((out.mean - y) ** 2) / out.var + out.var.log()).mean().backward()
        opt.step()
    after = trans.basis()
    eye = torch.eye(m, dtype=F64)
    for blk, (b0, b1) in enumerate(zip(before, after)):
        assert (b1[:, outside] == 0).all(), f"block {blk} has entries outside the band"
        assert not torch.equal(b0, b1), f"block {blk} did not train"
    mean = torch.randn(5, 2 * m, dtype=F64)
    for blk, a in enumerate(trans.transition_matrices(mean)):
        dev = a - eye if blk in (0, 3) else a
        assert (dev[:, outside] == 0).all()


# ------------------------------------------------------------------------------------------------
def dense_transition_loop(net: RecurrentKalmanNetwork, batch: int, steps: int):
    """Pure predictions from the initial state with dense matrices: means [B, T, 2m], dense covs [B, T, 2m, 2m]."""
    m = net.latent_obs_dim
    mean = torch.zeros(batch, 2 * m, dtype=F64)
    p = (net.initial_cov * torch.eye(2 * m, dtype=F64)).expand(batch, 2 * m, 2 * m)
    q = torch.diag(torch.cat(net.transition.noise()))
    means, covs = [], []
    for _ in range(steps):
        means.append(mean)
        covs.append(p)
        a11, a12, a21, a22 = net.transition.transition_matrices(mean)
        a = torch.cat([torch.cat([a11, a12], 2), torch.cat([a21, a22], 2)], 1)
        mean = (a @ mean.unsqueeze(-1)).squeeze(-1)
        # the RKN keeps only the diagonals of the blocks: do the same to the dense prior
        full = a @ p @ a.transpose(1, 2) + q
        keep = torch.zeros_like(full)
        for blk in (
            (slice(0, m), slice(0, m)),
            (slice(m, None), slice(m, None)),
            (slice(m, None), slice(0, m)),
            (slice(0, m), slice(m, None)),
        ):
            keep[:, blk[0], blk[1]] = torch.diag_embed(torch.diagonal(full[:, blk[0], blk[1]], dim1=1, dim2=2))
        p = keep
    return torch.stack(means, 1), torch.stack(covs, 1)


def test_unobserved_sequence_is_pure_prediction():
    torch.manual_seed(1)
    net = RecurrentKalmanNetwork([2], latent_state_dim=8, n_basis=3, coeff_hidden=(6,)).double()
    with torch.no_grad():
        for p in net.transition.parameters():
            p.add_(0.2 * torch.randn_like(p))
    # from the zero initial mean the means stay 0 (A z = 0); the covariances follow A(0) Sigma A(0)^T + Q
    batch, steps = 3, 7
    y = torch.randn(batch, steps, 2, dtype=F64)
    observed = torch.zeros(batch, steps, dtype=torch.bool)
    res = net.filter(y, observed)
    ref_means, ref_covs = dense_transition_loop(net, batch, steps)
    m = net.latent_obs_dim
    torch.testing.assert_close(res.means, ref_means, rtol=0, atol=1e-12)
    diag = torch.diagonal(ref_covs, dim1=-2, dim2=-1)  # [B, T, 2m]
    side = torch.diagonal(ref_covs[..., m:, :m], dim1=-2, dim2=-1)
    torch.testing.assert_close(res.covs.upper, diag[..., :m], rtol=1e-12, atol=1e-10)
    torch.testing.assert_close(res.covs.lower, diag[..., m:], rtol=1e-12, atol=1e-10)
    torch.testing.assert_close(res.covs.side, side, rtol=1e-12, atol=1e-10)
    assert side[:, 1:].abs().min() > 0  # the transitions do create cross-covariance
    # y changed nothing
    res2 = net.filter(torch.randn_like(y) * 100, observed)
    assert torch.equal(res.means, res2.means)


def test_pure_prediction_from_a_nonzero_state():
    """One observed first frame gives a nonzero posterior; the rest must be the hand-written transitions."""
    torch.manual_seed(2)
    net = RecurrentKalmanNetwork([3], latent_state_dim=6, n_basis=4).double()
    with torch.no_grad():
        for p in net.transition.parameters():
            p.add_(0.2 * torch.randn_like(p))
    batch, steps = 2, 6
    y = torch.randn(batch, steps, 3, dtype=F64)
    observed = torch.zeros(batch, steps, dtype=torch.bool)
    observed[:, 0] = True
    res = net.filter(y, observed)
    w, w_var = net.encode(y[:, 0])
    mean, cov = net.initial_state(batch)
    mean, cov = rkn_update(mean, cov, w, w_var)
    torch.testing.assert_close(res.means[:, 0], mean, rtol=0, atol=1e-12)
    for t in range(1, steps):
        a11, a12, a21, a22 = net.transition.transition_matrices(mean)
        a = torch.cat([torch.cat([a11, a12], 2), torch.cat([a21, a22], 2)], 1)
        mean = (a @ mean.unsqueeze(-1)).squeeze(-1)
        torch.testing.assert_close(res.means[:, t], mean, rtol=0, atol=1e-12)
        mean = res.means[:, t]  # follow the filter's own state to keep the comparison per step


def test_unobserved_values_change_nothing():
    torch.manual_seed(3)
    for obs_shape, kwargs in (([2], {}), ([1, 24, 24], {"latent_state_dim": 8, "n_basis": 3})):
        net = RecurrentKalmanNetwork(obs_shape, **kwargs)
        batch, steps = 3, 6
        gen = torch.Generator().manual_seed(0)
        y = torch.rand(batch, steps, *obs_shape, generator=gen)
        observed = torch.rand(batch, steps, generator=gen) < 0.5
        observed[:, 0] = True
        out = net(y, observed)
        y2 = torch.where(observed.view(batch, steps, *[1] * len(obs_shape)), y, torch.randn_like(y) * 10)
        out2 = net(y2, observed)
        assert torch.equal(out.mean, out2.mean)
        if out.var is not None:
            assert torch.equal(out.var, out2.var)
        # NaN at unobserved steps: same output, finite gradients
        y3 = torch.where(observed.view(batch, steps, *[1] * len(obs_shape)), y, torch.full_like(y, float("nan")))
        out3 = net(y3, observed)
        assert torch.equal(out.mean, out3.mean)
        out3.mean.sum().backward()
        assert all(torch.isfinite(p.grad).all() for p in net.parameters() if p.grad is not None)
        # observed values do matter
        y4 = y.clone()
        y4[:, 0] += 1.0
        assert not torch.equal(net(y4, observed).mean, out.mean)


def test_output_contract_and_causality():
    torch.manual_seed(4)
    net = RecurrentKalmanNetwork([1, 24, 24], latent_state_dim=8, n_basis=3)
    y = torch.rand(2, 5, 1, 24, 24)
    out = net(y, torch.ones(2, 5, dtype=torch.bool))
    assert isinstance(out, SequenceOutput) and out.var is None
    assert out.mean.shape == y.shape and (out.mean >= 0).all() and (out.mean <= 1).all()
    assert torch.equal(net(y).mean, out.mean)  # observed defaults to all True
    y2 = y.clone()
    y2[:, 3:] = torch.rand(2, 2, 1, 24, 24)
    torch.testing.assert_close(net(y2).mean[:, :3], out.mean[:, :3], rtol=0, atol=0)  # causal
    vec = RecurrentKalmanNetwork([3])
    res = vec.filter(torch.randn(4, 5, 3))
    assert res.means.shape == (4, 5, 30) and all(c.shape == (4, 5, 15) for c in res.covs)
    out = vec(torch.randn(4, 5, 3))
    assert out.mean.shape == out.var.shape == (4, 5, 3) and (out.var > 0).all()
    w, _ = vec.encode(torch.randn(7, 3))
    torch.testing.assert_close(w.norm(dim=-1), torch.ones(7))


# ------------------------------------------------------------------------------------------------
def train(net, y, observed, loss_fn, steps, lr):
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    losses = []
    for _ in range(steps):
        opt.zero_grad()
        loss = loss_fn(net(y, observed), y, observed)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 5.0)
        opt.step()
        losses.append(loss.item())
    with torch.no_grad():
        losses.append(loss_fn(net(y, observed), y, observed).item())
    return losses


def test_learns_noisy_sines_with_gaussian_nll():
    torch.manual_seed(0)
    gen = torch.Generator().manual_seed(0)
    batch, steps = 16, 25
    phase = torch.rand(batch, 1, generator=gen) * 2 * math.pi + 0.3 * torch.arange(steps)
    y = torch.stack([torch.sin(phase), torch.cos(phase)], -1) + 0.05 * torch.randn(batch, steps, 2, generator=gen)
    observed = torch.ones(batch, steps, dtype=torch.bool)
    observed[:, 15:] = False  # also learn to predict
    net = RecurrentKalmanNetwork([2], latent_state_dim=8, n_basis=4, decoder_hidden=(32,))

    def nll(out, y, observed):
        return 0.5 * (out.var.log() + (y - out.mean) ** 2 / out.var).mean()

    def mse(out, y, observed):
        return ((y - out.mean) ** 2).mean()

    with torch.no_grad():
        mse0 = mse(net(y, observed), y, observed).item()
    losses = train(net, y, observed, nll, steps=60, lr=1e-2)
    with torch.no_grad():
        mse1 = mse(net(y, observed), y, observed).item()
    assert losses[-1] < losses[0] - 0.3, losses
    assert mse1 < 0.7 * mse0, (mse0, mse1)


def moving_blob(batch: int, steps: int, size: int = 24, seed: int = 0) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    angle = torch.rand(batch, 1, generator=gen) * 2 * math.pi + 0.4 * torch.arange(steps)
    cx, cy = size / 2 + 6 * torch.cos(angle), size / 2 + 6 * torch.sin(angle)
    grid = torch.arange(size, dtype=torch.float32)
    d2 = (grid.view(1, 1, 1, size) - cx[..., None, None]) ** 2 + (grid.view(1, 1, size, 1) - cy[..., None, None]) ** 2
    return torch.exp(-d2 / 8.0).unsqueeze(2)  # [B, T, 1, size, size]


def test_learns_moving_blob_images_with_bce():
    torch.manual_seed(0)
    y = moving_blob(4, 8)
    observed = torch.ones(4, 8, dtype=torch.bool)
    net = RecurrentKalmanNetwork([1, 24, 24], latent_state_dim=8, n_basis=3)

    def bce(out, y, observed):
        return torch.nn.functional.binary_cross_entropy(out.mean, y)

    losses = train(net, y, observed, bce, steps=25, lr=3e-3)
    assert losses[-1] < 0.7 * losses[0], losses


# ------------------------------------------------------------------------------------------------
def test_bad_input():
    with pytest.raises(ValueError, match=r"latent_state_dim must be even.*use 14 or 16"):
        RecurrentKalmanNetwork([3], latent_state_dim=15)
    with pytest.raises(ValueError, match=r"'quad'.*\[1, 24, 24\].*\[3, 24, 24\].*no ConvDecoder preset"):
        RecurrentKalmanNetwork([3, 24, 24], latent_state_dim=8, n_basis=2, decoder_preset="quad")
    with pytest.raises(ValueError, match="give encoder_preset"):
        RecurrentKalmanNetwork([1, 24, 30], latent_state_dim=8)
    with pytest.raises(ValueError, match="obs_shape"):
        RecurrentKalmanNetwork([4, 4])
    net = RecurrentKalmanNetwork([3], latent_state_dim=4, n_basis=2)
    with pytest.raises(ValueError, match=r"y must be \[B, T, 3\].*got \[2, 5, 4\]"):
        net(torch.randn(2, 5, 4))
    with pytest.raises(ValueError, match=r"y must be"):
        net(torch.randn(5, 3))
    with pytest.raises(ValueError, match=r"observed must be \[B, T\] = \[2, 5\].*got \[2, 4\]"):
        net(torch.randn(2, 5, 3), torch.ones(2, 4, dtype=torch.bool))
    with pytest.raises(ValueError, match="bandwidth"):
        RKNTransition(3, bandwidth=-1)
