"""Tests of lorenz_oracle.py, frozen with the study: `make test` does not collect studies/ (testpaths: tests/).
Run: `.venv/bin/python -m pytest studies/lorenz_oracle`."""

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))  # the repository's packages and studies/, from wherever pytest runs


def test_lorenz_oracle_forecasts_the_truth_from_near_noiseless_measurements(tmp_path):
    """lorenz_oracle.py: with measurement noise std 0.01 the true model's UKF finds the state, so its
    10-step forecast of x matches the generator's noiseless x (closed form: the data itself) to well under the
    noise's variance scaled back; with the paper's noise (std 2.5) the UKF's error is larger, and the particle
    filter's forecasts stay on the sequences (a bootstrap filter cannot find a state from a wide prior through
    near-noiseless measurements, so it is not asked to); one row per config and filter setting."""
    from studies.lorenz_oracle import lorenz_oracle

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
