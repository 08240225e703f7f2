"""The chart of a model's states (ssm_ms.inference.chart) and the UKF run on its code (the closed loop's chart UKF)."""

import math

import pytest
import torch

from ssm_ms.inference.chart import ChartSettings, StateChart


def sheet(n: int, seed: int = 0) -> torch.Tensor:
    """``[n, 5]``: points of a curved two-dimensional sheet in five dimensions (a square, side 2, and three nonlinear
    functions of it)."""
    gen = torch.Generator().manual_seed(seed)
    p, q = torch.rand(n, generator=gen) * 2 - 1, torch.rand(n, generator=gen) * 2 - 1
    return torch.stack([p, q, p * q, p.pow(2) - q.pow(2), torch.sin(2 * p)], 1)


def test_a_chart_needs_as_many_dimensions_as_its_states_have():
    """Fitted to a two-dimensional sheet in five dimensions, a 2-dimensional chart reconstructs held-out points of it
    closely and a 1-dimensional one cannot; its codes are standardised over the states it was fitted to."""
    states = sheet(3000)
    two = StateChart.fit(states, ChartSettings(dims=2, steps=1500, batch=256, lr=3e-3, width=64))
    one = StateChart.fit(states, ChartSettings(dims=1, steps=1500, batch=256, lr=3e-3, width=64))
    unseen = sheet(500, seed=1)
    scale = states.std(0)
    error2 = ((two.decode(two.encode(unseen)) - unseen) / scale).pow(2).mean()
    error1 = ((one.decode(one.encode(unseen)) - unseen) / scale).pow(2).mean()
    assert two.held_error < 0.01 and error2 < 0.01
    assert error1 > 10 * error2 and one.held_error > 10 * two.held_error
    codes = two.encode(states)
    torch.testing.assert_close(codes.mean(0), torch.zeros(2), atol=1e-4, rtol=0)
    torch.testing.assert_close(codes.std(0), torch.ones(2), atol=1e-4, rtol=0)


def test_chart_settings_name_what_is_wrong():
    with pytest.raises(ValueError, match="a chart takes dims, steps, batch, lr, width"):
        ChartSettings.parse({"dim": 3})
    with pytest.raises(ValueError, match=r"dims <= the state's size \(the state has 10\)"):
        ChartSettings.parse({"dims": 12}, state_dim=10)
    with pytest.raises(ValueError, match="a chart's dims is a whole number, got 'six'"):
        ChartSettings.parse({"dims": "six"})
    with pytest.raises(ValueError, match="a chart's lr is a number > 0, got 0"):
        ChartSettings.parse({"dims": 2, "lr": 0})
    assert ChartSettings.parse({"dims": 4, "steps": 10}, state_dim=10) == ChartSettings(dims=4, steps=10)


def test_the_ukf_on_a_chart_tracks_a_system_as_a_kalman_filter_does_and_stays_on_its_states():
    """A rotation of a plane embedded in four dimensions, seen through three noisy linear sensors: the UKF on a
    2-dimensional chart fitted to the system's states estimates the state nearly as well as the exact Kalman filter in
    the plane's own coordinates (written out here; the gap is the chart's own error, a few hundredths here, met by
    the process variance), far better than each measurement alone, and every estimate lies in the plane."""
    from ssm_ms.control.estimators import ChartUKFEstimator
    from ssm_ms.inference.ukf import UnscentedKalmanFilter

    torch.manual_seed(0)
    basis = torch.linalg.qr(torch.randn(4, 2))[0]  # the plane: x = basis @ z
    c, s = math.cos(0.2), math.sin(0.2)
    rot = torch.tensor([[c, -s], [s, c]])
    sensors = torch.randn(3, 4)
    noise_std = 0.1

    def f(x, u):
        return (x @ basis) @ rot.T @ basis.T

    def g(x):
        return x @ sensors.T

    starts = torch.randn(400, 2) * 1.2
    visited = [starts]
    for _ in range(15):
        visited.append(visited[-1] @ rot.T)
    states = torch.cat(visited) @ basis.T
    chart = StateChart.fit(states, ChartSettings(dims=2, steps=3000, batch=256, lr=3e-3, width=64))
    fz, gz = chart.pulled_back(f, g)
    nodes = chart.encode(states)
    ukf = UnscentedKalmanFilter(
        fz, gz, process_var=1e-3, measurement_var=noise_std**2, init_var=nodes.var(0).tolist(), state_dim=2
    )
    estimator = ChartUKFEstimator(ukf, chart, lambda y: y)

    z = torch.tensor([[1.0, -0.5], [-0.8, 0.3]])  # two episodes
    gen = torch.Generator().manual_seed(1)
    h = sensors @ basis  # the Kalman filter's measurement matrix in plane coordinates
    mean = (states @ basis).mean(0).expand(2, 2).clone()
    cov = torch.cov((states @ basis).T).expand(2, 2, 2).clone()
    chart_errors, kalman_errors, alone_errors, off_plane = [], [], [], []
    for t in range(40):
        if t:
            z = z @ rot.T
            mean, cov = mean @ rot.T, rot @ cov @ rot.T
        y = g(z @ basis.T) + noise_std * torch.randn(2, 3, generator=gen)
        x_hat = estimator.start(y) if t == 0 else estimator.next(torch.zeros(2, 0), y)
        gain = cov @ h.T @ torch.linalg.inv(h @ cov @ h.T + noise_std**2 * torch.eye(3))
        mean = mean + (gain @ (y - mean @ h.T).unsqueeze(-1)).squeeze(-1)
        cov = (torch.eye(2) - gain @ h) @ cov
        if t >= 20:
            chart_errors.append((x_hat - z @ basis.T).norm(dim=1))
            kalman_errors.append((mean - z).norm(dim=1))
            alone_errors.append((y @ torch.linalg.pinv(h).T - z).norm(dim=1))  # least squares on this frame
            off_plane.append((x_hat - x_hat @ basis @ basis.T).norm(dim=1))
    chart_rms = torch.stack(chart_errors).pow(2).mean().sqrt()
    kalman_rms = torch.stack(kalman_errors).pow(2).mean().sqrt()
    alone_rms = torch.stack(alone_errors).pow(2).mean().sqrt()
    assert chart_rms < kalman_rms + 0.05 and chart_rms < alone_rms / 2, (chart_rms, kalman_rms, alone_rms)
    assert torch.stack(off_plane).max() < 0.05


def test_the_closed_loop_estimates_on_a_chart_of_its_models_states(tmp_path):
    """``estimator: {chart: {dims: k}}`` on the shipped torque-driven model: the loop fits a chart of the states its
    angle readout is distilled on (the same chart as fitted here from them) and runs the UKF on the chart's
    ``k``-dimensional code; the planner is given the decoded code at every step (the plain UKF: its own mean); a
    chart larger than the model's state is refused before anything runs."""
    import numpy as np

    from datamodules.pendulum import PendulumDataModule
    from ssm_ms.control.estimators import ChartUKFEstimator, UKFEstimator
    from ssm_ms.control.module import ClosedLoop

    ssm = "pretrained/pendulum_torque.ckpt"
    with pytest.raises(ValueError, match=r"the state has 10"):
        ClosedLoop(ssm, estimator={"chart": {"dims": 11}})
    settings = {"process_var": 1e-3, "measurement_var": 0.1, "iterations": 2}
    small = ChartSettings(dims=3, steps=200, batch=256)
    dm = PendulumDataModule(n_links=1, n_train=8, n_test=2, torque_limit=3.0, data_dir=str(tmp_path))
    for chart in (None, small):
        estimator = {**settings, "chart": None if chart is None else chart.as_dict()}
        loop = ClosedLoop(
            ssm, estimator=estimator, seconds=0.3, success_seconds=0.1, distill={"steps": 20, "rollout_steps": 2}
        )
        loop.attach(dm)
        pairs, seen = [], []  # (the filter's mean, the estimate returned) at each update; what the planner got
        make, planner = loop.estimator, loop.controller

        def recorded(make=make, pairs=pairs):
            made = make()
            originals = {name: getattr(made, name) for name in ("start", "next")}
            for name, method in originals.items():

                def update(*args, method=method, made=made):
                    out = method(*args)
                    pairs.append((type(made), made.mean.clone(), out.clone()))
                    return out

                setattr(made, name, update)
            return made

        def watched(batch, planner=planner, seen=seen):
            plan = planner(batch)

            def controller(x, applied=None):
                seen.append(x.clone())
                return plan(x, applied=applied)

            return controller

        loop.estimator, loop.controller = recorded, watched
        loop.episodes(np.array([[0.2, 0.0], [-0.1, 0.1]]))
        assert len(seen) == 3 and len(pairs) == 4
        assert {kind for kind, _, _ in pairs} == {UKFEstimator if chart is None else ChartUKFEstimator}
        if chart is not None:
            assert loop.estimator_name == "UKF on a 3-dimensional chart"
            again = StateChart.fit(loop.visited_states(loop.ssm.training_states()), small, seed=loop.seed)
        for t, (_, mean, out) in enumerate(pairs):
            assert mean.shape == (2, 10 if chart is None else 3)
            torch.testing.assert_close(out, mean if chart is None else again.decode(mean))
            if t < 3:
                torch.testing.assert_close(seen[t], out)
