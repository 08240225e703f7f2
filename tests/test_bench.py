"""The benchmark scripts run (tiny sizes), and the reference structure they time is the same model as ours."""

import time
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmarks import (
    bench_allocator,
    bench_narrow_linear,
    bench_train_step,
    bench_two_jobs,
    bench_ukf,
    profile_decoder,
)
from benchmarks.reference_structure import RefDecoder, RefLocallyLinear, RefTrainer, ref_ukf
from ssm_ms.inference.ukf import UnscentedKalmanFilter
from ssm_ms.nets import ConvDecoder, LocallyLinearTransition, native
from ssm_ms.training.shooting import compile_unavailable_reason, multiple_shooting_loss

ROOT = Path(__file__).resolve().parents[1]


def reference_copy_of(f: LocallyLinearTransition, g: ConvDecoder) -> tuple[RefLocallyLinear, RefDecoder]:
    """The reference networks holding our networks' weights (its Linear(K d -> d) is our A_k rearranged)."""
    d, k = f.state_dim, f.n_matrices
    rf = RefLocallyLinear(d, k, f.beta[0].out_features).double()
    rg = RefDecoder(d).double()
    with torch.no_grad():
        rf.alpha.load_state_dict(f.beta.state_dict())
        a = f.matrices.view(k, d, d)  # A_k[j, i]
        rf.matrix.weight.copy_(a.permute(1, 2, 0).reshape(d, d * k))  # column i*K + k holds A_k[:, i]
        rg.fc_obs.load_state_dict(g.stem[0].state_dict())
        own = {k: v for k, v in g.deconv.state_dict().items()}
        rg.conv_layers.load_state_dict(own)
    return rf, rg


def test_reference_structure_computes_our_loss():
    torch.manual_seed(0)
    f = LocallyLinearTransition(3, n_matrices=4, hidden=16).double()
    g = ConvDecoder(3, "pendulum").double()
    with torch.no_grad():
        for p in g.parameters():
            p.add_(0.05 * torch.randn_like(p))  # non-trivial LayerNorm affine parameters
    rf, rg = reference_copy_of(f, g)
    b, m, n, d = 2, 3, 4, 3
    index = np.array([1, 3])
    trainer = RefTrainer(rf, rg, n_train=5, m=m, d=d)
    trainer.nodes = trainer.nodes.double()
    y = torch.rand(b, m * n, 1, 24, 24, dtype=torch.float64)
    ref_fit, ref_gap = trainer.loss_function(index, y.view(b, m * n, -1))
    fit, gap = multiple_shooting_loss(f, g, trainer.nodes[index], y)
    torch.testing.assert_close(ref_fit, fit)
    torch.testing.assert_close(ref_gap, gap)


def test_reference_ukf_agrees_with_ours_on_a_linear_system():
    """With a linear f and no process noise both filters are exact Kalman filters, whatever their sigma
    points: same means. (With process noise they differ by design: the reference adds Q to P_xx only,
    not to the covariances of the predicted measurement.)"""
    torch.manual_seed(0)
    a = torch.tensor([[0.9, 0.2, 0.0], [-0.2, 0.9, 0.1], [0.0, -0.1, 0.95]], dtype=torch.float64)
    f = lambda x: x @ a.T  # noqa: E731
    g = lambda x: x[:, :1]  # noqa: E731
    y = torch.randn(4, 15, 1, dtype=torch.float64)
    ref = ref_ukf(f, g, y, 0.1, 0.5, 0.0)  # predicts through f first, then updates with y[:, t]
    x0 = torch.zeros(4, 3, dtype=torch.float64)
    x0[:, 0] = y[:, 0, 0]
    # ours updates first: give it the reference's prior for time 0, f of (x0, 0.1 I)
    ours = UnscentedKalmanFilter(f, g, 0.0, 0.5, 0.1, state_dim=3).filter(y, f(x0), 0.1 * a @ a.T)
    torch.testing.assert_close(ours.means, ref)


# slow tests: two_jobs starts seven worker processes one after the other (~40 s); train_step a reference worker
# process and both structures' steps (~40 s on a 2-core Zen 3)
@pytest.mark.parametrize(
    "script",
    [
        pytest.param("train_step", marks=pytest.mark.slow),
        "ukf",
        "narrow_linear",
        "profile_decoder",
        pytest.param("two_jobs", marks=pytest.mark.slow),
    ],
)
def test_benchmark_scripts_run_at_a_tiny_size(tmp_path, script):
    out = tmp_path / f"{script}.md"
    if script == "train_step":
        rows = _train_step_rows(out, compiled=False, inputs=True)
        assert not any("compiled rollout" in row for row in rows)
        assert "driven: f(x, u)" in rows[-1] and "over the same model without inputs" in out.read_text()
    elif script == "profile_decoder":
        profile_decoder.main(["--tiny", "--threads", "1", "--repeats", "1", "--out", str(out)])
        text = out.read_text()
        assert "| decoder, native kernels |" in text and "| decoder, torch-only |" in text
        assert ("| native kernels, all calls |" in text) == (native.library() is not None)
        assert "native.build.FLAG_SETS (-march=native)" in text
    elif script == "narrow_linear":
        bench_narrow_linear.main(["--tiny", "--rounds", "1", "--threads", "1", "--out", str(out)])
        assert "| tiny | 3 | 8 | 3 |" in out.read_text() and "NarrowLinear |" in out.read_text()
    elif script == "two_jobs":
        bench_two_jobs.main(["--tiny", "--rounds", "1", "--steps", "1", "--out", str(out)])
        rows = [line.split(" | ") for line in out.read_text().splitlines() if line.startswith(("| one", "| two"))]
        assert [row[0][2:] for row in rows] == [label for label, *_ in bench_two_jobs.VARIANTS]
        assert all(float(row[2]) > 0 for row in rows) and rows[0][3].strip(" |") == "1.00"  # the lone job is the unit
    else:
        bench_ukf.main(["--tiny", "--threads", "1", "--out", str(out)])
        text = out.read_text()
        assert "| reference UKF structure" in text and "| **UKF, float32 (default)** |" in text
    assert "TINY sizes" in out.read_text()


def test_narrow_linear_benchmark_refuses_zero_rounds(capsys):
    with pytest.raises(SystemExit) as stop:
        bench_narrow_linear.main(["--tiny", "--rounds", "0"])
    assert stop.value.code == 2 and "--rounds and --threads must be at least 1, got 0 and 2" in capsys.readouterr().err


def test_two_jobs_benchmark_refuses_zero_rounds_before_starting_workers(capsys):
    with pytest.raises(SystemExit) as stop:
        bench_two_jobs.main(["--tiny", "--rounds", "0"])
    assert stop.value.code == 2 and "--rounds 0: give at least 1 round and 1 step" in capsys.readouterr().err


def _train_step_rows(out, compiled: bool, inputs: bool = False) -> list[str]:
    """Run the train-step benchmark at its tiny size; its SSM-LL rows (reference first, then ours)."""
    bench_train_step.main(
        ["--tiny", "--rounds", "1", "--steps", "1", "--threads", "1", "--models", "SSM-LL", "--out", str(out)]
        + (["--compiled"] if compiled else [])
        + (["--inputs"] if inputs else [])
    )
    rows = [line for line in out.read_text().splitlines() if line.startswith("| SSM-LL")]
    assert len(rows) >= 2 and "reference structure" in rows[0] and "ssm-ms, float32" in rows[1]
    return rows


@pytest.mark.slow  # torch.compile's first compilation is ~30 s on 2 cores; the compiled rollout itself is
# checked against a plain loop in test_speed.py
@pytest.mark.skipif(compile_unavailable_reason("default") is not None, reason="torch.compile unavailable here")
def test_train_step_benchmark_times_the_compiled_rollout(tmp_path):
    rows = _train_step_rows(tmp_path / "train_step.md", compiled=True)
    assert "compiled rollout" in rows[-1]


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a GPU")
def test_train_step_benchmark_refuses_cuda_without_a_gpu(capsys):
    with pytest.raises(SystemExit) as stop:
        bench_train_step.main(["--tiny", "--device", "cuda"])
    assert stop.value.code == 2
    assert "--device cuda: torch sees no CUDA device here" in capsys.readouterr().err


def test_results_say_shared_when_other_processes_ran_not_after_a_busy_minute():
    """What CpuWatch counts, against the machine's own background load (measured in idle windows around the
    checks, so the test holds on a machine that other jobs keep busy: `make test` beside a training run)."""
    import os
    import subprocess
    import sys
    import time

    from ssm_ms.runtime.machine import SHARED_CORES, CpuWatch, quiet_note

    assert "otherwise quiet" in quiet_note(0.05) and "shared with other jobs" in quiet_note(SHARED_CORES + 0.5)
    assert "not measured" in quiet_note(None)

    def idle(seconds=1.0):
        watch = CpuWatch()
        time.sleep(seconds)
        return watch.others()

    before = idle()
    if before is None:
        pytest.skip("no /proc/stat here")
    # a process of its own that busied a core and exited (as a benchmark worker does) is not another's load
    watch = CpuWatch()
    subprocess.run([sys.executable, "-c", "import time\nt = time.time()\nwhile time.time() - t < 1: pass"], check=True)
    own = watch.others()
    after = idle()
    background, drift = max(before, after), abs(after - before)  # other jobs' load, and how steady it was
    assert own < background + drift + 0.5, (own, before, after)
    # a process still running beside the measurement (another job) is: about one more core, where one is free
    free = (os.cpu_count() or 1) - background
    if free < 1.2:
        pytest.skip(
            f"the machine's other jobs keep {background:.2f} of {os.cpu_count()} cores busy: no free core to "
            "see one more process on"
        )
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        time.sleep(0.3)  # its interpreter has started
        watch = CpuWatch()
        time.sleep(1.5)
        other = watch.others()
    finally:
        busy.kill()
        busy.wait()
    assert 0.6 - drift < other - min(before, after) and other - background < 1.6 + drift, (other, before, after)


def test_epoch_profile_shares_from_a_profiler_table():
    """profile_epoch reads SimpleProfiler's table and splits the fit into non-overlapping shares that add up."""
    from benchmarks.profile_epoch import parse_profile, shares

    table = """FIT Profiler Report
| Action | Mean duration (s) | Num calls | Total time (s) | Percentage % |
|------------------------------------------------------------------------|
| Total                                             | -       | 900   | 100.0 | 100 % |
|------------------------------------------------------------------------|
| run_training_epoch                                | 8.0     | 10    | 80.0  | 80.0 |
| run_training_batch                                | 0.25    | 300   | 75.0  | 75.0 |
| [Strategy]SingleDeviceStrategy.backward           | 0.1     | 300   | 30.0  | 30.0 |
| [LightningDataModule]PendulumDataModule.prepare_data | 6.0  | 1     | 6.0   | 6.0 |
| [_TrainingEpochLoop].train_dataloader_next        | 0.01    | 300   | 3.0   | 3.0 |
| [_EvaluationLoop].val_next                        | 0.1     | 5     | 0.5   | 0.5 |
| [Strategy]SingleDeviceStrategy.validation_step    | 1.0     | 5     | 5.0   | 5.0 |
| [Callback]EpochCheckpoint{'monitor': None}.on_train_epoch_end | 0.2 | 10 | 2.0 | 2.0 |
"""
    rows = parse_profile(table)
    assert rows["run_training_batch"] == (300, 75.0) and rows["Total"] == (900, 100.0)
    assert rows["[Strategy]SingleDeviceStrategy.validation_step"] == (5, 5.0)
    total, groups = shares(rows)
    assert total == 100.0
    got = dict(groups)
    assert got["training steps (forward, backward, optimizer)"] == 75.0
    assert got["waiting for the next training batch (data)"] == 3.0
    assert got["validation (steps, batches, its hooks)"] == 5.5
    assert got["end-of-epoch callbacks (last.ckpt, figures)"] == 2.0
    assert got["data set generation and set-up (first run of a config only)"] == 6.0
    assert got["the rest (logging, progress bar, set-up)"] == pytest.approx(100.0 - 75 - 3 - 5.5 - 2 - 6)
    assert sum(got.values()) == pytest.approx(total)


@pytest.mark.slow  # an SSM and an encoder fitted through the CLI, then the benchmark's workers (~15 s)
def test_allocator_benchmark_runs_at_a_tiny_size(tmp_path):
    """The README's oscillator example stands in for the quad: an SSM fitted one epoch, then its encoder's steps."""
    from tests.test_cli import ROOT as CLI_ROOT
    from tests.test_cli import oscillator_file, outputs, run

    data = ["--data.init_args.train_path", str(oscillator_file(tmp_path))]
    started = time.time()
    ssm_config = CLI_ROOT / "configs" / "oscillator.yaml"
    run(
        tmp_path,
        "fit",
        ssm_config,
        "--trainer.max_epochs",
        "1",
        "--trainer.limit_train_batches",
        "2",
        "--trainer.limit_val_batches",
        "1",
        *data,
    )
    out = tmp_path / "allocator.md"
    bench_allocator.main(
        [
            "--config",
            "configs/oscillator_encoder.yaml",
            "--rounds",
            "1",
            "--warm",
            "1",
            "--steps",
            "1",
            "--settings",
            "trim 2 GiB",
            "--ssm",
            str(outputs(tmp_path, ssm_config) / "checkpoints" / "last.ckpt"),
            "--out",
            str(out),
            *data,
        ]
    )
    rows = [line for line in out.read_text().splitlines() if line.startswith("| trim")]
    assert [row.split(" | ")[0] for row in rows] == ["| trim off", "| trim 2 GiB"]  # the base is always measured
    assert rows[0].split(" | ")[5] == "1.00"  # the base's ratio to itself
    assert not (CLI_ROOT / "config.yaml").exists() or (CLI_ROOT / "config.yaml").stat().st_mtime < started


def test_fit_by_speed_scores_each_frame_of_each_piece_as_a_naive_loop():
    """benchmarks/fit_by_speed.py: each frame's error of the pieces rolled out from their nodes under their inputs."""
    from types import SimpleNamespace

    from benchmarks.fit_by_speed import errors_by_frame
    from ssm_ms.module import MultipleShootingModule
    from ssm_ms.nets import LinearReadout

    torch.manual_seed(0)
    ssm = MultipleShootingModule(
        LocallyLinearTransition(2, 2, 4, input_dim=1), LinearReadout(2, 3), state_dim=2, num_trajectories=3, n_nodes=2
    )
    clean, u, state = torch.rand(3, 10, 3), torch.randn(3, 10, 1), torch.randn(3, 10, 2)
    items = [{"y_clean": clean[i], "u": u[i], "state": state[i]} for i in range(3)]
    dm = SimpleNamespace(datasets={"train": items}, n_links=1)
    err, empty, speed = errors_by_frame(ssm, dm, 3)
    nodes = ssm.nodes.weight.detach().view(3, 2, 2)
    with torch.no_grad():
        for i in range(3):
            for j in range(2):
                x = nodes[i, j][None]
                for k in range(5):
                    t = 5 * j + k
                    assert err[i, t] == pytest.approx((ssm.g(x)[0] - clean[i, t]).pow(2).mean().item(), rel=1e-5)
                    x = ssm.f(x, u[i, t][None])
    np.testing.assert_allclose(empty, clean.pow(2).mean(2).numpy(), rtol=1e-6)
    np.testing.assert_allclose(speed, state[..., 1].abs().numpy())


def test_torque_authority_turns_match_a_linear_systems_closed_form():
    """benchmarks/torque_authority.py: k steps of +tau against -tau through x+ = A x + B u, read as x[0], end
    2 tau (sum_{j<k} A^j B)[0] apart; a transition that ignores u turns nothing; the pendulum's equations about
    tau t^2 (the torque's push on a unit mass, gravity aside)."""
    from benchmarks.torque_authority import turns
    from ssm_ms.control.module import TruePendulum

    a = torch.tensor([[0.95, 0.1], [-0.2, 0.9]], dtype=torch.float64)
    b = torch.tensor([[0.03], [0.1]], dtype=torch.float64)
    x0 = torch.randn(5, 2, dtype=torch.float64) * 0.1
    got = turns(lambda x, u: x @ a.T + u @ b.T, lambda x: x[:, 0].numpy(), x0, 3, 2.0)
    want = 2 * 2.0 * (b + a @ b + a @ a @ b)[0, 0].item()
    np.testing.assert_allclose(got, want, rtol=1e-12)
    assert np.all(turns(lambda x, u: x @ a.T, lambda x: x[:, 0].numpy(), x0, 3, 2.0) == 0)
    pendulum = TruePendulum(0.1).double()
    states = torch.tensor([[np.pi - 0.1, 0.5], [0.3, -1.0]], dtype=torch.float64)
    true_turn = turns(pendulum, lambda z: z[:, 0].numpy(), states, 3, 3.0)
    np.testing.assert_allclose(true_turn, 3.0 * 0.3**2, rtol=0.1)  # gravity's pull is the same both ways, nearly


def test_torque_authority_falls_match_the_linearised_upright_pendulum():
    """Without torque, from d0 rad off upright at rest, the pendulum's distance from upright grows as d0 cosh(sqrt(g)
    t) (d'' = g d, linearised); a transition that keeps the state draws no fall."""
    from benchmarks.torque_authority import falls
    from ssm_ms.control.module import TruePendulum

    d0 = np.array([0.02, -0.05])
    states = torch.tensor(np.stack([np.pi + d0, np.zeros(2)], 1), dtype=torch.float64)
    got = falls(TruePendulum(0.1).double(), lambda z: z[:, 0].numpy(), states, 3)
    np.testing.assert_allclose(got, np.abs(d0) * (np.cosh(np.sqrt(9.81) * 0.3) - 1), rtol=0.02)
    assert np.all(falls(lambda x, u: x, lambda z: z[:, 0].numpy(), states, 3) == 0)


def test_authority_needed_scales_the_torque_near_upright_and_elsewhere():
    """benchmarks/authority_needed.py: the true pendulum with its torque scaled by 0.5 within 0.5 rad of upright and by
    2 elsewhere turns as the linearised pendulum under the scaled torque does, 2 s tau (cosh(w t) - 1) / w^2 at upright
    and 2 s tau (1 - cos(w t)) / w^2 hanging (w = sqrt(g), from rest, one frame of 0.1 s)."""
    from benchmarks.authority_needed import ScaledTorque
    from benchmarks.torque_authority import turns
    from ssm_ms.control.module import TruePendulum

    w, t, tau = np.sqrt(9.81), 0.1, 0.1
    states = torch.tensor([[np.pi + 0.01, 0.0], [0.01, 0.0]], dtype=torch.float64)  # upright, hanging
    got = turns(ScaledTorque(TruePendulum(t).double(), 0.5, 2.0), lambda z: z[:, 0].numpy(), states, 1, tau)
    want = [2 * 0.5 * tau * (np.cosh(w * t) - 1) / w**2, 2 * 2.0 * tau * (1 - np.cos(w * t)) / w**2]
    np.testing.assert_allclose(got, want, rtol=1e-3)


def test_authority_needed_refuses_more_episodes_than_starts_and_a_missing_config(tmp_path):
    from benchmarks.authority_needed import main

    with pytest.raises(SystemExit, match=r"--episodes must be 1 to 20 .* got 21"):
        main(["--episodes", "21", "--out", str(tmp_path / "unused.md")])
    with pytest.raises(SystemExit, match="no config at nope.yaml"):
        main(["--config", "nope.yaml"])


def test_control_diagnosis_reads_the_filter_and_its_k_step_predictions_as_a_naive_loop():
    """benchmarks/control_diagnosis.py: the angle of each filtered state, and of f applied k times to it under the
    torques that followed, at the frame it predicts; the table's bands by the true angle's distance from upright."""
    from types import SimpleNamespace

    from benchmarks import control_diagnosis as D
    from ssm_ms.control.estimators import UKFEstimator
    from ssm_ms.inference.ukf import UnscentedKalmanFilter

    torch.manual_seed(0)
    a, b = torch.tensor([[0.9, 0.2], [-0.3, 0.8]]), torch.tensor([[0.5], [-0.1]])

    def f(x, u):
        return x @ a.T + u @ b.T

    def g(x):
        return torch.cat([x, x.sum(1, keepdim=True)], 1)

    def features(x):
        return torch.stack([torch.sin(x[:, 0]), torch.cos(x[:, 0])], 1)

    ukf = UnscentedKalmanFilter(f, g, process_var=1e-2, measurement_var=0.1, init_var=1.0, state_dim=2)
    loop = SimpleNamespace(estimator=lambda: UKFEstimator(ukf, torch.zeros(2), lambda y: y), features=features, f=f)
    frames, inputs = [torch.randn(3, 3) for _ in range(7)], torch.randn(3, 6, 1)
    read, ahead = D.diagnose(loop, frames, inputs)
    assert np.isnan(ahead[5][:, :5]).all()  # no prediction before k frames
    mean = torch.zeros(3, 2)
    cov = ukf.initial_covariance(3, 2, mean.dtype, mean.device)
    mean, cov = ukf.update(mean, cov, frames[0])
    means = [mean]
    for t in range(6):
        mean, cov = ukf.update(*ukf.predict(mean, cov, inputs[:, t]), frames[t + 1])
        means.append(mean)
    for t in range(7):
        want = torch.atan2(torch.sin(means[t][:, 0]), torch.cos(means[t][:, 0]))
        np.testing.assert_allclose(read[:, t], want.double().numpy(), atol=1e-6)
        for k in D.STEPS:
            if t + k > 6:  # past the last frame
                continue
            x = means[t]
            for j in range(k):
                x = f(x, inputs[:, t + j])
            want = torch.atan2(torch.sin(x[:, 0]), torch.cos(x[:, 0]))
            np.testing.assert_allclose(ahead[k][:, t + k], want.double().numpy(), atol=1e-5)
    assert np.isnan(ahead[10]).all()  # 10 steps ahead of 7 frames: nothing
    truth = np.array([[np.pi, 0.0, 2.0, np.pi - 0.2]])  # upright, hanging, 1.14 from upright, upright
    nan = np.full_like(truth, np.nan)
    nan[0, 0] = truth[0, 0] + 0.3  # a column with one frame: the mean of the band's frames it has
    rows = D.table(truth, {"a": truth + 0.1, "b": truth - 0.2, "c": nan})
    assert rows[0] == "| true angle from upright (rad) | share of frames | a | b | c |"
    assert rows[2] == "| 0 to 0.5 | 0.50 | 0.100 | 0.200 | 0.300 |"
    assert rows[3].startswith("| 0.5 to 1.5 | 0.25 |") and rows[5].startswith("| 2.5 and above | 0.25 |")


def test_closed_loop_episodes_plan_on_the_true_state_or_on_the_estimate():
    """ClosedLoop.episodes (through benchmarks/control_diagnosis.py's episodes): the true model's controller sees the
    simulator's state; a learned model's sees its estimator's output after each measurement; measurements, torques
    (exploration noise included) and true angles are recorded per period, and the planner is told the torque
    applied (a scalar system stepped by hand)."""
    from types import SimpleNamespace

    from benchmarks import control_diagnosis as D
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

    dm = SimpleNamespace(test_dataloader=lambda: [{"state": torch.tensor([[[2.0, 0.0]], [[-1.0, 0.0]]])}])
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
        frames, inputs, angles = D.episodes(loop, dm, 2)
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


def test_benchmark_provenance_names_the_date_machine_and_the_command_given(tmp_path, monkeypatch):
    """benchmarks/report.py: the command is the arguments given (none given: none, not the test runner's), a note
    extends the machine line, and the file written is what is printed."""
    import datetime

    from benchmarks.report import provenance, write

    monkeypatch.setattr("sys.argv", ["pytest", "-k", "x"])
    date, machine, command = provenance("benchmarks/x.py", [])
    assert command == "- Command: `python benchmarks/x.py`"
    assert provenance("benchmarks/x.py", None)[2] == "- Command: `python benchmarks/x.py -k x`"
    assert provenance("benchmarks/x.py", ["--out", "a b.md"])[2] == "- Command: `python benchmarks/x.py --out 'a b.md'`"
    assert date.startswith(f"- Date: {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d}") and machine.startswith(
        "- Machine: "
    )
    noted = provenance("benchmarks/x.py", [], "2 torch threads")[1]
    assert noted.startswith(machine) and noted.endswith("; 2 torch threads"), (noted, machine)
    write(tmp_path / "sub" / "r.md", ["# r", "", command])
    assert (tmp_path / "sub" / "r.md").read_text() == "# r\n\n- Command: `python benchmarks/x.py`\n"


def test_decoder_reach_writes_its_table_and_figure(tmp_path, monkeypatch):
    """benchmarks/decoder_reach.py on the pretrained simple pendulum, 2 sequences: three rows, each with the model's,
    the free codes' and the mean frame's error; codes fitted to each clean frame from the pipeline's own states draw
    it at least as close as those states do, and closer than the mean frame; with --rollout, one state per sequence
    fitted through f and g to all frames draws them closer than the mean frame, and the predicted ones at least as
    close as one fitted to the given frames alone; the figure holds three strips of frames."""
    from PIL import Image

    from benchmarks import decoder_reach

    monkeypatch.chdir(ROOT)  # the pretrained encoder names its SSM file from the repository root
    out = tmp_path / "reach.md"
    decoder_reach.main(
        [
            "--encoder", str(ROOT / "pretrained/pendulum_encoder.ckpt"),
            "--data-config", str(ROOT / "configs/data/pendulum.yaml"),
            "--sequences", "2", "--steps", "150", "--rollout", "--out", str(out),
        ]
    )  # fmt: skip
    rows = [line for line in out.read_text().splitlines() if line.startswith("| the ") or line.startswith("| all ")]
    assert len(rows) == 3
    for row in rows:
        model, free, given_fit, all_fit, mean = (float(v) for v in row.strip("|").split("|")[1:])
        assert free <= model * 1.001 and free < mean, row
        assert all_fit < mean, row  # one state through f and g, fitted to the whole sequence, draws it
    predicted = rows[2].strip("|").split("|")[1:]
    assert float(predicted[3]) <= float(predicted[2])  # fitted to those frames too: at least as close to them
    image = Image.open(out.with_suffix(".png"))
    assert image.height == 3 * 24 * 2 and image.width == 10 * 24 * 2  # the 2 x 5 first predicted frames, each


def test_lorenz_oracle_forecasts_the_truth_from_near_noiseless_measurements(tmp_path):
    """benchmarks/lorenz_oracle.py: with measurement noise std 0.01 the true model's UKF finds the state, so its
    10-step forecast of x matches the generator's noiseless x (closed form: the data itself) to well under the
    noise's variance scaled back; with the paper's noise (std 2.5) the UKF's error is larger, and the particle
    filter's forecasts stay on the sequences (a bootstrap filter cannot find a state from a wide prior through
    near-noiseless measurements, so it is not asked to); one row per config and filter setting."""
    from benchmarks import lorenz_oracle

    configs = []
    for noise in (0.01, 2.5):
        path = tmp_path / f"lorenz_{noise}.yaml"
        init_args = {"n_train": 1, "train_steps": 10, "n_test": 3, "test_steps": 300, "noise_std": noise}
        path.write_text(f"class_path: datamodules.lorenz.LorenzDataModule\ninit_args: {init_args}\n")
        configs.append(str(path))
    out = tmp_path / "oracle.md"
    lorenz_oracle.main(["--data-config", *configs, "--n-filter", "290", "--particles", "500", "--out", str(out)])
    rows = [line.strip("|").split("|") for line in out.read_text().splitlines() if line.startswith("| `")]
    n_ukf, n_pf = len(lorenz_oracle.PROCESS_VARS), len(lorenz_oracle.PF_PROCESS_STDS)
    assert len(rows) == 2 * (n_ukf + n_pf)
    assert [r[2].strip() for r in rows[: n_ukf + n_pf]] == ["UKF"] * n_ukf + ["particle filter, 500"] * n_pf
    quiet, noisy = rows[: n_ukf + n_pf], rows[n_ukf + n_pf :]
    quiet_ukf = [float(r[4]) for r in quiet[:n_ukf]]
    assert max(quiet_ukf) < 1e-3, quiet_ukf
    assert all(0 < float(r[4]) < 1.0 for r in noisy[n_ukf:]), noisy  # the particles track the noisy sequences
    assert min(float(r[4]) for r in noisy[:n_ukf]) > 10 * max(quiet_ukf), (quiet, noisy)
    for wrong in (str(tmp_path / "missing.yaml"), str(ROOT / "configs/data/pendulum.yaml")):
        with pytest.raises(SystemExit, match="is not a Lorenz data config"):
            lorenz_oracle.main(["--data-config", wrong, "--out", str(out)])


def test_ssm_rollouts_score_the_first_node_rolled_out_as_a_naive_loop(tmp_path):
    """benchmarks/ssm_rollouts.py on the pretrained pendulum SSM and 8 generated training trajectories (4 picked,
    evenly: 0, 2, 5, 7): its MSE over all frames equals g(f^k(first node)) against the clean frames, computed here
    step by step; one figure per SSM, rows measured / clean / model per trajectory."""
    import yaml
    from PIL import Image

    from benchmarks import ssm_rollouts
    from datamodules.pendulum import PendulumDataModule
    from ssm_ms.forecasting.metrics import ssim_per_sequence
    from ssm_ms.module import load_ssm

    spec = yaml.safe_load((ROOT / "configs/data/pendulum.yaml").read_text())
    args = {**spec["init_args"], "n_train": 8, "n_test": 1, "data_dir": str(tmp_path / "data")}
    config = tmp_path / "pendulum.yaml"
    config.write_text(yaml.safe_dump({"class_path": spec["class_path"], "init_args": args}))
    out = tmp_path / "rollouts.md"
    ckpt = str(ROOT / "pretrained/pendulum.ckpt")
    ssm_rollouts.main(["--ssm", ckpt, "--data-config", str(config), "--out", str(out)])
    row = next(line for line in out.read_text().splitlines() if line.startswith("| `"))
    reported, ssim = float(row.split("|")[5]), float(row.split("|")[6])

    model, _ = load_ssm(ckpt)
    dm = PendulumDataModule(**args)
    dm.prepare_data()
    item = dm.load("train").__getitems__([0, 2, 5, 7])
    with torch.no_grad():
        x = model.node_states(torch.tensor([0, 2, 5, 7]))[:, 0]
        frames = []
        for _ in range(item["y"].shape[1]):
            frames.append(model.g(x))
            x = model.f(x)
    naive = (torch.stack(frames, 1) - item["y_clean"]).pow(2).mean().item()
    assert reported == pytest.approx(naive, abs=6e-5)  # the table's 4 decimals
    assert ssim == pytest.approx(ssim_per_sequence(torch.stack(frames, 1), item["y_clean"]).mean().item(), abs=6e-5)
    image = Image.open(out.with_name("rollouts_0.png"))
    assert image.size == (2 * (10 * 25 + 1), 2 * (4 * 3 * 25 + 1))  # 10 frames of 24 px + 1 px borders, 12 rows, x2


def test_lorenz_error_by_step_averages_to_the_protocol_score(tmp_path):
    """benchmarks/lorenz_error_by_step.py on the pretrained T = 1000 SSM and 4 short test sequences: the mean of its
    predicted steps is the score ``cli.py test`` writes for the same stage (the protocol's own path: Lightning's test
    loop, its metric); the true model's step-0 error on those sequences is below the SSM's; the second table's error
    at given sample 100 is the step-0 error of a run that filters only the first 100 (both filters are causal); a
    wrong config is refused in one line."""
    import json
    import subprocess
    import sys

    from benchmarks import lorenz_error_by_step

    def run(n_filter: int) -> tuple[Path, list[dict[str, list[float]]]]:
        """The script on the first ``n_filter`` samples: its config and tables, each ``{first cell: [column means]}``."""
        config = tmp_path / f"ukf{n_filter}.yaml"
        config.write_text(
            f"config: {ROOT / 'configs/lorenz_T1000_ukf.yaml'}\n"
            f"model.init_args.n_filter: {n_filter}\nmodel.init_args.analysis: null\n"
            "data.init_args.n_test: 4\ndata.init_args.test_steps: 300\ndata.init_args.n_train: 2\n"
            f"data.init_args.train_steps: 1000\ndata.init_args.data_dir: {tmp_path / 'data'}\n"
        )
        lorenz_error_by_step.main(["--ssm", str(ckpt), "--config", str(config), "--out", str(out)])
        tables = [[]]
        for line in out.read_text().splitlines():
            if line.startswith("|"):
                tables[-1].append([c.strip() for c in line.strip("|").split("|")])
            elif tables[-1]:
                tables.append([])
        return config, [{r[0]: [float(c.split("±")[0]) for c in r[1:] if c] for r in t[2:]} for t in tables if t]

    ckpt = ROOT / "pretrained/lorenz_T1000.ckpt"
    out = tmp_path / "by_step.md"
    _, (short_steps, _) = run(100)
    config, (steps, along) = run(290)
    assert [str(step) for step in range(11)] == [k for k in steps if k.isdigit()]
    assert list(along)[:5] == ["1", "10", "100", "250", "290"]
    late = along.pop("mean of 251-290 less the first column's, paired")  # the true model's less the SSM's
    assert late == pytest.approx([along["mean of 251-290"][1] - along["mean of 251-290"][0]], abs=2e-4)
    assert along["290"] == steps["0"]
    assert along["100"] == pytest.approx(short_steps["0"], rel=1e-3, abs=1e-4)
    assert along["100"] != steps["0"]
    mean = steps["mean of 1-10"][0]
    paired = steps.pop("mean of 1-10 less the first column's, paired")  # the true model's score less the SSM's
    assert paired == pytest.approx([steps["mean of 1-10"][1] - mean], abs=2e-4)
    step0_ssm, step0_true = steps["0"]
    assert step0_true < step0_ssm
    subprocess.run(
        [
            sys.executable, "cli.py", "test", "--config", str(config), f"--model.init_args.ssm_checkpoint={ckpt}",
            f"--model.init_args.results_dir={tmp_path}", f"--model.init_args.figures_dir={tmp_path}/figures",
            f"--trainer.logger.init_args.save_dir={tmp_path}/runs", "--trainer.enable_progress_bar=false",
        ],
        cwd=ROOT, check=True, stdout=subprocess.DEVNULL,
    )  # fmt: skip
    runs = json.loads((tmp_path / "lorenz_T1000.json").read_text())["runs"]
    score = next(iter(runs.values()))["summary"]
    score = next(v for k, v in score.items() if k.endswith("/clean/mse") and not k.startswith(("last", "mean")))
    assert mean == pytest.approx(score["mean"], rel=1e-3, abs=1e-4)
    for wrong in ("configs/pendulum.yaml", "configs/lorenz_T1000.yaml"):  # not Lorenz; Lorenz, but no filter stage
        with pytest.raises(SystemExit, match="is not a Lorenz UKF stage"):
            lorenz_error_by_step.main(["--ssm", str(ckpt), "--config", wrong, "--out", str(out)])
    with pytest.raises(SystemExit, match="make g match the data"):  # an SSM of other data
        lorenz_error_by_step.main(
            ["--ssm", str(ROOT / "pretrained/pendulum.ckpt"), "--config", str(config), "--out", str(out)]
        )
