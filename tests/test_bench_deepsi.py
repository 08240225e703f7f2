"""benchmarks/bench_deepsi.py end to end on a few trajectories (slow; skipped without deepSI, `make peers`)."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_the_deepsi_comparison_runs_and_scores_both(tmp_path):
    pytest.importorskip("deepSI")
    cmd = [sys.executable, "benchmarks/bench_deepsi.py", "--tiny", "--val-freq", "10", "--deepsi-seconds", "5"]
    cmd += ["--work", str(tmp_path / "work"), "--out-dir", str(tmp_path)]
    subprocess.run(cmd, cwd=ROOT, check=True, timeout=900)
    for system in ("pendulum", "lorenz"):
        out = tmp_path / f"deepsi_{system}_tiny.md"
        r = json.loads(out.with_suffix(".json").read_text())
        assert r["system"] == system
        methods = [row["method"] for row in r["rows"]]
        assert methods[0].startswith("ssm-ms") and all(m.startswith("deepSI") for m in methods[1:])
        assert all(row["mse"] >= 0 and row["seconds"] > 0 for row in r["rows"])
        assert "| deepSI SUBNET, last model |" in out.read_text()


@pytest.mark.slow
def test_a_config_of_files_trains_on_the_same_sequences_cut_into_windows(tmp_path):
    """``--ssm-configs deepsi_pendulum_amortised_fc.yaml`` (a FileDataModule config): trained on the .npz of the
    bench's own training sequences, cut into windows at every sample, and scored beside the system's config."""
    pytest.importorskip("deepSI")
    config = "benchmarks/configs/deepsi_pendulum_amortised_fc.yaml"
    cmd = [sys.executable, "benchmarks/bench_deepsi.py", "--systems", "pendulum", "--tiny", "--val-freq", "10"]
    cmd += ["--deepsi-seconds", "5", "--ssm-configs", config, "--work", str(tmp_path), "--out-dir", str(tmp_path)]
    subprocess.run(cmd, cwd=ROOT, check=True, timeout=900)
    rows = json.loads((tmp_path / "deepsi_pendulum_tiny.json").read_text())["rows"]
    assert config in rows[1]["method"] and "node encoder" in rows[1]["method"]
    (data,) = tmp_path.glob("pendulum-*-train.npz")
    with np.load(data) as arrays:
        n, t = arrays["y"].shape[:2]
        assert arrays["u"].shape[:2] == (n, t)
    (ckpt,) = tmp_path.glob("*/pendulum-*-1/checkpoints/last.ckpt")
    saved = torch.load(ckpt, map_location="cpu", weights_only=False)
    # 2 epochs (--tiny) of windows of 70 starting at every sample, 256 a batch
    assert saved["global_step"] == 2 * -(-(n * (t - 70 + 1)) // 256)


@pytest.mark.slow
def test_subnet_runs_a_benchmark_by_its_protocol(tmp_path):
    """``--benchmarks cascaded_tanks``: SUBNET's last and best models scored into a results file of their own."""
    pytest.importorskip("deepSI")
    data = ROOT.parent / "shared" / "data" / "nonlinear_benchmarks"
    cmd = [sys.executable, "benchmarks/bench_deepsi.py", "--benchmarks", "cascaded_tanks", "--tiny", "--val-freq", "10"]
    cmd += [
        "--deepsi-seconds",
        "5",
        "--dir-placement",
        str(data),
        "--work",
        str(tmp_path),
        "--results-dir",
        str(tmp_path),
    ]
    subprocess.run(cmd, cwd=ROOT, check=True, timeout=900)
    runs = json.loads((tmp_path / "cascaded_tanks.json").read_text())["runs"]
    assert sorted(runs) == ["deepSI SUBNET, best on validation", "deepSI SUBNET, last model"]
    assert all(run["tests"]["test"]["n_init"] == 50 for run in runs.values())
    # what other processes ran during its fit, as ssm-ms's rows record it: a fraction of the 2 cores, not missing
    assert all(0.0 <= run["info"]["validation"]["cpu_others"] < 4.0 for run in runs.values())
    assert (tmp_path / "cascaded_tanks.md").read_text().startswith("# cascaded_tanks")  # rendered by experiments/
    assert (tmp_path / "cascaded_tanks-subnet-best.pt").is_file()


def test_the_spread_over_seeds_is_each_methods_mean_and_sample_deviation(tmp_path):
    """write_seeds, on two hand-made runs: MSEs 1 and 3 give 2 +- 1.4 (sample std sqrt(2)), 4 and 8 give 6 +- 2.8 and
    the ratio 3.00 to the first row; a method missing from a seed is counted once, no spread, its cell a dash."""
    sys.path.insert(0, str(ROOT))
    from benchmarks.bench_deepsi import write_seeds

    def run(seed, ours, theirs, extra=None):
        rows = [{"method": "ours", "mse": ours}, {"method": "theirs", "mse": theirs}]
        if extra is not None:
            rows.append({"method": "extra", "mse": extra})
        provenance = [f"- Date: day {seed}", "- Machine: box", f"- Command: `run --seed {seed}`"]
        return {"seed": seed, "title": "t", "n_predict": 5, "n_filter": 3, "units": "u", "rows": rows,
                "provenance": provenance}  # fmt: skip

    out = tmp_path / "seeds.md"
    write_seeds([run(1, 3.0, 8.0), run(0, 1.0, 4.0, extra=0.5)], out)
    text = out.read_text()
    assert "| ours | 2 | 2 +- 1.4 | 1.00 | 1 | 3 |" in text
    assert "| theirs | 2 | 6 +- 2.8 | 3.00 | 4 | 8 |" in text
    assert "| extra | 1 | 0.5 | 0.25 | 0.5 | - |" in text
    assert "- seed 0: day 0; box; `run --seed 0`" in text.splitlines()[-2]


def test_a_seed_of_another_setting_is_refused_before_training_and_the_committed_folders_pass(tmp_path):
    """check_seed_folder: a folder with seed 0 run at ``--deepsi-seconds 250`` refuses seed 1 at the default budget
    (one message naming the difference and the fix), takes seed 1 at 250 s (the order of the arguments, where files
    go, which other systems run and defaults given explicitly do not count), and takes seed 0 at any setting (that
    run replaces it). The committed folders pass for the commands that wrote them."""
    sys.path.insert(0, str(ROOT))
    from types import SimpleNamespace

    from benchmarks.bench_deepsi import check_seed_folder

    def save(folder, seed, argv):
        folder.mkdir(exist_ok=True)
        command = "python benchmarks/bench_deepsi.py " + " ".join(argv)
        run = {"seed": seed, "provenance": ["- Date: d", "- Machine: m", f"- Command: `{command}`"]}
        (folder / f"deepsi_pendulum_seed{seed}.json").write_text(json.dumps(run))

    base = ["--systems", "pendulum", "--ssm-configs", "c.yaml"]
    save(tmp_path, 0, [*base, "--deepsi-seconds", "250", "--seed", "0"])
    with pytest.raises(SystemExit) as refused:
        check_seed_folder(tmp_path, "deepsi_pendulum", SimpleNamespace(seed=1, argv=[*base, "--seed", "1"]))
    message = str(refused.value)
    assert message.startswith("error: ") and "\n" not in message
    assert "deepsi_seconds 250.0 there, None here" in message and "give this setting its own --out-dir" in message
    at_250 = "--ssm-configs c.yaml --systems pendulum lorenz --work elsewhere --deepsi-seconds 250 --seed=1"
    at_250 = [*at_250.split(), "--val-freq", "250"]
    check_seed_folder(tmp_path, "deepsi_pendulum", SimpleNamespace(seed=1, argv=at_250))
    check_seed_folder(tmp_path, "deepsi_pendulum", SimpleNamespace(seed=0, argv=[*base, "--seed", "0"]))

    results = ROOT / "benchmarks" / "results"
    pendulum = ["--systems", "pendulum", "--ssm-configs", "benchmarks/configs/deepsi_pendulum_amortised_fc.yaml"]
    committed = {
        results: [*pendulum, "--seed", "3"],
        results / "deepsi_pendulum_250s": [
            *pendulum, "--deepsi-seconds", "250", "--seed", "3", "--out-dir", "benchmarks/results/deepsi_pendulum_250s"
        ],
    }  # fmt: skip
    for folder, argv in committed.items():
        check_seed_folder(folder, "deepsi_pendulum", SimpleNamespace(seed=3, argv=argv))
