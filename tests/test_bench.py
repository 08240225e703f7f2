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


def test_results_by_machine_keep_the_other_machines_rows_and_notes():
    """benchmarks/report.py: a run's rows, with a machine column, replace its machine's earlier rows; the other
    machines' stay, in the order of their runs; the run's ``- `` lines become its machine's entry in the list of
    runs; the file's hand-written ``## Notes`` stay."""
    from benchmarks.report import RUNS_INTRO, merge_by_machine

    def run(date: str, x: int, y: int) -> list[str]:
        return ["# t", "", f"- Date: {date}", "- set-up: s", "", "| case | ms |", "|---|---:|", f"| x | {x} |"] + [
            f"| y | {y} |",
            "",
            "prose",
        ]

    first = merge_by_machine(None, run("d1", 1, 2), "A")
    assert first == ["# t", "", RUNS_INTRO, "", "- **A**", "  - Date: d1", "  - set-up: s", ""] + [
        "| machine | case | ms |",
        "|---|---|---:|",
        "| A | x | 1 |",
        "| A | y | 2 |",
        "",
        "prose",
    ]
    second = merge_by_machine("\n".join(first) + "\n\n## Notes\n\nby hand\n", run("d2", 3, 4), "B")
    again = merge_by_machine("\n".join(second) + "\n", run("d3", 5, 6), "A")
    assert [line for line in again if line.startswith(("| A", "| B"))] == [
        "| A | x | 5 |",
        "| A | y | 6 |",
        "| B | x | 3 |",
        "| B | y | 4 |",
    ]
    assert again[again.index("- **A**") + 1] == "  - Date: d3" and again[again.index("- **B**") + 1] == "  - Date: d2"
    assert "  - Date: d1" not in again and again[-3:] == ["## Notes", "", "by hand"]
