"""The nonlinearbenchmark.org benchmarks through their official loader (../shared/data/nonlinear_benchmarks, offline):
the splits against the loader's arrays sliced by hand, the protocol (state from the first n_init samples, then a free
run) against a loop written here, divergence reported where it happens, one message for each mistake."""

from __future__ import annotations

import importlib
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from experiments.cli import reports
from ssm_ms.cli import main as cli_main
from ssm_ms.inference import UnscentedKalmanFilter
from ssm_ms.inference.simulation import free_run, local_stability
from ssm_ms.module import MultipleShootingModule
from ssm_ms.nets import LinearReadout, LocallyLinearTransition

nb = pytest.importorskip("nonlinear_benchmarks")

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "nonlinear_benchmarks"
pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason=f"no benchmark files at {DATA}")


def tanks(**kwargs):
    from datamodules.benchmarks import BenchmarkDataModule

    return BenchmarkDataModule("Cascaded_Tanks", dir_placement=str(DATA), **kwargs)


def test_the_splits_are_the_loader_s_arrays():
    """Training windows from the first 80% of the training recording, its last 20% the validation recording whole,
    the test recording whole; normalised with the training part's statistics (numpy, here)."""
    train, test = nb.Cascaded_Tanks(dir_placement=str(DATA))
    dm = tanks(window=100, batch_size=4)
    cut = round(1024 * 0.8)
    assert dm.n_init == 50 and dm.sample_period == 4.0 and dm.val_length == 1024 - cut
    dm.setup("fit")
    y_train = np.asarray(train.y[:cut], dtype=np.float64)
    windows = dm.datasets["train"].arrays["y"]
    for i, (_, start) in enumerate(dm.window_origins.tolist()):
        np.testing.assert_array_equal(windows[i, :, 0], np.asarray(train.y[start : start + 100], dtype=np.float32))
    assert dm.window_origins[-1, 1] + 100 == cut  # the last window ends where the held-out part begins
    in_windows = np.concatenate([y_train[s : s + 100] for _, s in dm.window_origins.tolist()])
    np.testing.assert_allclose(dm.normalizer.mean.numpy(), [in_windows.mean()], rtol=1e-5)
    np.testing.assert_allclose(dm.normalizer.std.numpy(), [in_windows.std()], rtol=1e-4)
    val = next(iter(dm.split_dataloader("val")))
    expected = (np.asarray(train.y[cut:]) - in_windows.mean()) / in_windows.std()
    np.testing.assert_allclose(val["y"][0, :, 0].numpy(), expected, rtol=1e-4, atol=1e-5)
    (loader,) = dm.test_dataloader()
    batch = next(iter(loader))
    np.testing.assert_allclose(
        batch["y"][0, :, 0].numpy(), (test.y - in_windows.mean()) / in_windows.std(), rtol=1e-4, atol=1e-5
    )
    assert batch["u"].shape == (1, 1024, 1)


def test_mistakes_get_one_message(monkeypatch, tmp_path):
    from datamodules import benchmarks

    with pytest.raises(ValueError, match="unknown benchmark 'Silverbx': the loader knows .*Silverbox"):
        benchmarks.BenchmarkDataModule("Silverbx", dir_placement=str(DATA))
    with pytest.raises(ValueError, match="no such folder"):
        benchmarks.BenchmarkDataModule("Silverbox", dir_placement=str(tmp_path / "nowhere"))
    with pytest.raises(ValueError, match="could not be downloaded"):  # a folder without the files, and no internet
        benchmarks.BenchmarkDataModule("Cascaded_Tanks", dir_placement=str(tmp_path))
    real = importlib.import_module

    def without_loader(name, *args):
        if name == "nonlinear_benchmarks":
            raise ImportError(name)
        return real(name, *args)

    monkeypatch.setattr(importlib, "import_module", without_loader)
    with pytest.raises(ValueError, match=r"pip install -e '\.\[benchmarks\]'"):
        benchmarks.BenchmarkDataModule("Cascaded_Tanks", dir_placement=str(DATA))


def test_a_free_run_that_leaves_the_bound_says_where():
    """``f(x) = 2 x`` from 1: past the bound 100 at step 7 (2^7 = 128), the values as computed."""

    class Doubling(torch.nn.Module):
        def forward(self, x):
            return 2 * x

    y, where = free_run(Doubling(), torch.nn.Identity(), torch.ones(2, 1), 20, chunk=3, bound=100.0)
    assert where.tolist() == [7, 7]
    np.testing.assert_array_equal(y[0, :, 0].numpy(), 2.0 ** np.arange(20))
    _, never = free_run(Doubling(), torch.nn.Identity(), torch.ones(1, 1), 5, bound=100.0)
    assert never.tolist() == [-1]


def test_local_stability_is_the_spectral_radius_of_df_dx():
    """An SSM-LL with one matrix is linear: x + A x, whose spectral radius the test computes by hand."""
    torch.manual_seed(0)
    f = LocallyLinearTransition(2, n_matrices=1, hidden=4)
    model = MultipleShootingModule(f, LinearReadout(2, 1), num_trajectories=3, n_nodes=2)
    with torch.no_grad():
        model.nodes.weight.normal_()
        jac = torch.eye(2) + f.matrices.view(2, 2)
    radius = float(torch.linalg.eigvals(jac.double()).abs().max())
    stats = local_stability(model)
    assert stats["median"] == pytest.approx(radius, rel=1e-5) and stats["max"] == pytest.approx(radius, rel=1e-5)
    assert stats["share_above_1"] == float(radius > 1) and stats["states"] == 6


def test_a_row_name_may_carry_the_latent_dimension():
    """``{d}`` in ``method_name`` is the checkpoint's latent dimension (one test config for every order ``--orders``
    fits); any other field in braces is refused in one message."""
    from ssm_ms.inference.simulation import SimulationTest

    for d in (2, 5):
        model = MultipleShootingModule(
            LocallyLinearTransition(d, n_matrices=1, hidden=4), LinearReadout(d, 1), num_trajectories=1
        )
        named = SimulationTest(model, method_name="SSM-LL, averaged (d = {d}) + UKF")
        assert named.method_name == f"SSM-LL, averaged (d = {d}) + UKF"
    with pytest.raises(ValueError, match=r"braces may hold only \{d\}"):
        SimulationTest(model, method_name="SSM-LL (n = {n})")


def test_cascaded_tanks_end_to_end_and_its_score_by_hand(tmp_path):
    """A tiny SSM fitted on Cascaded Tanks (the benchmark's config, shrunk), the validation keeping its best epoch,
    then ``cli.py test``: the results file's RMSE equals the protocol computed here (the UKF on the first 50
    normalised samples, f iterated under the test inputs, the statistics undone by hand, numpy's RMSE)."""
    where = ["--data.init_args.dir_placement", str(DATA), "--trainer.logger.init_args.save_dir", str(tmp_path)]
    small = [
        "--trainer.max_time", "null", "--trainer.max_epochs", "60", "--trainer.val_check_interval", "40", "--model.init_args.lr", "1e-2",
        "--trainer.enable_progress_bar", "false", "--model.init_args.state_dim", "2",
        "--model.init_args.f.init_args.n_matrices", "2", "--model.init_args.f.init_args.hidden", "8",
        "--data.init_args.window", "100", "--model.init_args.n_nodes", "4",
    ]  # fmt: skip
    cli_main(["fit", "--config", "configs/benchmarks/cascaded_tanks.yaml", *where, *small])
    best = tmp_path / "cascaded_tanks" / "version_0" / "checkpoints" / "best.ckpt"
    assert best.is_file()
    test = [
        "test", "--config", "configs/benchmarks/cascaded_tanks_test.yaml", "--data.init_args.dir_placement", str(DATA),
        "--model.init_args.ssm_checkpoint", str(best), "--model.init_args.results_dir", str(tmp_path / "results"),
        "--model.init_args.figures_dir", str(tmp_path / "figures"), "--trainer.enable_progress_bar", "false",
    ]  # fmt: skip
    with reports():  # python cli.py test: the library writes the JSON, the application renders its .md
        cli_main(test)
    results = json.loads((tmp_path / "results" / "cascaded_tanks.json").read_text())
    (run,) = results["runs"].values()
    row = run["tests"]["test"]
    assert row["n_init"] == 50 and row["samples"] == 1024
    assert (tmp_path / "results" / "cascaded_tanks.md").read_text().startswith("# cascaded_tanks")
    assert list((tmp_path / "figures").glob("*.png"))

    model = MultipleShootingModule.load_from_checkpoint(best, weights_only=False).eval()
    saved = torch.load(best, weights_only=False)
    norm = next(v for v in saved.values() if isinstance(v, dict) and "normalizer" in v)
    y_mean, y_std = norm["normalizer"]["mean"].item(), norm["normalizer"]["std"].item()
    u_mean, u_std = norm["input_normalizer"]["mean"].item(), norm["input_normalizer"]["std"].item()
    _, test_data = nb.Cascaded_Tanks(dir_placement=str(DATA))
    y = torch.tensor((test_data.y - y_mean) / y_std, dtype=torch.float32).view(1, -1, 1)
    u = torch.tensor((test_data.u - u_mean) / u_std, dtype=torch.float32).view(1, -1, 1)
    ukf = UnscentedKalmanFilter(model.f, model.g, process_var=1e-6, measurement_var=model.fit_mse, init_var=0.1)
    prior = model.nodes.weight.detach().view(-1, 2).mean(0)
    with torch.no_grad():
        x = ukf.filter(y[:, :50], prior[None], u=u[:, :49]).means[:, -1]
        x = model.f(x, u[:, 49])
        sim = []
        for t in range(50, 1024):
            sim.append(model.g(x)[0, 0].item() * y_std + y_mean)
            x = model.f(x, u[:, t])
    rmse = math.sqrt(np.mean((np.array(sim) - test_data.y[50:]) ** 2))
    assert row["rmse"] == pytest.approx(rmse, rel=1e-4)


@pytest.mark.parametrize(
    "path",
    sorted(p for p in (ROOT / "results" / "benchmarks").glob("*.json") if not p.name.endswith(".published.json")),
    ids=lambda p: p.stem,
)
def test_the_committed_results_are_rendered_from_their_json(path):
    """Each results/benchmarks/<experiment>.md is what its JSON, published rows and notes render to (after an edit of
    the notes: ``python -m experiments.benchmark_results``)."""
    from experiments.benchmark_results import render

    data = json.loads(path.read_text())
    assert path.with_suffix(".md").read_text() == render(data, path.parent)


@pytest.mark.parametrize("amortised", [False, True], ids=["free-nodes", "amortised"])
def test_the_simulation_speed_bench_times_a_free_run(tmp_path, amortised):
    """benchmarks/bench_simulation.py on a tiny driven SSM (free nodes, or nodes from a node encoder): one row, its
    steps per second the steps over its seconds."""
    import sys

    sys.path.insert(0, str(ROOT))
    from benchmarks import bench_simulation
    from ssm_ms import SSM, Recordings, fit

    rng = np.random.default_rng(0)
    data = Recordings(y=rng.normal(size=(300, 1)), u=rng.normal(size=(300, 1)), batch_size=2)
    options = {}
    if amortised:
        from ssm_ms.nets.history import HistoryEncoder

        options = {"node_encoder": HistoryEncoder(2, 1, 1, history=5), "n_nodes": 5}
    model = SSM(data, state_dim=2, f_options={"n_matrices": 2, "hidden": 8}, **options)
    fit(model, data, epochs=1, save_dir=tmp_path, logger=False, enable_progress_bar=False)
    out = tmp_path / "speed.md"
    bench_simulation.main(
        ["--checkpoint", str(model.save(tmp_path / "m.ckpt")), "--steps", "500", "--rounds", "1", "--out", str(out)]
    )
    (row,) = [line.split(" | ") for line in out.read_text().splitlines() if line.startswith("| ssm-ms")]
    seconds, per_second = float(row[1]), float(row[2].replace(",", ""))
    # the table's seconds are rounded to 1 ms: the rate lies between the steps over its bounds
    assert 500 / (seconds + 0.0005) - 1 <= per_second <= 500 / max(seconds - 0.0005, 1e-9) + 1
    assert row[3].strip(" |") == "1.00"


def test_seeds_are_summarised_and_the_readme_takes_the_method_that_validated_best(tmp_path):
    """Runs of one method over seeds become one row, mean and sample std (statistics, here); the README's ssm-ms
    column is the method of the lowest mean validation score, whatever the test scores say."""
    import statistics

    from experiments.benchmark_results import render
    from experiments.readme import Results, benchmarks
    from ssm_ms.forecasting.benchmark_results import run_key

    def run(method, seed, val, rmse, diverged=None, seconds=None, cpu_others=None):
        info = {"method": method, "seed": seed, "unit": "V", "model": "SSM-LL", "experiment": "toy"}
        info |= {"machine": f"machine of {method}", "date": f"2026-12-0{seed + 1}T00:00:00+00:00"}
        info["validation"] = {"val_sim_rmse": val, "epoch": 3, "seconds": seconds, "cpu_others": cpu_others}
        row = {"samples": 100, "n_init": 10, "seconds": 0.1, "rmse": rmse, "nrmse": None, "fit_index": None}
        row["diverged_at"] = diverged
        return run_key(info), {"info": info, "tests": {"test": row}}

    runs = dict(
        [
            run("A", 0, 1.0, 0.30, seconds=100.0),
            run("A", 1, 1.2, 0.40, seconds=200.0, cpu_others=1.25),
            run("A", 2, 1.1, 0.20, seconds=600.0),
            run("B", 0, 0.9, 0.50),
            run("B", 1, 0.95, None, diverged=42),
            run("A", 3, 1.1, 0.25, seconds=300.0),  # a later run of the method not chosen: not where the chosen row ran
        ]
    )
    assert list(runs) == ["A, seed 0", "A, seed 1", "A, seed 2", "B, seed 0", "B, seed 1", "A, seed 3"]
    data = {"experiment": "toy", "runs": runs}
    folder = tmp_path / "benchmarks"
    folder.mkdir()
    (folder / "toy.json").write_text(json.dumps(data))
    md = render(data, folder)
    a = f"{statistics.mean([0.3, 0.4, 0.2, 0.25]):.4g} ± {statistics.stdev([0.3, 0.4, 0.2, 0.25]):.2g}"
    assert f"| A | 0, 1, 2, 3 | {statistics.mean([1.0, 1.2, 1.1, 1.1]):.4g} | 300 | {a} |" in md  # kept after 300 s
    assert "| B | 0, 1 | 0.925 | — | 0.5 (1 of 2 diverged) |" in md
    # the one fit that shared its CPU says so under its run, and only it
    assert md.count("a shared CPU") == 1 and "other processes kept 1.25 cores busy" in md.split("### A, seed 1")[1]
    assert "a shared CPU" not in md.split("### A, seed 1")[1].split("### A, seed 2")[1]
    (row,) = [line for line in benchmarks(Results(tmp_path), {"kind": "benchmarks"}) if line.startswith("| toy")]
    assert "0.5 (1 of 2 diverged) (B, 2 seeds)" in row
    assert row.endswith("| machine of B, 2026-12-02 |")  # where the chosen method's last run ran, not the file's last
    # a SUBNET run on another machine is named beside it: the row's two columns are then not one run's
    key, subnet = run("deepSI SUBNET, best on validation", 0, 0.8, 0.45)
    subnet["info"] |= {"model": "SUBNET", "machine": "another machine"}
    (folder / "toy.json").write_text(json.dumps({"experiment": "toy", "runs": {**runs, key: subnet}}))
    (row,) = [line for line in benchmarks(Results(tmp_path), {"kind": "benchmarks"}) if line.startswith("| toy")]
    assert row.endswith("| machine of B, 2026-12-02; SUBNET: another machine, 2026-12-01 |")


def test_where_every_method_is_cross_validated_the_readme_chooses_by_those_scores(tmp_path):
    """Runs of ``make reproduce ... --folds K`` record each fold's score and their mean: the results file gets a
    cross-validated column (the chosen order's mean, averaged over the seeds that have one), and the README's ssm-ms
    column the method of the lowest one, here A (cross-validated 1.0 against 1.4) although B's held-out end validated
    better (0.5 against 0.9); while one method lacks it, the held-out end's judge stays (B)."""
    from experiments.benchmark_results import render
    from experiments.readme import Results, benchmarks
    from ssm_ms.forecasting.benchmark_results import run_key

    def run(method, seed, val, cv, rmse, order=None):
        info = {"method": method, "seed": seed, "unit": "V", "model": "SSM-LL", "experiment": "toy"}
        info |= {"machine": "m", "date": "2026-12-01T00:00:00+00:00", "validation": {"val_sim_rmse": val}}
        if cv is not None:
            key = "" if order is None else str(order)
            info["selection"] = {"folds": 3, "cross-validated (mean over the folds)": {key: cv, "99": 0.0}}
            info["selection"] |= {} if order is None else {"chosen": order}
        row = {"samples": 100, "n_init": 10, "seconds": 0.1, "rmse": rmse, "nrmse": None, "fit_index": None}
        return run_key(info), {
            "info": info,
            "tests": {
                "test": row,
            },
        }

    folder = tmp_path / "benchmarks"
    folder.mkdir()

    def readme_row(runs):
        data = {"experiment": "toy", "runs": dict(runs)}
        (folder / "toy.json").write_text(json.dumps(data))
        (row,) = [line for line in benchmarks(Results(tmp_path), {"kind": "benchmarks"}) if line.startswith("| toy")]
        return data, row

    a = [run("A", 0, 0.9, 0.8, 0.3, order=4), run("A", 1, 0.9, 1.2, 0.3, order=4), run("A", 2, 0.9, None, 0.3)]
    data, row = readme_row([*a, run("B", 0, 0.5, 1.4, 0.6)])
    assert "(A, 3 seeds)" in row
    md = render(data, folder)
    assert "| method | seeds | validation | cross-validated | kept after (s) | test |" in md
    assert (
        "| A | 0, 1, 2 | 0.9 | 1 | — | 0.3 ± 0 |" in md
    )  # the mean of the two seeds cross-validated and "| B | 0 | 0.5 | 1.4 | — | 0.6 |" in md
    assert "each held-out part of the training recording in turn" in md
    _, row = readme_row([*a, run("B", 0, 0.5, None, 0.6)])
    assert "(B, 1 seed)" in row


def test_amortised_nodes_on_cascaded_tanks_end_to_end_and_their_score_by_hand(tmp_path):
    """The benchmark's amortised-node config shrunk (windows at every sample), then ``cli.py test``: the results
    file's RMSE equals the encoder's reading of samples 30..49 of the normalised test recording, f iterated under the
    test inputs from sample 50, the statistics undone by hand."""
    where = ["--data.init_args.dir_placement", str(DATA), "--trainer.logger.init_args.save_dir", str(tmp_path)]
    small = [
        "--trainer.max_time", "null", "--trainer.max_epochs", "10", "--trainer.val_check_interval", "10",
        "--trainer.enable_progress_bar", "false",
    ]  # fmt: skip
    cli_main(["fit", "--config", "configs/benchmarks/cascaded_tanks_amortised.yaml", *where, *small])
    best = tmp_path / "cascaded_tanks_amortised" / "version_0" / "checkpoints" / "best.ckpt"
    test = [
        "test", "--config", "configs/benchmarks/cascaded_tanks_amortised_test.yaml", "--data.init_args.dir_placement",
        str(DATA), "--model.init_args.ssm_checkpoint", str(best), "--model.init_args.results_dir", str(tmp_path),
        "--model.init_args.figures_dir", "null", "--trainer.enable_progress_bar", "false",
    ]  # fmt: skip
    cli_main(test)
    (run,) = json.loads((tmp_path / "cascaded_tanks.json").read_text())["runs"].values()
    assert run["info"]["method"] == "SSM-FC with a linear part (d = 10) + node encoder" and run["info"]["seed"] == 0
    assert run["info"]["validation"]["val_sim_rmse"] > 0

    model = MultipleShootingModule.load_from_checkpoint(best, weights_only=False).eval()
    saved = torch.load(best, weights_only=False)
    norm = next(v for v in saved.values() if isinstance(v, dict) and "normalizer" in v)
    y_mean, y_std = norm["normalizer"]["mean"].item(), norm["normalizer"]["std"].item()
    u_mean, u_std = norm["input_normalizer"]["mean"].item(), norm["input_normalizer"]["std"].item()
    train_data, test_data = nb.Cascaded_Tanks(dir_placement=str(DATA))

    def free_run(data) -> list[float]:
        """The normalised outputs of a recording's free run from the node encoder's state of samples 30-49."""
        y = torch.tensor((data.y - y_mean) / y_std, dtype=torch.float32).view(1, -1, 1)
        u = torch.tensor((data.u - u_mean) / u_std, dtype=torch.float32).view(1, -1, 1)
        with torch.no_grad():
            x = model.node_encoder(y[:, 30:50], u[:, 30:50])
            out = []
            for t in range(50, 1024):
                out.append(model.g(x)[0, 0].item())
                x = model.f(x, u[:, t])
        return out

    normalised = free_run(test_data)
    row = run["tests"]["test"]
    beyond = np.flatnonzero(~(np.abs(normalised) <= 100.0))  # 100 training stds: a run past them diverged
    if len(beyond):  # a model this brief may grow: then the row says where, and gives no score
        assert row["rmse"] is None and row["diverged_at"] == 50 + beyond[0]
    else:
        rmse = math.sqrt(np.mean((np.array(normalised) * y_std + y_mean - test_data.y[50:]) ** 2))
        assert row["rmse"] == pytest.approx(rmse, rel=1e-4) and row["diverged_at"] is None

    # the config validates with val_run_in: all: the kept epoch's score is the free run of the whole training
    # recording from its first 50 samples, the RMSE of its held-out end (the last 205 samples) alone
    normalised = free_run(train_data)
    held = np.array(normalised[819 - 50 :]) * y_std + y_mean
    validation = run["info"]["validation"]["val_sim_rmse"]
    if np.all(np.abs(normalised) <= 100.0):
        assert validation == pytest.approx(math.sqrt(np.mean((held - train_data.y[819:]) ** 2)), rel=1e-4)
    else:  # a run past 100 training stds diverged: no finite score
        assert validation == math.inf


def test_a_segment_held_out_inside_the_recording_trains_on_both_sides_of_it():
    """``val_at``: the held-out segment (a fifth, 205 samples) starts at that fraction of the training recording; the
    windows are cut from the samples before it and after it (none overlaps it), normalised with their statistics, the
    validation recording is the segment behind its run-in; ``val_at`` 0.8 is the default's end, and one past it is
    refused. Against slices of the loader's arrays."""
    train, _ = nb.Cascaded_Tanks(dir_placement=str(DATA))
    y = np.asarray(train.y, dtype=np.float64)
    for val_at, start, run_in in ((0.4, 410, "all"), (0.0, 0, "all"), (0.4, 410, 0)):
        dm = tanks(window=100, batch_size=4, val_at=val_at, val_run_in=run_in)
        dm.setup("fit")
        end = start + 205
        pieces = [(a, b) for a, b in ((0, start), (end, 1024)) if b > a]  # the training part, around the segment
        for (y_piece, _), (a, b) in zip(dm.raw_recordings("train"), pieces, strict=True):
            np.testing.assert_array_equal(y_piece[:, 0], y[a:b].astype(np.float32))
        offsets = [a for a, _ in pieces]
        windows = dm.datasets["train"].arrays["y"][:, :, 0]
        at = [offsets[r] + s for r, s in dm.window_origins.tolist()]
        for w, a in zip(windows, at):
            np.testing.assert_array_equal(w, y[a : a + 100].astype(np.float32))
            assert a + 100 <= start or a >= end  # no window sees the held-out segment
        assert start == 0 or (min(at) < start and max(at) >= end)  # windows on both sides
        seen = np.concatenate([y[a : a + 100] for a in at])
        np.testing.assert_allclose(dm.normalizer.mean.item(), seen.mean(), rtol=1e-5)
        first = start if run_in == 0 else 0
        val = next(iter(dm.split_dataloader("val")))["y"][0, :, 0].numpy()
        np.testing.assert_allclose(val, (y[first:end] - seen.mean()) / seen.std(), rtol=1e-4, atol=1e-5)
        assert dm.val_length == 205 and dm.val_scored_from == max(50, start - first)
        np.testing.assert_array_equal(dm.raw_recordings("val")[0][0][:, 0], y[start:end].astype(np.float32))
    end_default, end_given = tanks(window=100), tanks(window=100, val_at=0.8)
    np.testing.assert_array_equal(end_default.window_origins, end_given.window_origins)
    np.testing.assert_array_equal(end_default.raw_recordings("val")[0][0], end_given.raw_recordings("val")[0][0])
    with pytest.raises(ValueError, match="val_at must be in \\[0, 0.8\\]"):
        tanks(val_at=0.9)


def test_the_validation_may_run_in_through_the_training_recording():
    """``val_run_in``: the validation recording is the held-out end behind that many training samples, scored from
    the first held-out sample; ``raw_recordings("val")`` (a peer's validation) stays the held-out end."""
    train, _ = nb.Cascaded_Tanks(dir_placement=str(DATA))
    cut = round(1024 * 0.8)
    for run_in, scored_from in ((0, 50), (30, 50), (300, 300), ("all", cut)):
        dm = tanks(window=100, batch_size=4, val_run_in=run_in)
        dm.setup("fit")
        start = cut - (cut if run_in == "all" else run_in)
        val = next(iter(dm.split_dataloader("val")))["y"][0, :, 0].numpy()
        expected = (np.asarray(train.y[start:]) - dm.normalizer.mean.item()) / dm.normalizer.std.item()
        np.testing.assert_allclose(val, expected, rtol=1e-4, atol=1e-5)
        assert dm.val_length == 1024 - cut and dm.val_scored_from == scored_from
        np.testing.assert_array_equal(dm.raw_recordings("val")[0][0][:, 0], np.asarray(train.y[cut:], np.float32))
    for wrong in (-1, cut + 1, "some"):
        with pytest.raises(ValueError, match="val_run_in must be 'all' or a number of samples in \\[0, 819\\]"):
            tanks(val_run_in=wrong)
