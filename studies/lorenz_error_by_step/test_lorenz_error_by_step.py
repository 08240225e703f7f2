"""Tests of lorenz_error_by_step.py, frozen with the study: `make test` does not collect studies/ (testpaths: tests/).
Run: `.venv/bin/python -m pytest studies/lorenz_error_by_step`."""

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))  # the repository's packages and studies/, from wherever pytest runs


def test_lorenz_error_by_step_averages_to_the_protocol_score(tmp_path):
    """lorenz_error_by_step.py on the pretrained T = 1000 SSM and 4 short test sequences: the mean of its
    predicted steps is the score ``cli.py test`` writes for the same stage (the protocol's own path: Lightning's test
    loop, its metric); the true model's step-0 error on those sequences is below the SSM's; the second table's error
    at given sample 100 is the step-0 error of a run that filters only the first 100 (both filters are causal); a
    wrong config is refused in one line."""
    import json
    import subprocess
    import sys

    from studies.lorenz_error_by_step import lorenz_error_by_step

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
