"""The augmented Lagrangian: a toy problem with a closed-form KKT point, the gaps against a naive
loop, the multiplier update in training, checkpoints and bad settings."""

import pytest
import torch
from lightning.pytorch.callbacks import Callback, ModelCheckpoint

from ssm_ms.nets import LocallyLinearTransition, Projection
from ssm_ms.training.constraints import (
    AugmentedLagrangianOptions,
    augmented_lagrangian,
    raised_factor,
    update_multipliers,
)
from ssm_ms.training.shooting import multiple_shooting_loss, shooting_residuals
from tests.conftest import RotationDataModule, fast_trainer, rotation_model

NEWTON_GRAD_TOL = 1e-12


def _minimise(loss_fn, x0):
    """Newton's method on autograd's gradient and Hessian, until max |gradient| <= NEWTON_GRAD_TOL.

    The losses here are quadratic in x, so one step lands on the minimiser up to rounding. The stop
    is on the gradient, which rounding perturbs by ~1e-16 relative: a solver stopping on the loss no
    longer decreasing (L-BFGS's line search, here) leaves x only to ~sqrt(machine epsilon) ~ 1e-8
    (the loss is flat to second order at its minimum), an error whose size depends on the CPU's
    rounding and which is what made this test fail on one machine and pass on another."""
    x = x0.clone()
    for _ in range(10):
        z = x.clone().requires_grad_()
        (grad,) = torch.autograd.grad(loss_fn(z), z)
        if grad.abs().max() <= NEWTON_GRAD_TOL:
            return x
        x = x - torch.linalg.solve(torch.autograd.functional.hessian(loss_fn, x), grad)
    raise AssertionError(f"Newton did not reach max |gradient| <= {NEWTON_GRAD_TOL}: {grad.abs().max().item():.3g}")


def test_augmented_lagrangian_reaches_the_kkt_point_where_the_penalty_stays_biased():
    """min ||x - a||^2 s.t. A x = b (2 constraints, mean-normalised as the gaps are): the KKT point is
    the projection of a onto {A x = b}; its multiplier solves 2 (x* - a) + A^T lambda* / K = 0.

    The tolerances are the method's own error bound, not numbers fitted to one machine: with
    H = 2 I + (2 alpha / K) A^T A the Hessian of the augmented Lagrangian in x, the multiplier error
    e = lambda - lambda* contracts each outer iteration by R = I - (2 alpha / K) A H^-1 A^T
    (symmetric, ||R|| = 1 / (1 + alpha s_min^2 / K), s_min the smallest singular value of A), and
    x - x* = -H^-1 A^T e / K. An inexact inner solve (max |gradient| <= NEWTON_GRAD_TOL) moves x by
    at most delta = sqrt(3) NEWTON_GRAD_TOL / lambda_min(H), and lambda by 2 alpha ||A|| delta per update."""
    torch.manual_seed(0)
    a = torch.randn(3, dtype=torch.float64)
    A = torch.randn(2, 3, dtype=torch.float64)
    b = torch.randn(2, dtype=torch.float64)
    K = 2
    x_star = a - A.T @ torch.linalg.solve(A @ A.T, A @ a - b)
    lam_star = torch.linalg.lstsq(A.T, -2 * K * (x_star - a).unsqueeze(1)).solution.squeeze(1)
    alpha = 1.0
    n_outer = 40

    def fit(x):
        return (x - a).pow(2).sum()

    lam = torch.zeros(2, dtype=torch.float64)
    x = torch.zeros(3, dtype=torch.float64)
    for _ in range(n_outer):  # outer iterations: minimise the augmented Lagrangian, then update lambda
        x = _minimise(lambda z, lam=lam: augmented_lagrangian(fit(z), A @ z - b, lam, alpha), x)
        lam = update_multipliers(lam, A @ x - b, alpha)

    # the error bound after n_outer iterations from lambda_0 = 0 (e_0 = -lambda*)
    H = 2 * torch.eye(3, dtype=torch.float64) + 2 * alpha / K * A.T @ A
    rate = 1 / (1 + alpha * torch.linalg.svdvals(A).min() ** 2 / K)
    torch.testing.assert_close(
        torch.linalg.matrix_norm(
            torch.eye(2, dtype=torch.float64) - 2 * alpha / K * A @ torch.linalg.solve(H, A.T), ord=2
        ),
        rate,
        rtol=1e-12,
        atol=0,
    )
    delta = 3**0.5 * NEWTON_GRAD_TOL / torch.linalg.eigvalsh(H).min()
    lam_err = rate**n_outer * lam_star.norm() + 2 * alpha * torch.linalg.matrix_norm(A, ord=2) * delta / (1 - rate)
    x_err = (
        torch.linalg.matrix_norm(torch.linalg.solve(H, A.T), ord=2)
        / K
        * (
            rate ** (n_outer - 1) * lam_star.norm()
            + 2 * alpha * torch.linalg.matrix_norm(A, ord=2) * delta / (1 - rate)
        )
        + delta
    )
    assert x_err < 1e-8 and lam_err < 1e-7  # the bound is tight enough for the check to mean something
    assert (x - x_star).norm() <= x_err
    assert (lam - lam_star).norm() <= lam_err

    x_penalty = _minimise(
        lambda z: augmented_lagrangian(fit(z), A @ z - b, torch.zeros(2, dtype=torch.float64), alpha), x
    )
    assert (x_penalty - x_star).norm() > 1e-2  # the same alpha without multipliers: biased
    assert (A @ x_penalty - b).norm() > 1e-2


def naive_residuals(f, nodes, n):
    """c[b, i] = s[b, i+1] - f^n(s[b, i]), one trajectory and one gap at a time."""
    b, m, _ = nodes.shape
    out = torch.zeros(b, m - 1, nodes.shape[2], dtype=nodes.dtype)
    for j in range(b):
        for i in range(m - 1):
            x = nodes[j, i : i + 1]
            for _ in range(n):
                x = f(x)
            out[j, i] = nodes[j, i + 1] - x[0]
    return out


def test_residuals_are_the_gaps_and_give_the_penalty_loss():
    torch.manual_seed(1)
    f = LocallyLinearTransition(3, n_matrices=4, hidden=8).double()
    g = Projection([0, 2])
    nodes = torch.randn(2, 4, 3, dtype=torch.float64)
    y = torch.randn(2, 12, 2, dtype=torch.float64)
    fit, c = shooting_residuals(f, g, nodes, y)
    torch.testing.assert_close(c, naive_residuals(f, nodes, 3), rtol=1e-12, atol=1e-12)
    fit_ref, gap_ref = multiple_shooting_loss(f, g, nodes, y)
    assert torch.equal(fit, fit_ref)
    torch.testing.assert_close(c.pow(2).mean(), gap_ref, rtol=1e-14, atol=0)
    # zero multipliers: the augmented Lagrangian is the paper's penalty
    torch.testing.assert_close(
        augmented_lagrangian(fit, c, torch.zeros_like(c), 7.0), fit_ref + 7.0 * gap_ref, rtol=1e-14, atol=0
    )


class MultiplierCheck(Callback):
    """Before each step: multipliers and the batch's gaps by the naive loop; after it: the update."""

    def __init__(self):
        self.checked, self.untouched = 0, 0

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        with torch.no_grad():
            nodes = pl_module.node_states(batch["index"])
            self.c = naive_residuals(pl_module.f, nodes, batch["y"].shape[1] // pl_module.n_nodes).flatten(1)
        self.before = pl_module.multipliers.clone()
        self.alpha = float(pl_module.alpha * pl_module.alpha_factor)

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        index = batch["index"]
        after = pl_module.multipliers
        if (trainer.current_epoch + 1) % 2 == 0:  # every_n_epochs=2: epochs 1, 3, ...
            torch.testing.assert_close(after[index], self.before[index] + 2 * self.alpha * self.c, rtol=1e-5, atol=1e-7)
            self.checked += 1
        else:
            assert torch.equal(after, self.before)
            self.untouched += 1
        outside = [j for j in range(len(after)) if j not in index.tolist()]
        assert torch.equal(after[outside], self.before[outside])


@pytest.mark.parametrize("node_optimizer", ["dense", "sparse"])
def test_multipliers_follow_lambda_plus_two_alpha_gap_on_their_cadence(tmp_path, rotation_dm, node_optimizer):
    check = MultiplierCheck()
    model = rotation_model(
        constraint="augmented_lagrangian",
        constraint_options={"every_n_epochs": 2},
        alpha=3.0,
        node_optimizer=node_optimizer,
    )
    fast_trainer(tmp_path, max_epochs=4, callbacks=[check]).fit(model, rotation_dm)
    assert check.checked == 4 and check.untouched == 4  # 2 steps per epoch
    assert model.multipliers.shape == (8, 2 * 2) and (model.multipliers != 0).all()


def test_alpha_grows_only_when_the_gaps_stop_shrinking():
    opts = AugmentedLagrangianOptions(growth=10.0, shrink=0.25, max_factor=500.0)
    assert raised_factor(1.0, 0.5, float("inf"), opts) == 1.0  # first update epoch: nothing to compare
    assert raised_factor(1.0, 0.2, 1.0, opts) == 1.0  # shrank below 0.25x
    assert raised_factor(1.0, 0.3, 1.0, opts) == 10.0
    assert raised_factor(100.0, 0.3, 1.0, opts) == 500.0  # capped


def test_augmented_lagrangian_state_is_checkpointed_and_resumes_exactly(tmp_path):
    """Multipliers, alpha's factor and the last gap are buffers: a run stopped after 2 epochs and
    resumed ends where an uninterrupted 4-epoch run does, bit for bit (growth on every epoch)."""

    def dm():
        return RotationDataModule(data_dir=str(tmp_path / "data"), batch_size=4, val_trajectories=0)

    def model():
        return rotation_model(
            constraint="augmented_lagrangian",
            node_optimizer="sparse",
            constraint_options={"growth": 2.0, "shrink": 1.01, "max_factor": 100.0},
        )

    full = model()
    fast_trainer(tmp_path / "full", max_epochs=4).fit(full, dm())
    assert full.alpha_factor.item() == 8.0  # raised after epochs 1, 2, 3 (epoch 0 has nothing to compare)
    ckpt = ModelCheckpoint(dirpath=tmp_path / "ckpt", save_last=True)
    fast_trainer(tmp_path / "a", max_epochs=2, callbacks=[ckpt]).fit(model(), dm())
    resumed = model()
    fast_trainer(tmp_path / "b", max_epochs=4).fit(resumed, dm(), ckpt_path=str(tmp_path / "ckpt" / "last.ckpt"))
    a, b = full.state_dict(), resumed.state_dict()
    assert {"multipliers", "alpha_factor", "last_gap_rms"} <= set(a)
    for key in a:
        torch.testing.assert_close(b[key], a[key], rtol=0, atol=0)


def test_bad_constraint_settings_are_refused():
    with pytest.raises(ValueError, match=r"augmented_lagrangian' needs continuity gaps, but n_nodes=1 has none"):
        rotation_model(constraint="augmented_lagrangian", n_nodes=1)
    with pytest.raises(ValueError, match="unknown constraint 'barrier'"):
        rotation_model(constraint="barrier")
    with pytest.raises(ValueError, match=r"unknown constraint_options \['rho'\]"):
        rotation_model(constraint="augmented_lagrangian", constraint_options={"rho": 2.0})
    with pytest.raises(ValueError, match="apply to constraint: augmented_lagrangian only"):
        rotation_model(constraint_options={"growth": 10.0})
    with pytest.raises(ValueError, match="every_n_epochs must be a whole number >= 1"):
        rotation_model(constraint="augmented_lagrangian", constraint_options={"every_n_epochs": 0})


def test_constraint_benchmark_runs_at_a_tiny_size(tmp_path):
    """benchmarks/bench_constraints.py --tiny: every row it promises, the TINY note, the AL's final alpha."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_constraints.py"
    spec = importlib.util.spec_from_file_location("bench_constraints", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    out = tmp_path / "constraints.md"
    rows = bench.main(
        [
            "--tiny",
            "--experiments",
            "lorenz_T1000",
            "--variants",
            "penalty, alpha x0.1",
            "augmented Lagrangian, alpha x0.1",
            "penalty, sparse nodes",
            "--data-dir",
            str(tmp_path / "data"),
            "--workdir",
            str(tmp_path / "runs"),
            "--out",
            str(out),
        ]
    )
    text = out.read_text()
    assert "TINY sizes" in text and "## lorenz_T1000" in text
    assert [r["variant"] for r in rows] == [
        "penalty, alpha x0.1",
        "augmented Lagrangian, alpha x0.1",
        "penalty, sparse nodes",
    ]
    assert rows[0]["final_alpha"] == 10.0  # the config's alpha 100, times 0.1, raised at the scaled milestone
    assert rows[0]["initial_alpha"] == pytest.approx(0.1)  # the model's initial alpha 1, times 0.1
    for r in rows:
        assert r["epochs"] == 2 and r["gap"] > 0 and r["fit"] > 0 and r["rollout_mse"] > 0
        assert f"| {r['variant']} | 2 |" in text
