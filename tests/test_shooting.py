"""The multiple-shooting objective against a naive per-step loop written here."""

import pytest
import torch
import torch.nn.functional as F

from ssm_ms.nets import ConvDecoder, LocallyLinearTransition, Projection
from ssm_ms.training.shooting import multiple_shooting_loss, rollout


def naive_loss(f, g, nodes, y, loss):
    """Literal transcription of the objective: one state, one step, one sub-trajectory at a time."""
    b, m, d = nodes.shape
    n = y.shape[1] // m
    fit_sum, fit_count, gap_sum, gap_count = 0.0, 0, 0.0, 0
    for j in range(b):
        for i in range(m):
            x = nodes[j, i]
            for k in range(n):
                pred = g(x.unsqueeze(0))[0]
                target = y[j, i * n + k]
                if loss == "mse":
                    fit_sum = fit_sum + ((pred - target) ** 2).sum()
                else:
                    fit_sum = fit_sum - (target * torch.log(pred) + (1 - target) * torch.log(1 - pred)).sum()
                fit_count += target.numel()
                x = f(x.unsqueeze(0))[0]
            if i < m - 1:  # x is now f^n(s_i)
                gap_sum = gap_sum + ((nodes[j, i + 1] - x) ** 2).sum()
                gap_count += d
    gap = gap_sum / gap_count if gap_count else torch.tensor(0.0, dtype=nodes.dtype)
    return fit_sum / fit_count, gap


@pytest.fixture
def small_model():
    torch.manual_seed(0)
    f = LocallyLinearTransition(3, n_matrices=4, hidden=16).double()
    g = ConvDecoder(3, preset=None, stem_channels=4, stem_size=2, layers=[[3, 3, 2], [1, 2, 1]]).double()
    return f, g


@pytest.mark.parametrize("loss", ["mse", "bce"])
def test_loss_matches_naive_loop(small_model, loss):
    f, g = small_model
    nodes = torch.randn(2, 3, 3, dtype=torch.float64, requires_grad=True)
    y = torch.rand(2, 12, *g.out_shape, dtype=torch.float64)
    fit, gap = multiple_shooting_loss(f, g, nodes, y, loss=loss)
    fit_ref, gap_ref = naive_loss(f, g, nodes, y, loss)
    torch.testing.assert_close(fit, fit_ref, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(gap, gap_ref, rtol=1e-10, atol=1e-12)
    # the gradients with respect to the nodes agree too (the indexing of nodes and windows is right)
    grad = torch.autograd.grad(fit + 7.0 * gap, nodes)[0]
    grad_ref = torch.autograd.grad(fit_ref + 7.0 * gap_ref, nodes)[0]
    torch.testing.assert_close(grad, grad_ref, rtol=1e-9, atol=1e-12)


def test_single_node_is_the_initial_value_problem(small_model):
    f, g = small_model
    x0 = torch.randn(3, 1, 3, dtype=torch.float64)
    y = torch.rand(3, 10, *g.out_shape, dtype=torch.float64)
    fit, gap = multiple_shooting_loss(f, g, x0, y)
    # IVP: roll out the whole length from x0, one state at a time
    preds = []
    for j in range(3):
        x, traj = x0[j, 0], []
        for _ in range(10):
            traj.append(g(x.unsqueeze(0))[0])
            x = f(x.unsqueeze(0))[0]
        preds.append(torch.stack(traj))
    torch.testing.assert_close(fit, F.mse_loss(torch.stack(preds), y), rtol=1e-10, atol=1e-12)
    assert gap.item() == 0.0


def test_gaps_vanish_on_a_trajectory_of_f(small_model):
    f, g = small_model
    n, m = 5, 4
    x = torch.randn(2, 3, dtype=torch.float64)
    nodes = []
    for _ in range(m):  # each node is f^n of the previous one
        nodes.append(x)
        for _ in range(n):
            x = f(x)
    nodes = torch.stack(nodes, dim=1)
    y = torch.rand(2, n * m, *g.out_shape, dtype=torch.float64)
    _, gap = multiple_shooting_loss(f, g, nodes, y)
    assert gap.item() < 1e-24
    # and not when a node is moved off the trajectory: gap = delta^2 / ((m-1) * d * B) for one component
    moved = nodes.clone()
    moved[1, m - 1, 0] += 0.5  # the last node: no sub-trajectory starts from it
    _, gap = multiple_shooting_loss(f, g, moved, y)
    assert gap.item() == pytest.approx(0.25 / ((m - 1) * 3 * 2), rel=1e-9)


def test_chunked_decoding_equals_one_call(small_model):
    f, g = small_model
    nodes = torch.randn(2, 2, 3, dtype=torch.float64)
    y = torch.rand(2, 8, *g.out_shape, dtype=torch.float64)
    a = multiple_shooting_loss(f, g, nodes, y)
    b = multiple_shooting_loss(f, g, nodes, y, decode_chunk=5)
    torch.testing.assert_close(a, b, rtol=1e-12, atol=0)


def test_rollout_iterates_f():
    f = torch.nn.Linear(2, 2, bias=False).double()
    x0 = torch.randn(4, 2, dtype=torch.float64)
    traj = rollout(f, x0, 6)
    a = f.weight.detach()
    for k in range(6):
        torch.testing.assert_close(traj[:, k], x0 @ torch.linalg.matrix_power(a, k).T)


def test_bad_inputs_are_named():
    f, g = torch.nn.Identity(), Projection([0])
    nodes = torch.zeros(2, 3, 2)
    with pytest.raises(ValueError, match=r"T=10 is not divisible .* m=3.*\[1, 2, 5, 10\]"):
        multiple_shooting_loss(f, g, nodes, torch.zeros(2, 10, 1))
    with pytest.raises(ValueError, match="unknown loss 'l1'"):
        multiple_shooting_loss(f, g, nodes, torch.zeros(2, 9, 1), loss="l1")
    with pytest.raises(ValueError, match=r"outputs measurements of shape \(1,\) but the data have shape \(2,\)"):
        multiple_shooting_loss(f, g, nodes, torch.zeros(2, 9, 2))
    with pytest.raises(ValueError, match="nodes hold 2 trajectories but y holds 3"):
        multiple_shooting_loss(f, g, nodes, torch.zeros(3, 9, 1))
