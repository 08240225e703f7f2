"""Control on a learned model (ssm_ms.control): the planner's pieces against their formulas and known systems, the
angle read from rendered frames, and the whole closed loop swinging the true pendulum up."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from datamodules.pendulum import PendulumDataModule
from datamodules.pendulum_render import quantize, render_paper
from datamodules.pendulum_sim import pendulum_model, simulate
from ssm_ms.control.cost import SwingUpCost, upright_error
from ssm_ms.control.goals import DistilledFeatures, ink_angle_features
from ssm_ms.control.mppi import MPPISettings, RecedingHorizon, mppi
from ssm_ms.control.plant import TruePendulum


def test_true_pendulum_is_the_simulators_frame():
    """The planner's true model over one 0.1 s frame against Pinocchio's simulation of the data (RK4, 5 ms)."""
    model = pendulum_model(1)
    q0, v0 = np.array([[0.3], [2.5], [-1.0]]), np.array([[0.0], [1.0], [-3.0]])
    torque = np.array([[[2.0]], [[-3.0]], [[0.5]]])
    q, v, _ = simulate(model, model.createData(), q0, v0, 2, 20, 5e-3, 0.0, torque)
    x = torch.tensor(np.concatenate([q0, v0], 1))
    exact = TruePendulum(0.1, substeps=20)(x, torch.tensor(torque[:, 0]))
    torch.testing.assert_close(exact, torch.tensor(np.concatenate([q[:, 1], v[:, 1]], 1)), rtol=0, atol=1e-9)
    coarse = TruePendulum(0.1, substeps=5)(x, torch.tensor(torque[:, 0]))
    assert (coarse - exact).abs().max() < 1e-3  # the planner's cheaper model


def test_the_angle_read_from_rendered_frames():
    """The ink's centroid about the frame's centre gives the pendulum's angle: rendered at known angles, clean and
    noisy as the data's."""
    angles = np.linspace(-math.pi, math.pi, 37)[:-1]
    frames = torch.from_numpy(render_paper(angles[:, None], 24)).clamp(0, 1)
    sc = ink_angle_features(frames, (12.0, 12.0))
    read = torch.atan2(sc[:, 0], sc[:, 1]).numpy()
    error = np.angle(np.exp(1j * (read - angles)))
    assert np.abs(error).max() < 0.06
    noisy = (frames + 0.2 * torch.randn(frames.shape, generator=torch.Generator().manual_seed(0))).clamp(0, 1)
    sc = ink_angle_features(noisy, (12.0, 12.0), floor=0.5)
    assert np.abs(np.angle(np.exp(1j * (torch.atan2(sc[:, 0], sc[:, 1]).numpy() - angles)))).max() < 0.2


def test_swing_up_cost_is_its_formula():
    torch.manual_seed(0)
    b, k, h = 2, 3, 4
    phi = torch.randn(b, k, h + 1) * 2
    states = torch.stack([torch.sin(phi), torch.cos(phi)], -1)
    inputs = torch.randn(b, k, h, 1)
    cost = SwingUpCost(lambda x: x, dt=0.1, w_velocity=0.05, w_input=1e-3)(states, inputs)
    expected = torch.zeros(b, k)
    for i in range(b):
        for j in range(k):
            p = phi[i, j, 1:]
            height = ((1 + torch.cos(p)) / 2).mean()
            turn = torch.atan2(torch.sin(p[1:] - p[:-1]), torch.cos(p[1:] - p[:-1])) / 0.1
            motion = ((1 - torch.cos(p[1:])) / 2 * turn**2).mean()
            expected[i, j] = height + 0.05 * motion + 1e-3 * inputs[i, j].pow(2).mean()
    torch.testing.assert_close(cost, expected, rtol=1e-5, atol=1e-6)
    bounded = SwingUpCost(lambda x: x, dt=0.1, w_velocity=0.05, w_input=1e-3, max_energy=5.0, w_energy=0.2)
    over = torch.zeros(b, k)
    for i in range(b):
        for j in range(k):
            p = phi[i, j, 1:]
            turn = torch.atan2(torch.sin(p[1:] - p[:-1]), torch.cos(p[1:] - p[:-1])) / 0.1
            energy = 0.5 * turn**2 + 9.81 * (1 - torch.cos(p[1:]))  # unit mass on a unit link, 0 hanging at rest
            over[i, j] = 0.2 * (energy - 5.0).clamp_min(0).pow(2).mean()
    assert over.min() > 0
    torch.testing.assert_close(bounded(states, inputs), expected + over, rtol=1e-5, atol=1e-3)
    still = torch.stack([torch.zeros(1, 1, h + 1), torch.ones(1, 1, h + 1)], -1)  # hanging at rest: within it
    torch.testing.assert_close(bounded(still, inputs[:1, :1]), SwingUpCost(lambda x: x, 0.1)(still, inputs[:1, :1]))
    assert upright_error(torch.tensor([math.pi, 0.0, -math.pi + 0.1, 3 * math.pi])).tolist() == pytest.approx(
        [0.0, math.pi, 0.1, 0.0], abs=1e-6
    )


def test_mppi_drives_a_point_to_its_target_within_the_bounds():
    """x+ = x + 0.1 u, cost (x - 1)^2: the receding plan brings x from 0 to 1 and never asks for more than u_max."""
    settings = MPPISettings(horizon=10, samples=128, iterations=2, noise_std=1.0, temperature=0.1, u_min=-2, u_max=2)

    def f(x, u):
        return x + 0.1 * u

    def cost(states, inputs):
        return (states[..., 0] - 1.0).pow(2).sum(-1)

    controller = RecedingHorizon(f, cost, settings, batch=3, input_dim=1)
    x = torch.zeros(3, 1)
    for _ in range(20):
        u = controller(x)
        assert u.abs().max() <= 2.0
        x = f(x, u)
    assert (x - 1).abs().max() < 0.1
    plan, best = mppi(f, cost, torch.ones(1, 1), torch.zeros(1, 5, 1), settings)
    assert plan.abs().max() < 0.5 and best.item() < 0.05  # at the target: stay


def test_offset_free_planning_cancels_a_constant_model_error():
    """The system x+ = x + 0.1 u + 0.1, planned on the model x+ = x + 0.1 u towards x = 1: plain receding-horizon
    planning holds x about the model's error (0.1) off the target, offset-free planning (gain 1) at the target."""
    settings = MPPISettings(horizon=10, samples=128, iterations=2, noise_std=1.0, temperature=0.1, u_min=-2, u_max=2)

    def model(x, u):
        return x + 0.1 * u

    def cost(states, inputs):
        return (states[..., 0] - 1.0).pow(2).sum(-1)

    def settle(gain: float) -> float:
        controller = RecedingHorizon(model, cost, settings, batch=3, input_dim=1, offset_gain=gain)
        x, seen = torch.zeros(3, 1), []
        for _ in range(40):
            x = model(x, controller(x)) + 0.1
            seen.append((x - 1).abs().mean().item())
        return sum(seen[-10:]) / 10

    assert settle(0.0) > 0.07
    assert settle(1.0) < 0.03
    with pytest.raises(ValueError, match="offset_gain"):
        RecedingHorizon(model, cost, settings, batch=1, input_dim=1, offset_gain=1.5)


def test_offset_estimate_is_the_filtered_one_step_error():
    """The planner's offset against a naive running filter of x[t] - f(x[t-1], u[t-1]), with the inputs it returned
    or, where given, the ones applied instead."""
    settings = MPPISettings(horizon=4, samples=16, iterations=1, noise_std=0.5, u_min=-1, u_max=1)

    def f(x, u):
        return 0.9 * x + torch.sin(x) * u

    def cost(states, inputs):
        return states.pow(2).sum((-1, -2))

    gain, generator = 0.3, torch.Generator().manual_seed(1)
    states = [torch.randn(2, 3, generator=generator) for _ in range(4)]
    controller = RecedingHorizon(f, cost, settings, batch=2, input_dim=1, offset_gain=gain)
    u0 = controller(states[0])
    assert controller.offset is None
    u1 = controller(states[1])
    expected = gain * (states[1] - f(states[0], u0))
    torch.testing.assert_close(controller.offset, expected)
    other = torch.full((2, 1), 0.7)
    controller(states[2], applied=other)
    expected = (1 - gain) * expected + gain * (states[2] - f(states[1], other))
    torch.testing.assert_close(controller.offset, expected)
    assert not torch.allclose(u1, other)


def test_distilled_features_fit_a_known_map():
    torch.manual_seed(0)
    states = torch.rand(5000, 3) * 6 - 3

    def target(x):
        return torch.stack([torch.sin(x[:, 0]), torch.cos(x[:, 0])], 1)

    net, error = DistilledFeatures.fit(states, target, steps=1500)
    assert error < 5e-3
    torch.testing.assert_close(net(states[:5]), target(states[:5]), atol=0.15, rtol=0)
    # the same map on states 1000x smaller and off the origin (a model's states have the scale training gave them):
    # fitted as well
    small = 0.7 + states / 1000
    net, error = DistilledFeatures.fit(small, lambda x: target((x - 0.7) * 1000), steps=1500)
    assert error < 5e-3
    torch.testing.assert_close(net(small[:5]), target(states[:5]), atol=0.15, rtol=0)


def test_the_planner_reads_the_angle_head_of_a_camera_and_angle_decoder():
    """With camera and joint angle, the planner's angle readout (ClosedLoop._distill) learns what g's angle head
    draws, not the ink of the frame it draws: a known decoder whose angle head shows the angle x[0] and whose frame
    always shows the chain pointing right (ink angle pi / 2); with a camera alone it reads that ink."""
    from types import SimpleNamespace

    from ssm_ms.control.module import ClosedLoop

    frame = torch.zeros(24, 24)
    frame[11:13, 13:24] = 1.0  # a bar from the centre to the right edge: the ink's angle pi / 2

    def g(x):  # [N, 2] -> [N, 576 + 2]: the frame, then (sin, cos) of x[0]
        image = frame.flatten().expand(len(x), -1)
        return torch.cat([image, torch.sin(x[:, :1]), torch.cos(x[:, :1])], 1)

    def loop(streams):
        fake = SimpleNamespace(
            distill_settings={"rollout_steps": 3, "steps": 1500, "pivot": None},
            seed=0,
            settings=SimpleNamespace(u_min=-3.0, u_max=3.0),
            frame_dt=0.1,
            f=lambda x, u: x + 0.1 * torch.cat([x[:, 1:], u], 1),  # x = (angle, velocity)
            ssm=SimpleNamespace(g=g),
            from_frames=lambda y: y,
            streams=streams,
            ink_angle=lambda frames: ink_angle_features(frames, (12.0, 12.0)),  # about the frame's centre
        )
        fake.drawn_angle = lambda x: ClosedLoop.drawn_angle(fake, x)
        return fake

    both = lambda y: {"image": y[:, :576].reshape(-1, 1, 24, 24), "angle": y[:, 576:]}  # noqa: E731
    camera = lambda y: {"image": y[:, :576].reshape(-1, 1, 24, 24)}  # noqa: E731
    torch.manual_seed(0)
    nodes = torch.stack([torch.rand(400) * 6 - 3, torch.randn(400)], 1)
    test = torch.stack([torch.linspace(-2.5, 2.5, 11), torch.zeros(11)], 1)
    both_loop, camera_loop = loop(both), loop(camera)
    features, error = ClosedLoop._distill(both_loop, ClosedLoop.visited_states(both_loop, nodes))
    assert error < 5e-3
    torch.testing.assert_close(features(test), torch.stack([test[:, 0].sin(), test[:, 0].cos()], 1), atol=0.1, rtol=0)
    features, _ = ClosedLoop._distill(camera_loop, ClosedLoop.visited_states(camera_loop, nodes))
    torch.testing.assert_close(features(test), torch.tensor([[1.0, 0.0]]).expand(11, 2), atol=0.05, rtol=0)


def true_control(tmp_path: Path, *args: str) -> None:
    """``cli.py test`` of configs/pendulum_true_control.yaml with its data, results and logs under ``tmp_path`` (3
    timing steps, no progress bar), then ``args``."""
    from experiments.cli import reports
    from ssm_ms.cli import main

    where = ["--data.init_args.data_dir", str(tmp_path / "data"), "--model.init_args.results_dir", str(tmp_path)]
    quiet = ["--trainer.logger", "false", "--trainer.default_root_dir", str(tmp_path)]
    quiet += ["--trainer.enable_progress_bar", "false", "--model.init_args.timing_steps", "3"]
    with reports():  # the report beside the results file, as `python cli.py test` renders it
        main(["test", "--config", "configs/pendulum_true_control.yaml", *where, *quiet, *args])


def test_the_closed_loop_swings_the_true_pendulum_up(tmp_path):
    """The whole loop through the command line, planning on the true model: two episodes from hanging, both upright
    and still over their last 2 s, the results file and its figures written."""
    true_control(tmp_path, "--data.init_args.n_test", "2", "--model.init_args.figures_dir", str(tmp_path / "figures"))
    result = json.loads((tmp_path / "pendulum_control.json").read_text())["runs"]["true model, true state"]
    assert result["summary"]["true model, true state/episodes/success"]["mean"] == 1.0
    assert result["summary"]["true model, true state/episodes/upright_error_final"]["mean"] < 0.3
    assert (tmp_path / "figures" / "pendulum_control_true_model_true_state.gif").is_file()
    assert "Closed-loop control results" in (tmp_path / "pendulum_control.md").read_text()


def test_the_encoder_estimates_step_by_step_what_it_infers_from_the_whole_sequence(tmp_path):
    """The closed loop's encoder estimator (one frame and the torque before it at a time) gives at every step the
    state the encoder infers from the whole sequence so far; an encoder trained on another SSM is refused."""
    import lightning.pytorch as pl

    from ssm_ms.control.estimators import EncoderEstimator, load_encoder
    from ssm_ms.inference import StateEncoderModule

    root = Path(__file__).resolve().parents[1]
    ssm_file = root / "pretrained" / "pendulum.ckpt"
    torch.manual_seed(0)
    module = StateEncoderModule(str(ssm_file), n_filter=5, encoder={"preset": "pendulum", "hidden": 16})
    with torch.no_grad():
        module.latent_mean.normal_()
        module.latent_std.uniform_(0.5, 2.0)
        module.latent_stats_ready.fill_(True)
    path = tmp_path / "encoder.ckpt"
    torch.save(
        {
            "state_dict": module.state_dict(),
            "hyper_parameters": dict(module.hparams),
            "pytorch-lightning_version": pl.__version__,
        },
        path,
    )
    loaded = load_encoder(str(path), str(ssm_file), module.ssm)
    y = torch.rand(3, 6, 1, 24, 24)
    want = module.infer(y)
    estimator = EncoderEstimator(loaded, lambda v: v, lambda u: u)
    got = [estimator.start(y[:, 0])] + [estimator.next(torch.zeros(3, 0), y[:, t]) for t in range(1, 6)]
    torch.testing.assert_close(torch.stack(got, 1), want, rtol=1e-5, atol=1e-5)
    other = StateEncoderModule(str(root / "pretrained" / "pendulum_fc.ckpt"), n_filter=5)
    with pytest.raises(ValueError, match="was trained on another SSM than ssm_checkpoint"):
        load_encoder(str(path), str(root / "pretrained" / "pendulum_fc.ckpt"), other.ssm)
    with pytest.raises(ValueError, match="no encoder checkpoint at"):
        load_encoder(str(tmp_path / "none.ckpt"), str(ssm_file), module.ssm)
    ssm_file_other = tmp_path / "other.ckpt"  # the same networks, one weight moved: refused too
    saved = torch.load(ssm_file, weights_only=True)
    key = next(k for k, v in saved["state_dict"].items() if k.startswith("f.") and v.is_floating_point())
    saved["state_dict"][key] = saved["state_dict"][key] + 1.0
    torch.save(saved, ssm_file_other)
    moved = StateEncoderModule(str(ssm_file_other), n_filter=5, encoder={"preset": "pendulum", "hidden": 16})
    with pytest.raises(ValueError, match=f"differ in {key}"):
        load_encoder(str(path), str(ssm_file), moved.ssm)


def test_recorded_episodes_become_training_data(tmp_path):
    """The closed loop's record (true model, with exploration) read back by the pendulum data module: appended after
    the generated trajectories, each recorded trajectory what the simulator does under its recorded torques from its
    first state, its clean frames the rendering of its angles; a file of another system refused in one line."""
    record = tmp_path / "episodes.npz"
    true_control(
        tmp_path,
        *("--data.init_args.n_test", "3", "--data.init_args.duration", "1.0"),
        *("--model.init_args.seconds", "1.0", "--model.init_args.success_seconds", "0.5"),
        *("--model.init_args.exploration", "0.5", "--model.init_args.record", str(record)),
        "--model.init_args.planner",
        "{horizon: 5, samples: 32, iterations: 1, noise_std: 1.5, u_min: -3.0, u_max: 3.0}",
        *("--model.init_args.figures_dir", "null", "--model.init_args.timing_steps", "1"),
    )
    args = dict(n_train=2, n_test=1, duration=1.0, max_energy=22.0, torque_limit=3.0, data_dir=str(tmp_path / "data"))
    dm = PendulumDataModule(**args, recorded=[str(record)])
    assert dm.num_train_trajectories == 5
    dm.setup("fit")
    train = dm.datasets["train"].arrays
    plain = PendulumDataModule(**args)
    plain.setup("fit")
    np.testing.assert_array_equal(train["y"][:2], plain.datasets["train"].arrays["y"])  # generated ones unchanged
    state, u = np.asarray(train["state"][2:], np.float64), np.asarray(train["u"][2:], np.float64)
    assert np.abs(u).max() <= 3.0 and len(np.unique(u.round(6))) > 10
    model = pendulum_model(1)
    q, v, _ = simulate(model, model.createData(), state[:, 0, :1], state[:, 0, 1:], 10, 20, 5e-3, 0.0, u)
    np.testing.assert_allclose(np.concatenate([q, v], -1), state, atol=2e-4)  # recorded as float32
    clean = np.stack([quantize(render_paper(np.asarray(a, np.float32), 24)) for a in state[..., :1]])
    assert np.abs(clean.astype(int) - np.asarray(train["y_clean"][2:]).astype(int)).max() <= 1
    with pytest.raises(ValueError, match=r"recorded on another system: image_size 24 \(data: 32\)"):
        PendulumDataModule(**{**args, "image_size": 32}, recorded=[str(record)]).recorded_info()
    with pytest.raises(ValueError, match="the data need"):
        PendulumDataModule(**{**args, "duration": 2.0}, recorded=[str(record)]).recorded_info()


def test_an_episode_succeeds_when_every_angle_of_its_final_window_is_within_tolerance():
    """ClosedLoop.judge against a naive loop: 1 s episodes of 0.1 s periods, success over the last 0.3 s (3 angles)
    within 0.3 rad of upright; one angle of the window outside fails the episode, earlier ones do not count."""
    from ssm_ms.control.module import ClosedLoop

    loop = ClosedLoop(true_model=True, seconds=1.0, success_seconds=0.3, tolerance=0.3, figures_dir=None)
    loop.frame_dt = 0.1
    rng = np.random.default_rng(0)
    angles = np.pi + rng.uniform(-0.25, 0.25, size=(4, 11))
    angles[1, -2] = np.pi + 0.4  # in the window: fails
    angles[2, -4] = np.pi - 1.0  # before the window: still succeeds
    angles[3, -1] = -np.pi + 0.2  # upright from the other side (wrapped): succeeds
    error, window, final, success = loop.judge(torch.from_numpy(angles))
    naive = [all(abs((a - np.pi + np.pi) % (2 * np.pi) - np.pi) < 0.3 for a in row[-3:]) for row in angles]
    assert window == 3 and final.shape == (4, 3)
    assert success.tolist() == naive == [True, False, True, True]


def test_an_unknown_estimator_setting_is_named():
    from ssm_ms.control.module import ClosedLoop

    with pytest.raises(ValueError, match=r"estimator takes .* got \['measurement_std'\]"):
        ClosedLoop(true_model=True, estimator={"measurement_std": 0.2}, figures_dir=None)


def test_closed_loop_episodes_plan_on_the_true_state_or_on_the_estimate():
    """ClosedLoop.episodes: the true model's controller sees the simulator's state; a learned model's sees its
    estimator's output after each measurement; measurements, torques (exploration noise included) and true angles
    are recorded per period, and the planner is told the torque applied (a scalar system stepped by hand)."""
    from types import SimpleNamespace

    from ssm_ms.control.module import ClosedLoop

    class Env:  # x+ = x + u, measured as y = 10 x
        params = {"n_links": 1}

        def reset(self, q, v):
            self.q = q.copy()
            return 10 * self.q

        @property
        def state(self):
            return np.concatenate([self.q, np.zeros_like(self.q)], 1)

        def step(self, u):
            self.q = self.q + u
            return 10 * self.q

    class Estimator:  # reads y / 10, biased by +1
        def start(self, y):
            return y.float() / 10 + 1

        def next(self, u, y):
            return y.float() / 10 + 1

    start = np.array([[2.0, 0.0], [-1.0, 0.0]])  # angles, then velocities
    for learned, exploration in ((False, 0.0), (True, 0.0), (True, 0.3)):
        seen, told = [], []

        def controller(x, applied=None, seen=seen, told=told):
            seen.append(x[:, :1].clone())
            told.append(applied)
            return -0.5 * x[:, :1]

        loop = SimpleNamespace(
            seconds=0.3,
            frame_dt=0.1,
            env=Env(),
            controller=lambda b, c=controller: c,
            ssm=object() if learned else None,
            estimator=Estimator,
            seed=0,
            exploration=exploration,
            settings=SimpleNamespace(u_min=-10.0, u_max=10.0),
        )
        loop.episodes = lambda start, loop=loop, **k: ClosedLoop.episodes(loop, start, **k)
        run = loop.episodes(start)
        frames, inputs, angles = run["measurements"], run["inputs"], run["states"][..., 0].double().numpy()
        q, bias = np.array([[2.0], [-1.0]]), 1.0 if learned else 0.0
        assert told[0] is None
        for t in range(3):
            np.testing.assert_allclose(seen[t].numpy(), q + bias, rtol=1e-6)
            np.testing.assert_allclose(angles[:, t], q[:, 0], rtol=1e-6)
            np.testing.assert_allclose(frames[t].numpy(), 10 * q, rtol=1e-6)
            u = inputs[:, t].numpy()
            planned = -0.5 * (q + bias)
            assert np.allclose(u, planned, rtol=1e-6) == (exploration == 0)
            if t:
                np.testing.assert_allclose(told[t].numpy(), inputs[:, t - 1].numpy())
            q = q + u
        np.testing.assert_allclose(angles[:, 3], q[:, 0], rtol=1e-6)


def test_success_rates_carry_their_wilson_interval():
    """The interval at 0 and n successes in closed form (z^2 / (n + z^2) and n / (n + z^2)), 92 of 100 as tables give
    it (0.850-0.959), and the results' cell that prints it."""
    from experiments.results import score_cell
    from ssm_ms.control.scoring import wilson_interval

    z2 = 1.959964**2
    assert wilson_interval(0, 20) == pytest.approx((0.0, z2 / (20 + z2)))
    assert wilson_interval(20, 20) == pytest.approx((20 / (20 + z2), 1.0))
    assert wilson_interval(92, 100) == pytest.approx((0.8501, 0.9589), abs=1e-4)
    entry = {"mean": 0.9, "std": 0.3, "n": 20, "non_finite": 0, "ci95": [0.699, 0.972]}
    assert score_cell(entry) == "18/20 = 0.90 (95% CI 0.70-0.97)"
