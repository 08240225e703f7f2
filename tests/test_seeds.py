"""Scores over seeds (experiments.seeds), against means and standard deviations computed here."""

from __future__ import annotations

import json
import statistics

import pytest

from experiments.seeds import main

SCORES = {
    "config seed": (0.13, 0.50, 0.68, 0.82, 1.0),
    "seed1": (0.20, 0.41, 1.10, 0.79, 0.9),
    "seed2": (0.16, 0.62, 0.95, 0.90, 1.0),
}


def write_seed(results_dir, experiment, ukf, encoder, w1, largest, wings):
    """A results json as :mod:`ssm_ms.forecasting.results` writes it: two methods of one SSM."""
    dynamics = {"free_run": {"wasserstein": [w1], "both_wings_share": wings}, "lyapunov": {"largest": largest}}
    runs = {}
    for method, mse in (("ukf", ukf), ("encoder", encoder)):
        runs[method] = {
            "info": {"experiment": experiment, "method": method, "model": "SSM-LL", "inference": method},
            "summary": {
                f"{method}/clean/mse": {"mean": mse, "std": 0.1, "n": 64},
                "last/clean/mse": {"mean": 9.0, "std": 1.0, "n": 64},
            },
            "analysis": {
                "valid_time": {"mean_steps": 1000 * (1 - mse)},
                "dynamics": dynamics,
                "true_system": {"largest": 0.88},
            },
        }
    (results_dir / f"{experiment}.json").write_text(json.dumps({"experiment": experiment, "runs": runs}))


def test_seeds_are_gathered_as_mean_and_sample_std(tmp_path, capsys):
    for seed, values in SCORES.items():
        write_seed(tmp_path, "lor_cpu" if seed == "config seed" else f"lor_cpu_{seed}", *values)
    write_seed(tmp_path, "lor_cpu_noisy", 5.0, 5.0, 5.0, 5.0, 0.0)  # another experiment: not a seed of this one
    md = main(["lor_cpu", "--results-dir", str(tmp_path)])
    table = json.loads((tmp_path / "lor_cpu_seeds.json").read_text())
    assert table["seeds"] == ["config seed", "seed1", "seed2"]
    for i, label in enumerate(
        [
            "ukf: clean/mse",
            "encoder: clean/mse",
            "f: W1 of x over the free runs",
            "f: largest Lyapunov exponent",
            "f: free runs visiting both wings",
        ]
    ):
        values = [v[i] for v in SCORES.values()]
        got = table["summary"][label]
        assert got["mean"] == pytest.approx(statistics.mean(values)) and got["n"] == 3
        assert got["std"] == pytest.approx(statistics.stdev(values))
    assert table["summary"]["ukf: valid time (steps)"]["mean"] == pytest.approx(
        1000 * (1 - statistics.mean([0.13, 0.20, 0.16]))
    )
    assert table["summary"]["true system: largest Lyapunov exponent"]["std"] == pytest.approx(0.0)
    assert not any(label.startswith("last") for label in table["rows"])  # references are not the method's scores
    text = md.read_text()
    assert "| quantity | config seed | seed1 | seed2 | mean ± std over seeds |" in text
    main(["lor_cpu", "--results-dir", str(tmp_path)])  # its own output is not read as a seed
    assert json.loads((tmp_path / "lor_cpu_seeds.json").read_text())["seeds"] == table["seeds"]


def test_a_seed_whose_forecasts_diverged_on_some_sequences_says_how_many(tmp_path):
    for seed, values in SCORES.items():
        write_seed(tmp_path, "lor_cpu" if seed == "config seed" else f"lor_cpu_{seed}", *values)
    data = json.loads((tmp_path / "lor_cpu_seed2.json").read_text())
    data["runs"]["ukf"]["summary"]["ukf/clean/mse"]["non_finite"] = 3  # its mean is over the 61 others
    (tmp_path / "lor_cpu_seed2.json").write_text(json.dumps(data))
    main(["lor_cpu", "--results-dir", str(tmp_path)])
    table = json.loads((tmp_path / "lor_cpu_seeds.json").read_text())
    assert table["rows"]["ukf: clean/mse, non-finite sequences"] == {"config seed": 0.0, "seed1": 0.0, "seed2": 3.0}
    assert table["summary"]["ukf: clean/mse, non-finite sequences"]["mean"] == pytest.approx(1.0)  # per seed
    assert "encoder: clean/mse, non-finite sequences" not in table["rows"]  # no seed's encoder diverged
    assert table["summary"]["ukf: clean/mse"]["n"] == 3  # the three seeds' scores are still gathered


def test_no_results_is_one_message(tmp_path):
    with pytest.raises(SystemExit, match="no results for 'nothing_cpu'"):
        main(["nothing_cpu", "--results-dir", str(tmp_path)])
