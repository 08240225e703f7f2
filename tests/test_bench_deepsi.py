"""benchmarks/bench_deepsi.py end to end on a few trajectories (slow; skipped without deepSI, `make peers`)."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_the_deepsi_comparison_runs_and_scores_both(tmp_path):
    pytest.importorskip("deepSI")
    out = tmp_path / "deepsi.md"
    cmd = [sys.executable, "benchmarks/bench_deepsi.py", "--tiny", "--val-freq", "10", "--deepsi-seconds", "5"]
    cmd += ["--work", str(tmp_path / "work"), "--out", str(out)]
    subprocess.run(cmd, cwd=ROOT, check=True, timeout=900)
    results = json.loads(out.with_suffix(".json").read_text())
    assert [r["system"] for r in results] == ["pendulum", "lorenz"]
    for r in results:
        methods = [row["method"] for row in r["rows"]]
        assert methods[0].startswith("ssm-ms") and all(m.startswith("deepSI") for m in methods[1:])
        assert all(row["mse"] >= 0 and row["seconds"] > 0 for row in r["rows"])
    assert "| deepSI SUBNET, last model |" in out.read_text()
