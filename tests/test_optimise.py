"""State inference by optimisation (``ssm_ms.inference.optimise.fit_nodes``) against the closed form of a linear
system: with ``f(x, u) = A x + B u`` and ``g(x) = C x`` the shooting objective is a linear least-squares problem in the
nodes, solved here by numpy from the matrices alone. The forecaster built on it: tests/test_protocol.py."""

import numpy as np
import pytest
import torch

from ssm_ms.inference.optimise import fit_nodes, step_scale

D, OBS, T = 3, 2, 12


class Affine(torch.nn.Module):
    """``x -> A x (+ B u)`` with fixed matrices."""

    def __init__(self, a: np.ndarray, b: np.ndarray | None = None):
        super().__init__()
        self.register_buffer("a", torch.from_numpy(a))
        self.register_buffer("b", None if b is None else torch.from_numpy(b))

    def forward(self, x: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        out = x @ self.a.T
        return out if u is None else out + u @ self.b.T


def system(seed: int = 0):
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.standard_normal((D, D)))
    a = 0.95 * q  # a damped rotation: powers stay well conditioned over T steps
    return a, rng.standard_normal((D, 1)), rng.standard_normal((OBS, D)), rng


def closed_form(a, b, c, y, u, m, alpha, weights):
    """The nodes ``[m, d]`` minimising ``sum_obs w (C x_t - y_t)^2 / N_obs + alpha * sum |gap|^2 / ((m - 1) d)`` for one
    sequence ``y [T, obs]`` (NaN: not observed), by least squares on the stacked nodes."""
    n = len(y) // m
    observed = np.isfinite(y)
    rows, rhs = [], []
    for i in range(m):
        x_basis, offset = np.eye(D), np.zeros(D)  # x_t = x_basis @ s_i + offset along piece i
        for j in range(n + 1):
            t = i * n + j
            if j == n:  # the gap to the next node
                if i + 1 < m:
                    w = np.sqrt(alpha / ((m - 1) * D))
                    for comp in range(D):
                        row = np.zeros(m * D)
                        row[i * D : (i + 1) * D] = -x_basis[comp]
                        row[(i + 1) * D + comp] = 1.0
                        rows.append(w * row)
                        rhs.append(w * offset[comp])
                break
            for comp in range(OBS):
                if observed[t, comp]:
                    w = np.sqrt(weights[comp] / observed.sum())
                    row = np.zeros(m * D)
                    row[i * D : (i + 1) * D] = (c @ x_basis)[comp]
                    rows.append(w * row)
                    rhs.append(w * (y[t, comp] - (c @ offset)[comp]))
            x_basis = a @ x_basis
            offset = a @ offset + (0 if u is None else b @ u[t])
    solution, *_ = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)
    residual = np.array(rows) @ solution - np.array(rhs)
    return solution.reshape(m, D), float(residual @ residual)


def measurements(a, b, c, rng, driven: bool, n_seq: int = 3):
    x = rng.standard_normal((n_seq, D))
    u = rng.standard_normal((n_seq, T, 1)) if driven else None
    y = np.zeros((n_seq, T, OBS))
    for t in range(T):
        y[:, t] = x @ c.T
        x = x @ a.T + (0 if u is None else u[:, t] @ b.T)
    return y + 0.1 * rng.standard_normal(y.shape), u


def test_one_node_is_the_least_squares_initial_state():
    a, _, c, rng = system()
    y, _ = measurements(a, None, c, rng, driven=False)
    start = torch.zeros(len(y), 1, D, dtype=torch.float64)
    g = Affine(c)
    nodes, objective = fit_nodes(Affine(a), g, torch.from_numpy(y), start, steps=1500, lr=0.05)
    for seq in range(len(y)):
        best, value = closed_form(a, None, c, y[seq], None, 1, 0.0, np.ones(OBS))
        np.testing.assert_allclose(nodes[seq].numpy(), best, atol=2e-4)
        assert objective[seq].item() == pytest.approx(value, rel=1e-5)


def test_several_nodes_with_inputs_weights_and_missing_samples_match_the_closed_form():
    a, b, c, rng = system(1)
    y, u = measurements(a, b, c, rng, driven=True)
    y[0, 5, 1] = y[2, 0, 0] = np.nan  # samples a sensor did not take: left out of the fit
    weights = np.array([1.0, 2.5])
    m, alpha = 3, 0.3
    start = torch.zeros(len(y), m, D, dtype=torch.float64)
    nodes, objective = fit_nodes(
        Affine(a, b),
        Affine(c),
        torch.from_numpy(y),
        start,
        alpha=alpha,
        steps=2000,
        lr=0.05,
        u=torch.from_numpy(u),
        weights=torch.from_numpy(weights),
        missing=True,
    )
    for seq in range(len(y)):
        best, value = closed_form(a, b, c, y[seq], u[seq], m, alpha, weights)
        np.testing.assert_allclose(nodes[seq].numpy(), best, atol=5e-4)
        assert objective[seq].item() == pytest.approx(value, rel=1e-4)


def test_the_best_step_is_kept_so_never_worse_than_the_start():
    a, _, c, rng = system(2)
    y, _ = measurements(a, None, c, rng, driven=False)
    optimum = np.stack([closed_form(a, None, c, y[s], None, 2, 1.0, np.ones(OBS))[0] for s in range(len(y))])
    start = torch.from_numpy(optimum)
    # a learning rate far too large: every step lands away from the optimum it started at
    nodes, objective = fit_nodes(Affine(a), Affine(c), torch.from_numpy(y), start, alpha=1.0, steps=50, lr=1.0)
    assert torch.equal(nodes, start)
    expected = [closed_form(a, None, c, y[s], None, 2, 1.0, np.ones(OBS))[1] for s in range(len(y))]
    np.testing.assert_allclose(objective.numpy(), expected, rtol=1e-9)
    none, at_start = fit_nodes(Affine(a), Affine(c), torch.from_numpy(y), start, alpha=1.0, steps=0)
    assert torch.equal(none, start)
    torch.testing.assert_close(at_start, objective)


def test_it_fits_under_the_test_loops_inference_mode():
    a, _, c, rng = system(3)
    y, _ = measurements(a, None, c, rng, driven=False)
    start = torch.zeros(len(y), 1, D, dtype=torch.float64)
    f, g = Affine(a), Affine(c)  # a trained model's parameters are normal tensors, its test batches are not
    plain, _ = fit_nodes(f, g, torch.from_numpy(y), start, steps=100)
    with torch.inference_mode():
        frozen, _ = fit_nodes(f, g, torch.from_numpy(y), start.clone(), steps=100)
    torch.testing.assert_close(frozen, plain)


def test_bad_settings_are_named():
    a, _, c, _ = system()
    y, start = torch.zeros(1, T, OBS, dtype=torch.float64), torch.zeros(1, 1, D, dtype=torch.float64)
    with pytest.raises(ValueError, match="steps must be >= 0"):
        fit_nodes(Affine(a), Affine(c), y, start, steps=-1)
    with pytest.raises(ValueError, match="lr must be > 0"):
        fit_nodes(Affine(a), Affine(c), y, start, lr=0.0)


def test_the_step_unit_is_the_nodes_spread_with_a_floor():
    rng = np.random.default_rng(0)
    nodes = torch.from_numpy(np.stack([rng.normal(0, 2, 500), np.full(500, 3.0), rng.normal(0, 1e-6, 500)], 1))
    spread = nodes.std(0)
    expected = torch.tensor([spread[0], 1e-3 * spread[0], 1e-3 * spread[0]], dtype=nodes.dtype)
    torch.testing.assert_close(step_scale(nodes), expected)  # a constant or barely used component still moves
    torch.testing.assert_close(step_scale(torch.full((10, 3), 1e-9, dtype=torch.float64)), torch.ones(3).double())
    torch.testing.assert_close(step_scale(nodes[:1]), torch.ones(3).double())  # one node: no spread to read
