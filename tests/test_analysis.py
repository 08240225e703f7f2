"""ssm_ms.analysis against independent answers: finite differences, closed forms, scipy, the Lorenz equations."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats

from datamodules.lorenz import LorenzDataModule, lorenz_rk4, lorenz_rk4_step, lorenz_wing_level
from ssm_ms.analysis import (
    amplitude_ratio,
    attractor_statistics,
    both_wings_share,
    dominant_period,
    dynamics_report,
    free_run,
    jacobian,
    linearize,
    lyapunov_spectrum,
    lyapunov_time,
    summarize_valid_time,
    valid_prediction_time,
    wasserstein_1d,
)
from ssm_ms.nets import ConvDecoder, FullyConnectedTransition, LocallyLinearTransition, Projection

SIGMA, BETA, RHO, DT = 10.0, 8.0 / 3.0, 28.0, 0.005
F64 = torch.float64


@pytest.fixture
def one_thread():
    """Benettin's loop is thousands of tiny batched QRs: on a busy 2-core machine, handing each to a
    second thread costs far more than the work itself, so these tests run single-threaded."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def finite_difference_jacobian(fn, x: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Central differences, one input direction at a time: ``[N, *out, d]``."""
    cols = []
    for i in range(x.shape[1]):
        e = torch.zeros_like(x)
        e[:, i] = eps
        with torch.no_grad():
            cols.append((fn(x + e) - fn(x - e)) / (2 * eps))
    return torch.stack(cols, dim=-1)


def small_decoder() -> ConvDecoder:
    # channels-last by default: vmap cannot batch its layout copy, so this exercises the forward-mode fallback
    return ConvDecoder(3, preset=None, stem_channels=4, stem_size=2, layers=[[3, 3, 2], [1, 2, 1]]).double()


def rotation(omega: float):
    c, s = math.cos(omega), math.sin(omega)
    m = torch.tensor([[c, -s], [s, c]], dtype=F64)
    return lambda x: x @ m.T


def lorenz_states(runs: int, steps: int, seed: int = 0, transient: int = 2000) -> np.ndarray:
    """True Lorenz states ``[runs, steps, 3]`` on the attractor (numpy integrator of the data module)."""
    x0 = np.random.default_rng(seed).uniform(-10, 10, size=(runs, 3))
    return lorenz_rk4(x0, transient + steps, DT)[:, transient:]


# ---------------------------------------------------------------------------- the true Lorenz transition
def test_lorenz_rk4_step_iterated_equals_numpy_integrator():
    x0 = np.random.default_rng(1).uniform(-10, 10, size=(5, 3))
    ref = lorenz_rk4(x0, 400, DT)
    x, out = torch.tensor(x0), []
    for _ in range(400):
        out.append(x)
        x = lorenz_rk4_step(x, DT, SIGMA, BETA, RHO)
    np.testing.assert_allclose(torch.stack(out, dim=1).numpy(), ref, rtol=1e-13, atol=1e-12)


def test_true_transition_uses_the_data_modules_parameters(tmp_path):
    dm = LorenzDataModule(data_dir=str(tmp_path), dt=0.01, sigma=9.0, beta=2.5, rho=30.0)
    x0 = np.random.default_rng(2).uniform(-10, 10, size=(4, 3))
    ref = lorenz_rk4(x0, 2, dt=0.01, sigma=9.0, beta=2.5, rho=30.0)[:, 1]
    np.testing.assert_allclose(dm.true_transition()(torch.tensor(x0)).numpy(), ref, rtol=1e-14, atol=1e-13)
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        lorenz_rk4_step(torch.zeros(4, 2, dtype=F64))


# ---------------------------------------------------------------------------- Jacobians
def test_jacobian_of_a_linear_map_is_its_matrix():
    torch.manual_seed(0)
    m, b = torch.randn(4, 3, dtype=F64), torch.randn(4, dtype=F64)
    jac = jacobian(lambda x: x @ m.T + b, torch.randn(5, 3, dtype=F64))
    assert jac.shape == (5, 4, 3)
    torch.testing.assert_close(jac, m.expand(5, 4, 3), rtol=0, atol=1e-15)


@pytest.mark.parametrize("net", ["ll", "fc"])
def test_jacobian_of_transitions_matches_finite_differences(net):
    torch.manual_seed(0)
    f = LocallyLinearTransition(3, n_matrices=4, hidden=16) if net == "ll" else FullyConnectedTransition(3, (16, 16))
    f = f.double()  # both use nn.ReLU(inplace=True)
    x = torch.randn(6, 3, dtype=F64)
    with torch.no_grad():
        jac = jacobian(f, x)
    assert jac.shape == (6, 3, 3) and not jac.requires_grad
    torch.testing.assert_close(jac, finite_difference_jacobian(f, x), rtol=1e-6, atol=1e-8)


def test_linearize_shapes_and_values():
    torch.manual_seed(0)
    f, g = LocallyLinearTransition(3, n_matrices=4, hidden=16).double(), small_decoder()
    x = torch.randn(5, 3, dtype=F64)
    a, _, c = linearize(f, g, x)
    assert a.shape == (5, 3, 3) and c.shape == (5, 36, 3)  # 1 x 6 x 6 frames
    torch.testing.assert_close(a, finite_difference_jacobian(f, x), rtol=1e-6, atol=1e-8)
    torch.testing.assert_close(c, finite_difference_jacobian(g, x).reshape(5, 36, 3), rtol=1e-6, atol=1e-8)
    _, _, c_proj = linearize(f, Projection([0, 2]), x)
    torch.testing.assert_close(c_proj, Projection([0, 2]).observation_matrix(3).to(F64).expand(5, 2, 3))


# ---------------------------------------------------------------------------- Lyapunov exponents
def test_lyapunov_spectrum_of_a_linear_map_is_log_eigenvalue_moduli(one_thread):
    v = torch.tensor([[1.0, 0.8, 0.3], [0.0, 1.0, 0.7], [0.5, 0.0, 1.0]], dtype=F64)  # far from orthogonal
    m = v @ torch.diag(torch.tensor([2.0, 0.5, 0.1], dtype=F64)) @ torch.linalg.inv(v)
    expected = torch.log(torch.tensor([2.0, 0.5, 0.1], dtype=F64)) / 0.1
    x0 = torch.randn(3, 3, dtype=F64, generator=torch.Generator().manual_seed(0))
    plain = lyapunov_spectrum(lambda x: x @ m.T, x0, steps=500, dt=0.1)
    assert plain.per_run.shape == (3, 3) and plain.dt == 0.1 and plain.steps == 500
    torch.testing.assert_close(plain.exponents, expected, rtol=1e-3, atol=0)
    aligned = lyapunov_spectrum(lambda x: x @ m.T, x0, steps=20, dt=0.1, align=60)  # frame on the eigenvectors
    torch.testing.assert_close(aligned.exponents, expected, rtol=1e-10, atol=0)
    torch.testing.assert_close(aligned.std, torch.zeros(3, dtype=F64), rtol=0, atol=1e-10)
    top = lyapunov_spectrum(lambda x: x @ m.T, x0, steps=20, dt=0.1, align=60, n_exponents=1)
    torch.testing.assert_close(top.exponents, expected[:1], rtol=1e-10, atol=0)


def test_lyapunov_spectrum_of_a_rotation_is_zero(one_thread):
    res = lyapunov_spectrum(rotation(0.3), torch.tensor([[1.0, 0.0], [0.0, 2.0]], dtype=F64), steps=50)
    torch.testing.assert_close(res.exponents, torch.zeros(2, dtype=F64), rtol=0, atol=1e-13)


def test_lyapunov_spectrum_of_the_true_lorenz_system(one_thread):
    """Lorenz 63 per time unit: ~0.906, 0, -14.57; their sum is the divergence -(sigma + 1 + beta)."""
    x0 = torch.empty(32, 3, dtype=F64).uniform_(-10, 10, generator=torch.Generator().manual_seed(0))
    f = LorenzDataModule(data_dir="unused").true_transition()
    res = lyapunov_spectrum(f, x0, steps=3000, dt=DT, transient=4000, align=600)  # 15 time units, 32 runs
    first, second, third = res.exponents.tolist()
    assert 0.85 < first < 0.97, res.exponents
    assert abs(second) < 0.1, res.exponents
    assert res.exponents.sum().item() == pytest.approx(-(SIGMA + 1 + BETA), rel=0.02)
    assert third == pytest.approx(-14.57, rel=0.02)
    assert lyapunov_time(first) == pytest.approx(1 / first)


def test_lyapunov_time():
    assert lyapunov_time(0.5) == 2.0
    assert lyapunov_time(0.0) == math.inf and lyapunov_time(-1.0) == math.inf


# ---------------------------------------------------------------------------- free runs and statistics
def test_free_run_matches_a_naive_loop():
    torch.manual_seed(0)
    f = LocallyLinearTransition(3, n_matrices=4, hidden=16)
    x0 = torch.randn(4, 3)
    out = free_run(f, x0, steps=5, transient=3)
    with torch.no_grad():
        for r in range(4):
            x = x0[r : r + 1]
            for _ in range(3):
                x = f(x)
            for k in range(5):
                torch.testing.assert_close(out[r, k], x[0])
                x = f(x)
    assert out.shape == (4, 5, 3) and not out.requires_grad
    torch.testing.assert_close(free_run(f, x0, steps=1)[:, 0], x0)


def test_wasserstein_closed_forms():
    a = torch.randn(300, dtype=F64, generator=torch.Generator().manual_seed(0))
    assert wasserstein_1d(a, a + 1.7) == pytest.approx(1.7, abs=1e-12)
    assert wasserstein_1d(a, a) == 0.0
    assert wasserstein_1d(torch.tensor([2.0]), torch.tensor([-1.0])) == pytest.approx(3.0)
    # half the mass at 0 vs all at 1: 0.5 * 1 + 0.5 * 0
    assert wasserstein_1d(torch.tensor([0.0, 1.0]), torch.tensor([1.0, 1.0, 1.0])) == pytest.approx(0.5)


def test_wasserstein_matches_scipy_on_different_sizes():
    rng = np.random.default_rng(0)
    for n, m in ((50, 73), (200, 31), (1, 9)):
        a, b = rng.standard_normal(n), rng.exponential(2.0, m)
        expected = stats.wasserstein_distance(a, b)
        got = wasserstein_1d(torch.tensor(a), torch.tensor(b, dtype=torch.float32))  # mixed dtypes: computed in float64
        assert got == pytest.approx(expected, rel=1e-6)


def test_attractor_statistics():
    rng = np.random.default_rng(0)
    model, ref = rng.normal(1.0, 2.0, size=(400, 2)), rng.normal(0.0, 1.0, size=(300, 2))
    out = attractor_statistics(torch.tensor(model), torch.tensor(ref))
    assert set(out) == {"wasserstein", "model_mean", "model_std", "reference_mean", "reference_std"}
    for key, value in (
        ("model_mean", model.mean(0)),
        ("model_std", model.std(0)),
        ("reference_mean", ref.mean(0)),
        ("reference_std", ref.std(0)),
    ):
        assert isinstance(out[key], list) and out[key] == pytest.approx(value.tolist())
    assert out["wasserstein"] == pytest.approx([stats.wasserstein_distance(model[:, i], ref[:, i]) for i in range(2)])


def test_both_wings_share():
    level = lorenz_wing_level()
    assert level == pytest.approx(0.5 * math.sqrt(BETA * (RHO - 1)))  # fixed points at +-8.49
    x = torch.tensor(lorenz_states(runs=6, steps=4000)[..., 0])  # 20 s each
    assert both_wings_share(x, level) == 1.0
    one_sided = 8.5 + 3 * torch.sin(torch.linspace(0, 200, 4000, dtype=F64)).expand(3, 4000)  # a cycle around +8.5
    assert both_wings_share(one_sided, level) == 0.0
    assert both_wings_share(-one_sided, level) == 0.0
    assert both_wings_share(torch.cat([x[:1], one_sided[:1]]), level) == 0.5


# ---------------------------------------------------------------------------- valid prediction time
def test_valid_prediction_time_of_an_exact_forecast_is_inf():
    truth = free_run(rotation(0.3), torch.tensor([[1.0, 0.0], [0.3, 0.4]], dtype=F64), steps=40)
    pred = free_run(rotation(0.3), truth[:, 0], steps=40)
    vpt = valid_prediction_time(pred, truth, truth.reshape(-1, 2).std(0))
    assert vpt.tolist() == [math.inf, math.inf]


def test_valid_prediction_time_crosses_where_computed_by_hand():
    # normalised error at step j is a * j (the same in every component): valid while a * j <= 0.5
    scale = torch.tensor([1.0, 2.0, 4.0], dtype=F64)
    a = torch.tensor([0.07, 0.3, 0.6, 1e-3], dtype=F64)
    j = torch.arange(20, dtype=F64)
    truth = torch.randn(4, 20, 3, dtype=F64, generator=torch.Generator().manual_seed(0))
    pred = truth + a[:, None, None] * j[None, :, None] * scale
    # a = 0.07: 0.07 * 7 = 0.49 <= 0.5 < 0.56 -> steps 0..7 valid = 8; 0.3: 0, 0.3 -> 2; 0.6: 1; 1e-3: never
    assert valid_prediction_time(pred, truth, scale).tolist() == [8.0, 2.0, 1.0, math.inf]
    assert valid_prediction_time(pred, truth, scale, threshold=0.25).tolist() == [4.0, 1.0, 1.0, math.inf]
    # only leading steps count; a NaN forecast is invalid
    back = truth.clone()
    back[0, 3] += 10.0
    back[1, 5] = math.nan
    assert valid_prediction_time(back, truth, scale)[:2].tolist() == [3.0, 5.0]


def test_summarize_valid_time_by_hand():
    out = summarize_valid_time(torch.tensor([2.0, 4.0, math.inf, 6.0]), horizon=10, dt=0.01, largest_exponent=0.9)
    # censored inf -> 10: values 2, 4, 10, 6
    assert out["mean_steps"] == pytest.approx(5.5)
    assert out["std_steps"] == pytest.approx(math.sqrt((3.5**2 + 1.5**2 + 4.5**2 + 0.5**2) / 4))
    assert out["median_steps"] == pytest.approx(5.0)
    assert out["censored_share"] == 0.25
    assert out["mean_seconds"] == pytest.approx(0.055) and out["median_seconds"] == pytest.approx(0.05)
    assert out["mean_lyapunov_times"] == pytest.approx(0.0495) and out["median_lyapunov_times"] == pytest.approx(0.045)
    for exponent in (None, 0.0, -0.2):
        out = summarize_valid_time(torch.tensor([3.0]), horizon=10, dt=0.1, largest_exponent=exponent)
        assert out["mean_lyapunov_times"] is None and out["median_lyapunov_times"] is None


# ---------------------------------------------------------------------------- oscillators
def test_dominant_period_of_sines():
    dt, t = 0.05, torch.arange(200, dtype=F64) * 0.05  # 10 s
    periods = [0.37, 1.23, 2.9]  # 27, 8.1 and 3.4 periods in the window
    x = torch.stack(
        [
            torch.stack([torch.sin(2 * math.pi * t / p + k), 0.3 * torch.cos(2 * math.pi * t / p + k) + 5.0], dim=-1)
            for k, p in enumerate(periods)
        ]
    )  # [3, 200, 2], a constant offset on the second component
    torch.testing.assert_close(dominant_period(x, dt), torch.tensor(periods, dtype=F64), rtol=0.01, atol=0)
    assert math.isnan(dominant_period(torch.ones(1, 50, 2), dt).item())


def test_amplitude_ratio_closed_form():
    # period 20 steps; the last 40-step window is the first shifted by 160 steps = 8 whole periods
    j = torch.arange(200, dtype=F64)
    wave = torch.sin(2 * math.pi * j / 20 + 0.3)
    gamma = 0.01  # per step
    x = torch.stack(
        [
            torch.stack([wave, 2 * wave + 7.0], dim=-1),  # constant amplitude, a static offset
            torch.exp(-gamma * j)[:, None] * torch.stack([wave, wave], dim=-1),  # damped
            torch.exp(gamma * j)[:, None] * torch.stack([wave, -wave], dim=-1),  # growing
        ]
    )
    expected = torch.tensor([1.0, math.exp(-gamma * 160), math.exp(gamma * 160)], dtype=F64)
    torch.testing.assert_close(amplitude_ratio(x, window=40), expected, rtol=1e-10, atol=0)


# ---------------------------------------------------------------------------- bad input
def test_bad_input_says_what_to_change():
    f = rotation(0.3)
    with pytest.raises(ValueError, match=r"\[N, d\]"):
        lyapunov_spectrum(f, torch.zeros(2, dtype=F64), steps=5)
    with pytest.raises(ValueError, match="dt"):
        lyapunov_spectrum(f, torch.zeros(1, 2, dtype=F64), steps=5, dt=0.0)
    with pytest.raises(ValueError, match="n_exponents"):
        lyapunov_spectrum(f, torch.zeros(1, 2, dtype=F64), steps=5, n_exponents=3)
    with pytest.raises(ValueError, match="steps"):
        free_run(f, torch.zeros(1, 2), steps=0)
    with pytest.raises(ValueError, match=r"\[N, d\]"):
        jacobian(f, torch.zeros(2, 3, 4))
    with pytest.raises(ValueError, match="same shape"):
        valid_prediction_time(torch.zeros(2, 5, 3), torch.zeros(2, 6, 3), torch.ones(3))
    with pytest.raises(ValueError, match=r"\[B, p, D\]"):
        valid_prediction_time(torch.zeros(5, 3), torch.zeros(5, 3), torch.ones(3))
    with pytest.raises(ValueError, match="scale"):
        valid_prediction_time(torch.zeros(2, 5, 3), torch.zeros(2, 5, 3), torch.ones(2))
    with pytest.raises(ValueError, match="threshold"):
        valid_prediction_time(torch.zeros(2, 5, 3), torch.zeros(2, 5, 3), torch.ones(3), threshold=0.0)
    with pytest.raises(ValueError, match="horizon"):
        summarize_valid_time(torch.tensor([12.0]), horizon=10, dt=0.1, largest_exponent=None)
    with pytest.raises(ValueError, match="dt"):
        summarize_valid_time(torch.tensor([2.0]), horizon=10, dt=-1.0, largest_exponent=None)
    with pytest.raises(ValueError, match="1-D"):
        wasserstein_1d(torch.zeros(3, 2), torch.zeros(3))
    with pytest.raises(ValueError, match="components"):
        attractor_statistics(torch.zeros(5, 2), torch.zeros(5, 3))
    with pytest.raises(ValueError, match="level"):
        both_wings_share(torch.zeros(2, 10), level=0.0)
    with pytest.raises(ValueError, match=r"\[R, T\]"):
        both_wings_share(torch.zeros(10), level=1.0)
    with pytest.raises(ValueError, match=r"\[R, T, D\]"):
        dominant_period(torch.zeros(4, 10), dt=0.1)
    with pytest.raises(ValueError, match="dt"):
        dominant_period(torch.zeros(1, 10, 1), dt=0.0)
    with pytest.raises(ValueError, match="window"):
        amplitude_ratio(torch.zeros(1, 10, 1), window=11)


# ---------------------------------------------------------------------------- the composite report
def test_dynamics_report_of_the_true_lorenz_system_recovers_its_attractor(one_thread):
    """The true equations as f, a projection on x as g: the model's statistics are the system's own
    (exponent near 0.9 like the true one, both wings on every run, x distribution close to the data's)."""
    f = LorenzDataModule(data_dir="unused").true_transition()
    starts = torch.from_numpy(lorenz_states(8, 1, seed=1)[:, 0]).double()
    reference = torch.from_numpy(lorenz_states(32, 10_000, seed=2)[..., :1]).reshape(
        -1, 1
    )  # long runs: the invariant measure
    report = dynamics_report(
        f,
        Projection([0]),
        starts,
        DT,
        reference=reference,
        lyapunov_steps=2000,
        transient=1000,
        align=600,
        free_steps=20_000,
        wing_level=lorenz_wing_level(),
    )
    assert 0.7 < report["lyapunov"]["largest"] < 1.1  # 8 runs of 10 time units: a coarse estimate of 0.906
    free = report["free_run"]
    assert free["both_wings_share"] == 1.0 and free["finite_share"] == 1.0
    assert free["wasserstein"][0] < 1.0  # a point at the mean is ~6.8 away
    assert free["model_std"][0] == pytest.approx(free["reference_std"][0], rel=0.1)
    # a contracting map instead: no chaos, both runs collapse to the origin, far from the data
    report = dynamics_report(
        lambda x: 0.9 * x,
        Projection([0]),
        starts,
        DT,
        reference=reference,
        lyapunov_steps=100,
        transient=10,
        align=0,
        free_steps=100,
        wing_level=lorenz_wing_level(),
        true_f=lambda x: 0.5 * x,
        true_starts=starts,
    )
    assert report["lyapunov"]["largest"] == pytest.approx(math.log(0.9) / DT, rel=1e-6)
    assert report["lyapunov_true"]["exponents"] == pytest.approx([math.log(0.5) / DT] * 3, rel=1e-6)
    assert report["free_run"]["both_wings_share"] == 0.0 and report["free_run"]["wasserstein"][0] > 5
    # free runs from their own starts (more than the spectrum's): the identity map stays where it starts
    free_starts = torch.arange(30.0, dtype=torch.float64).view(10, 3)
    report = dynamics_report(
        lambda x: x,
        Projection([0]),
        starts,
        DT,
        reference=reference,
        lyapunov_steps=10,
        transient=0,
        align=0,
        free_steps=5,
        free_starts=free_starts,
    )
    assert report["lyapunov"]["runs"] == 8 and report["free_run"]["runs"] == 10
    assert report["free_run"]["model_mean"][0] == pytest.approx(free_starts[:, 0].mean().item())


def test_short_sequences_from_off_attractor_starts_are_not_the_attractors_distribution():
    """Why the free runs are compared with the long training trajectories, not the 10-s test sequences: the
    true system's own long runs are far from 64 test-like sequences (2000 steps from uniform starts) in
    W1, and close to 100 training-like trajectories of 10,000 steps (the README states both figures)."""
    x0 = np.random.default_rng(3).uniform(-10, 10, size=(16, 3))
    long_runs = torch.from_numpy(lorenz_rk4(x0, 22_000, DT)[:, 2000:, 0].reshape(-1))
    test_like = torch.from_numpy(lorenz_states(64, 2000, seed=5, transient=0)[..., 0].reshape(-1))
    train_like = torch.from_numpy(lorenz_states(100, 10_000, seed=7, transient=0)[..., 0].reshape(-1))
    assert 1.5 < wasserstein_1d(long_runs, test_like) < 2.3
    assert wasserstein_1d(long_runs, train_like) < 0.6


def test_the_true_systems_exponents_are_computed_again_over_a_cache_cut_short(tmp_path):
    """``reference_exponents`` caches the true system's exponents in the data's cache folder; a cache file cut short
    (a run stopped while writing it) is computed again, not a crash at the end of a test run. The system: a diagonal
    linear map, whose exponents are ``log|a_i| / dt`` in closed form."""
    import json
    from types import SimpleNamespace

    from ssm_ms.forecasting.valid_time import reference_exponents

    scale, dt = torch.tensor([1.5, 0.5], dtype=torch.float64), 0.1
    test = SimpleNamespace(arrays={"state": np.ones((4, 3, 2))})
    dm = SimpleNamespace(
        true_transition=lambda: lambda x: x * scale, sample_period=dt, cache_dir=str(tmp_path), datasets={"test": test}
    )
    settings = {"runs": 4, "lyapunov_steps": 20, "transient": 0, "align": 0}
    first = reference_exponents(dm, settings)
    (cache,) = tmp_path.glob("true_exponents_*.json")
    cache.write_text(cache.read_text()[:10])  # cut short
    again = reference_exponents(dm, settings)
    expected = (torch.log(scale) / dt).tolist()
    assert again["exponents"] == pytest.approx(expected) and first["exponents"] == pytest.approx(expected)
    assert json.loads(cache.read_text())["exponents"] == pytest.approx(expected)  # and cached whole again
