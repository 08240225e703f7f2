"""Systems driven by inputs: ``x[t+1] = f(x[t], u[t])``. The shooting loss rolls each piece under its own slice of
inputs (against a naive loop), both transitions take inputs as documented (against their formulas), the model
learned from noisy data of a linear system recovers its Markov parameters ``C A^k B``, and the files DataModule
reads, checks and normalises ``u``."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from datamodules.files import FileDataModule
from ssm_ms.module import MultipleShootingModule
from ssm_ms.nets import FullyConnectedTransition, LinearReadout, LocallyLinearTransition
from ssm_ms.training.shooting import multiple_shooting_loss, rollout, shooting_residuals
from tests.conftest import fast_trainer


# ---------------------------------------------------------------------------- the transitions
def test_locally_linear_with_inputs_is_its_formula():
    torch.manual_seed(0)
    f = LocallyLinearTransition(3, n_matrices=4, hidden=8, input_dim=2)
    x, u = torch.randn(5, 3), torch.randn(5, 2)
    beta = torch.softmax(f.beta[2](torch.relu(f.beta[0](torch.cat([x, u], 1)))), dim=1)  # [5, K]
    a = f.matrices.view(4, 3, 3)
    b = f.input_matrices.view(4, 3, 2)
    expected = x + sum(beta[:, k, None] * (x @ a[k].T + u @ b[k].T) for k in range(4))
    torch.testing.assert_close(f(x, u), expected)
    # the local maps: f(x, u) = A(x, u) x + B(x, u) u
    local = (f.matrix(x, u) @ x[..., None] + f.input_matrix(x, u) @ u[..., None])[..., 0]
    torch.testing.assert_close(local, f(x, u))


def test_input_dim_zero_is_the_paper_model():
    """Without inputs: the same parameters (names and shapes) as before inputs existed, f(x) = x + sum beta A x."""
    torch.manual_seed(0)
    f = LocallyLinearTransition(3, n_matrices=4, hidden=8)
    assert sorted(f.state_dict()) == ["beta.0.bias", "beta.0.weight", "beta.2.bias", "beta.2.weight", "matrices"]
    x = torch.randn(5, 3)
    beta = torch.softmax(f.beta[2](torch.relu(f.beta[0](x))), dim=1)
    a = f.matrices.view(4, 3, 3)
    torch.testing.assert_close(f(x), x + sum(beta[:, k, None] * (x @ a[k].T) for k in range(4)))
    fc = FullyConnectedTransition(3, hidden=[8])
    assert sorted(fc.state_dict()) == ["mlp.0.bias", "mlp.0.weight", "mlp.2.bias", "mlp.2.weight"]


def test_fully_connected_with_inputs_is_x_plus_mlp_of_x_and_u():
    torch.manual_seed(0)
    f = FullyConnectedTransition(3, hidden=[8, 8], input_dim=2)
    x, u = torch.randn(5, 3), torch.randn(5, 2)
    torch.testing.assert_close(f(x, u), x + f.mlp(torch.cat([x, u], 1)))


@pytest.mark.parametrize(
    "make",
    [lambda m: LocallyLinearTransition(3, 2, 4, input_dim=m), lambda m: FullyConnectedTransition(3, [4], input_dim=m)],
)
def test_inputs_given_or_missing_are_named(make):
    with pytest.raises(ValueError, match="needs inputs u"):
        make(2)(torch.zeros(1, 3))
    with pytest.raises(ValueError, match="takes no inputs"):
        make(0)(torch.zeros(1, 3), torch.zeros(1, 2))
    with pytest.raises(ValueError, match=r"u must be \[N, 2\]"):
        make(2)(torch.zeros(1, 3), torch.zeros(1, 3))


# ---------------------------------------------------------------------------- the shooting loss
def test_each_piece_rolls_out_under_its_own_inputs():
    """fit and gaps against a naive loop over trajectories, pieces and steps."""
    torch.manual_seed(0)
    f = LocallyLinearTransition(2, n_matrices=3, hidden=8, input_dim=1)
    g = torch.nn.Linear(2, 1)
    b, m, n = 3, 4, 5
    nodes, y, u = torch.randn(b, m, 2), torch.randn(b, m * n, 1), torch.randn(b, m * n, 1)
    fit, residual = shooting_residuals(f, g, nodes, y, u=u)
    sq, gaps = [], torch.zeros(b, m - 1, 2)
    for j in range(b):
        for i in range(m):
            x = nodes[j, i : i + 1]
            for k in range(n):
                sq.append((g(x) - y[j, i * n + k]).pow(2).sum())
                x = f(x, u[j, i * n + k : i * n + k + 1])
            if i + 1 < m:
                gaps[j, i] = nodes[j, i + 1] - x[0]
    torch.testing.assert_close(fit, torch.stack(sq).sum() / y.numel())
    torch.testing.assert_close(residual, gaps)
    with pytest.raises(ValueError, match=r"inputs u must be \[batch, T, input_dim\] = \[3, 20, m\]"):
        shooting_residuals(f, g, nodes, y, u=u[:, :10])


def test_rollout_uses_the_input_of_each_step():
    f = lambda x, u: x + u  # noqa: E731
    x0, u = torch.zeros(1, 1), torch.arange(1.0, 5.0).view(1, 4, 1)
    assert rollout(f, x0, 5, u)[0, :, 0].tolist() == [0.0, 1.0, 3.0, 6.0, 10.0]
    with pytest.raises(ValueError, match="needs 4 inputs"):
        rollout(f, x0, 5, u[:, :3])


# ---------------------------------------------------------------------------- a known linear system
A = np.array([[0.95, 0.2], [-0.2, 0.95]])
B = np.array([[0.0], [0.3]])
C = np.array([[1.0, 0.5]])


def linear_data(n: int, t: int, noise: float, seed: int = 0) -> dict[str, np.ndarray]:
    """``x+ = A x + B u``, ``y = C x + noise``, white inputs, random initial states."""
    rng = np.random.default_rng(seed)
    x, u, ys = rng.normal(size=(n, 2)), rng.normal(size=(n, t, 1)), []
    for k in range(t):
        ys.append(x @ C.T)
        x = x @ A.T + u[:, k] @ B.T
    y = np.stack(ys, 1)
    return {
        "y": (y + noise * rng.normal(size=y.shape)).astype(np.float32),
        "y_clean": y.astype(np.float32),
        "u": u.astype(np.float32),
    }


def markov(a, b, c, steps: int = 12) -> np.ndarray:
    return np.array([float((c @ np.linalg.matrix_power(a, k) @ b).item()) for k in range(steps)])


def test_a_linear_system_is_recovered_to_its_markov_parameters():
    """SSM-LL with one matrix pair is linear: trained by multiple shooting (4 pieces of 10 steps, the gap weight
    raised after a third) on 32 noisy trajectories (noise std 0.05), its ``C A^k B``, which do not depend on the
    state's coordinates, match the true system's to 2% of their largest value for k = 0..11.

    ``f`` starts near the identity (its matrix drawn a tenth of the default bound): with the default, ``x + A x`` of a
    2-d state can start with an eigenvalue of 1.6, a 10-step piece grows 100-fold, and 2 of 8 seeds had not fitted
    in 600 steps (16 of 16 fit from near the identity, Markov error 0.14-0.21%)."""
    torch.manual_seed(0)
    data = linear_data(32, 40, 0.05)
    y, u = torch.from_numpy(data["y"]), torch.from_numpy(data["u"])
    f = LocallyLinearTransition(2, n_matrices=1, hidden=4, input_dim=1)
    with torch.no_grad():
        f.matrices.mul_(0.1)
    g = torch.nn.Linear(2, 1, bias=False)
    nodes = torch.zeros(32, 4, 2, requires_grad=True)
    optimizer = torch.optim.Adam([*f.parameters(), *g.parameters(), nodes], lr=0.03)
    for step in range(600):
        fit, gap = multiple_shooting_loss(f, g, nodes, y, u=u)
        optimizer.zero_grad()
        (fit + (1.0 if step < 200 else 100.0) * gap).backward()
        optimizer.step()
    assert fit.item() < 1.3 * 0.05**2 and gap.item() < 1e-5  # the noise's variance: nothing left to explain
    with torch.no_grad():
        zero, none = torch.zeros(1, 2), torch.zeros(1, 1)
        learned = markov(
            f.matrix(zero, none)[0].double().numpy(),
            f.input_matrix(zero, none)[0].double().numpy(),
            g.weight.double().numpy(),
        )
    true = markov(A, B, C)
    assert np.abs(learned - true).max() < 0.02 * np.abs(true).max(), (learned.round(3), true.round(3))


# ---------------------------------------------------------------------------- the files DataModule
def write(path, **arrays):
    np.savez(path, **arrays)
    return str(path)


def test_files_serve_inputs_normalised_and_the_module_trains_on_them(tmp_path):
    data = linear_data(16, 20, 0.05)
    path = write(tmp_path / "lin.npz", **data)
    dm = FileDataModule(path, clean_key="y_clean", input_key="u", normalize=True, batch_size=8, val_trajectories=2)
    assert dm.input_dim == 1
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    u_raw = data["u"][batch["index"].numpy()]
    mean, std = data["u"].mean(), data["u"].std()
    np.testing.assert_allclose(batch["u"].numpy(), (u_raw - mean) / std, rtol=1e-4, atol=1e-5)
    assert dm.state_dict()["input_normalizer"]["mean"].item() == pytest.approx(mean, rel=1e-5)
    model = MultipleShootingModule(
        LocallyLinearTransition(2, 2, 8, input_dim=1), LinearReadout(2, 1), state_dim=2, n_nodes=4
    )
    fast_trainer(tmp_path, max_epochs=2, limit_val_batches=1).fit(model, dm)
    autonomous = MultipleShootingModule(LocallyLinearTransition(2, 2, 8), LinearReadout(2, 1), state_dim=2, n_nodes=4)
    with pytest.raises(ValueError, match="f takes 0 inputs per step but the data have 1: give f input_dim: 1"):
        fast_trainer(tmp_path, max_epochs=1).fit(autonomous, dm)


@pytest.mark.parametrize(
    "change,match",
    [
        (lambda d: d.pop("u"), r"input_key 'u'"),
        (
            lambda d: d.update(u=d["u"][:, :10]),
            r"holds 16 trajectories of 10 inputs but its measurements hold 16 of 20",
        ),
        (lambda d: d.update(u=(d["u"] * 100).astype(np.uint8)), r"must be a float \(or signed integer\) array"),
        (lambda d: d["u"].__setitem__((3, 4, 0), np.nan), r"(?i)nan|not finite"),
    ],
)
def test_bad_inputs_are_refused_with_one_message(tmp_path, change, match):
    data = linear_data(16, 20, 0.05)
    change(data)
    path = write(tmp_path / "bad.npz", **data)
    with pytest.raises(ValueError, match=match):
        dm = FileDataModule(path, input_key="u", batch_size=8)
        dm.setup("fit")


# ---------------------------------------------------------------------------- forecasting with inputs
class LinearSystem(torch.nn.Module):
    """The true ``x+ = A x + B u`` as a driven transition."""

    input_dim = 1
    state_dim = 2

    def __init__(self):
        super().__init__()
        self.register_buffer("a", torch.tensor(A, dtype=torch.float32))
        self.register_buffer("b", torch.tensor(B, dtype=torch.float32))

    def forward(self, x, u):
        return x @ self.a.T + u @ self.b.T


@pytest.fixture(scope="module")
def exact_driven(tmp_path_factory):
    """An SSM whose f is the true linear system and g its C, checkpointed after a nominal epoch, and its data."""
    tmp = tmp_path_factory.mktemp("driven")
    data = linear_data(12, 40, 0.01)
    path = write(tmp / "lin.npz", **data)
    g = torch.nn.Linear(2, 1, bias=False)
    with torch.no_grad():
        g.weight.copy_(torch.tensor(C, dtype=torch.float32))
    g.requires_grad_(False)
    model = MultipleShootingModule(LinearSystem(), g, state_dim=2, n_nodes=4, lr=1e-9)
    dm = FileDataModule(path, clean_key="y_clean", input_key="u", batch_size=4, val_trajectories=0)
    trainer = fast_trainer(tmp, max_epochs=1)
    trainer.fit(model, dm)
    trainer.save_checkpoint(tmp / "ssm.ckpt")
    return tmp, path, data


@pytest.mark.parametrize("method", ["ukf", "optimise"])
def test_a_driven_forecast_rolls_out_under_the_future_inputs(exact_driven, method):
    """The UKF (or a fit of 4 pieces through f and g) infers states under the given inputs, the forecast continues
    under the next ones: against a naive loop of the true system from the last estimate, and close to the noiseless
    future."""
    from ssm_ms.inference.filter_module import FilterForecaster
    from ssm_ms.inference.optimise import OptimisationForecaster

    tmp, _, data = exact_driven
    if method == "ukf":
        forecaster = FilterForecaster(
            str(tmp / "ssm.ckpt"), n_filter=20, method="ukf", process_var=1e-6, measurement_var=1e-4, init_var=1.0
        )
    else:
        forecaster = OptimisationForecaster(str(tmp / "ssm.ckpt"), n_filter=20, n_nodes=4, n_candidates=8)
    assert forecaster.input_dim == 1
    y, u = torch.from_numpy(data["y"][:3]), torch.from_numpy(data["u"][:3])
    k, p = 20, 10
    out = forecaster.checked_forecast(y[:, :k], p, u=u)
    x = out.states[:, k - 1].double()
    expected = []
    for j in range(p):
        x = x @ torch.tensor(A).T + u[:, k - 1 + j].double() @ torch.tensor(B).T
        expected.append(x @ torch.tensor(C).T)
    torch.testing.assert_close(out.predicted.double(), torch.stack(expected, 1), rtol=1e-4, atol=1e-5)
    truth = torch.from_numpy(data["y_clean"][:3, k : k + p])
    assert (out.predicted - truth).abs().max() < 0.05  # the filter found the state: the forecast is the future
    with pytest.raises(ValueError, match=r"needs the inputs of those 29 transitions \(u\[0 \.\. 28\]\), got 25"):
        forecaster.checked_forecast(y[:, :k], p, u=u[:, :25])
    with pytest.raises(ValueError, match="got none"):
        forecaster.checked_forecast(y[:, :k], p)


def test_the_encoder_reads_the_input_that_led_to_each_frame():
    """Frame t's LSTM step sees u[t-1] (zeros at t = 0): changing u[5] changes the states from t = 6 on only."""
    from ssm_ms.nets.encoder import StateEncoder

    torch.manual_seed(0)
    enc = StateEncoder(3, [2], preset="vector", hidden=8, input_dim=1)
    y, u = torch.randn(2, 10, 2), torch.randn(2, 9, 1)
    changed = u.clone()
    changed[:, 5] += 1.0
    a, b = enc(y, u), enc(y, changed)
    torch.testing.assert_close(a[:, :6], b[:, :6])
    assert (a[:, 6:] - b[:, 6:]).abs().min() > 0
    with pytest.raises(ValueError, match=r"needs the inputs u \[2, >= 9, 1\]"):
        enc(y)
    memory, steps = None, []
    for t in range(10):  # one frame at a time, with the input that led to it: the same states
        state, memory = enc.step(y[:, t], u[:, t - 1] if t else None, memory)
        steps.append(state)
    torch.testing.assert_close(torch.stack(steps, 1), a, rtol=1e-5, atol=1e-6)


def test_predict_takes_the_future_inputs_and_refuses_a_horizon_without_them(exact_driven, tmp_path, capsys):
    """cli predict on new recordings: y for the 20 given samples, u for those and the 10 to forecast; the file's
    forecast is the forecaster's; with too few inputs, one message."""
    from ssm_ms.cli import main

    ckpt, _, data = exact_driven
    config = tmp_path / "ukf.yaml"
    config.write_text(f"""
model:
  class_path: ssm_ms.inference.FilterForecaster
  init_args: {{ssm_checkpoint: {ckpt / "ssm.ckpt"}, n_filter: 20, method: ukf, measurement_var: 1.0e-4, init_var: 1.0,
              metrics: [mse], results_dir: {tmp_path / "results"}}}
data:
  class_path: datamodules.files.FileDataModule
  init_args: {{train_path: {ckpt / "lin.npz"}, input_key: u, batch_size: 4}}
trainer: {{accelerator: cpu, logger: false, enable_progress_bar: false, default_root_dir: {tmp_path}}}
""")
    new = linear_data(3, 40, 0.01, seed=7)
    np.savez(tmp_path / "new.npz", y=new["y"][:, :20], u=new["u"][:, :29])
    out = tmp_path / "pred.npz"
    main(
        [
            "predict",
            "--config",
            str(config),
            "--data.init_args.predict_path",
            str(tmp_path / "new.npz"),
            "--data.init_args.predict_steps",
            "10",
            "--trainer.callbacks+=ssm_ms.forecasting.ForecastWriter",
            "--trainer.callbacks.output",
            str(out),
        ]
    )
    saved = np.load(out)
    assert saved["predicted"].shape == (3, 10, 1)
    assert np.abs(saved["predicted"] - new["y_clean"][:, 20:30]).max() < 0.05
    np.savez(tmp_path / "short.npz", y=new["y"][:, :20], u=new["u"][:, :25])
    with pytest.raises(SystemExit):
        main(
            [
                "predict",
                "--config",
                str(config),
                "--data.init_args.predict_path",
                str(tmp_path / "short.npz"),
                "--data.init_args.predict_steps",
                "10",
                "--trainer.callbacks+=ssm_ms.forecasting.ForecastWriter",
                "--trainer.callbacks.output",
                str(out),
            ]
        )
    err = capsys.readouterr().err
    assert "give the future inputs too" in err and "Traceback" not in err
