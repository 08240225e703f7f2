"""The results tables of the README and docs/results.md are generated from ``results/*.json`` (``python -m
experiments.readme``): they fail here when a document and the results files disagree, regenerated in memory
and compared."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from experiments import readme
from experiments.results import score_cell

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
RESULTS = ROOT / "results"


@pytest.mark.parametrize("document", readme.DOCUMENTS, ids=lambda p: p.name)
def test_the_tables_are_those_the_results_files_give(document):
    stale = readme.stale(document.read_text(encoding="utf-8"), RESULTS)
    assert stale == [], (
        f"{document.name}'s tables {stale} differ from results/*.json: run "
        f"`python -m experiments.readme` and commit {document.name}"
    )


def test_every_table_has_its_markers_in_exactly_one_document():
    names = [m.group("name") for d in readme.DOCUMENTS for m in readme.MARKER.finditer(d.read_text(encoding="utf-8"))]
    assert sorted(names) == sorted(readme.tables())


def test_every_row_is_produced_by_a_command_a_clean_clone_can_run():
    """A README row's command is a promise (docs/tests.md, "The README is a test"): none may need a run folder of this machine (``runs/``), as
    a row tested by hand from a local checkpoint would; such a row is produced through ``make reproduce`` instead."""
    text = "\n".join(d.read_text(encoding="utf-8") for d in readme.DOCUMENTS)
    rows = [line for m in readme.MARKER.finditer(text) for line in m.group("body").splitlines()]
    local = [next(c.strip() for c in row.split("|")[1:] if c.strip()) for row in rows if "runs/" in row]
    assert not local, f"README rows produced by a command that needs a local run: {local}"


@pytest.fixture
def results_copy(tmp_path: Path) -> Path:
    for path in RESULTS.glob("*.json"):
        shutil.copy2(path, tmp_path / path.name)
    shutil.copytree(RESULTS / "benchmarks", tmp_path / "benchmarks")
    return tmp_path


def _edit(path: Path, change) -> None:
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


def test_a_changed_score_makes_its_table_stale(results_copy):
    text = (ROOT / "docs" / "results.md").read_text(encoding="utf-8")  # the page of the full-size table
    assert readme.stale(text, results_copy) == []

    def change(data):
        data["runs"]["encoder"]["summary"]["encoder/noisy/mse"]["mean"] = 0.0123456

    _edit(results_copy / "pendulum.json", change)
    assert readme.stale(text, results_copy) == ["full-size"]
    rewritten = readme.render(text, results_copy)
    assert "0.01235 ± 0.0027" in rewritten and readme.stale(rewritten, results_copy) == []
    assert rewritten.replace("0.01235 ± 0.0027", "0.01521 ± 0.0027") == text  # nothing outside the markers moves


def test_a_row_names_the_pipeline_that_produced_it_and_its_budget(results_copy):
    """quad_fc.json keeps two records of one run (encoder budget 25, then resumed to 100): the row's command is the one
    recorded with its test; the encoder's epochs and runs come from its stage command."""
    table = "\n".join(readme.methods(readme.Results(results_copy), readme.tables()["full-size"]))
    quad_fc = next(line for line in table.splitlines() if "reproduce quad_fc" in line)
    assert "--encoder-epochs 100" in quad_fc and "encoder 100 epochs" in quad_fc and "in 5 runs" in quad_fc
    assert "--encoder-epochs 25" not in table
    lstm = next(line for line in table.splitlines() if "pendulum_lstm" in line)
    assert "--baseline-epochs 1000" in lstm and "LSTM 1000 epochs" in lstm and "in 5 runs" in lstm


def test_the_check_command_exits_1_on_a_stale_document(tmp_path, results_copy, capsys):
    """Both documents are checked; a table edited by hand in one of them (the Lorenz sweep, docs/results.md's) is
    named, and the rewrite restores it."""
    readme_copy, page = tmp_path / "README.md", tmp_path / "results.md"
    readme_copy.write_text(README.read_text(encoding="utf-8"))
    original = (ROOT / "docs" / "results.md").read_text(encoding="utf-8")
    page.write_text(original)
    both = [str(readme_copy), str(page), "--results-dir", str(results_copy)]
    assert readme.main([*both, "--check"]) == 0
    sweep = original.index(readme.BEGIN.format(name="lorenz-sweep"))  # a cell of that table edited by hand
    page.write_text(original[:sweep] + original[sweep:].replace("| SSM-LL + UKF | ", "| SSM-LL + UKF | 1 ", 1))
    assert readme.main([*both, "--check"]) == 1
    err = capsys.readouterr().err
    assert "lorenz-sweep" in err and "results.md" in err and "README.md" not in err
    assert readme.main(both) == 0
    assert page.read_text() == original and readme_copy.read_text() == README.read_text(encoding="utf-8")


def test_markers_that_name_no_table_or_are_not_closed_are_refused(results_copy):
    with pytest.raises(KeyError, match="no such table"):
        readme.render("<!-- results:begin nothing -->\n<!-- results:end -->\n", results_copy)
    with pytest.raises(ValueError, match="without its"):
        readme.render("<!-- results:begin full-size -->\n| a |\n", results_copy)


def test_cells_read_as_the_results_files_count_them():
    assert score_cell({"mean": 663.3, "std": 190.2, "n": 64}) == "663.3 ± 190"
    diverged = {"mean": 3.29e5, "std": 2.7e5, "n": 64, "non_finite": 1}
    assert score_cell(diverged) == "3.29e+05 ± 2.7e+05 (1 of 64 non-finite, left out)"
    assert score_cell({**diverged, "non_finite": 64}) == "non-finite on all 64"
    assert readme.minutes(2290) == "38 min" and readme.minutes(9573.6) == "2.7 h" and readme.minutes(235) == "3.9 min"
