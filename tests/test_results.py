"""The paper's tables of the experiment registry (configs/experiments.yaml, as experiments.registry reads them), against the transcription beside the paper (../shared/paper/tables.md,
read by this test only: the project itself never reads ../shared), and the table a results file renders."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from experiments.registry import paper_table
from experiments.results import paper_row, render_file, render_markdown

TABLES = Path(__file__).resolve().parents[2] / "shared" / "paper" / "tables.md"
NUMBER = r"-?\d+(?:\.\d+)?"


def transcribed_tables() -> dict[str, list[list[str]]]:
    """``{"Table 1": [[cell, ...], ...]}``: the rows of each table of tables.md, header excluded."""
    if not TABLES.is_file():
        pytest.skip(f"the paper's transcription is not at {TABLES}")
    tables: dict[str, list[list[str]]] = {}
    current = None
    for line in TABLES.read_text().splitlines():
        heading = re.match(r"## (Table \d)", line)
        if heading:
            current = heading.group(1)
            tables[current] = []
        elif line.startswith("## "):
            current = None
        elif current and line.startswith("|") and not line.startswith("|---"):
            tables[current].append([c.strip() for c in line.strip("|").split("|")])
    return {name: rows[1:] for name, rows in tables.items()}  # without the header row


def cell(text: str):
    """``"0.0154 ± 0.0026"`` -> ``(0.0154, 0.0026)``, ``"3592.273"`` -> ``(3592.273, None)``, words stay words."""
    numbers = re.findall(NUMBER, text.replace(",", ""))
    if not numbers:
        return text
    return (float(numbers[0]), float(numbers[1]) if len(numbers) > 1 else None)


def short(name: str) -> str:
    return name.split(" ")[0]  # "LSTM (seq2seq CNN-LSTM)" -> "LSTM", "SSM-RNN (...)" -> "SSM-RNN"


@pytest.mark.parametrize("table,key", [("Table 1", "pendulum"), ("Table 2", "quad")])
def test_image_tables_match_the_transcription(table, key):
    rows = transcribed_tables()[table]
    assert len(rows) == 4
    for name, mse, bce in rows:
        ours = paper_table(key)["rows"][short(name)]
        assert ours == {"noisy/mse": cell(mse), "noisy/bce": cell(bce)}, name


def test_moving_mnist_table_matches_the_transcription():
    rows = transcribed_tables()["Table 3"]
    paper = paper_table("mnist")["rows"]
    assert sorted(cell(bce)[0] for _, bce in rows) == sorted(v["noisy/bce"][0] for v in paper.values())
    ssm = next(bce for name, bce in rows if name.startswith("SSM-LL"))
    assert paper["SSM-LL"]["noisy/bce"] == cell(ssm)


def test_lorenz_table_matches_the_transcription():
    rows = transcribed_tables()["Table 4"]
    assert [short(r[0]) for r in rows] == ["SSM-RNN", "SSM-UKF", "LSTM", "RKN"]
    for name, *values in rows:
        for t, text in zip((10, 100, 1000, 10000), values):
            assert paper_table(f"lorenz_T{t}")["rows"][short(name)]["clean/mse"] == cell(text), (name, t)


def test_each_run_meets_the_paper_row_of_its_method():
    assert paper_table("pendulum_fc_cpu") == paper_table("pendulum") is not None
    assert paper_table("lorenz_T1000_cpu")["table"].endswith("T = 1000 steps)")
    assert paper_table("lorenz_T10")["table"].endswith("T = 10 steps)") and paper_table("oscillator") is None
    assert paper_table("lorenz_T1000_noiseless_cpu") is None  # a variant the paper has no table for
    pendulum, lorenz = paper_table("pendulum"), paper_table("lorenz_T1000")
    assert paper_row(pendulum, {"model": "SSM-FC", "inference": "encoder"}) == "SSM-FC"
    assert paper_row(pendulum, {"model": "SSM-LL", "inference": "pf"}) is None  # the paper has no such row
    assert paper_row(lorenz, {"model": "SSM-LL", "inference": "encoder"}) == "SSM-RNN"
    assert paper_row(lorenz, {"model": "SSM-LL", "inference": "ukf"}) == "SSM-UKF"
    assert paper_row(paper_table("quad"), {"model": "RKN", "inference": None}) == "RKN"
    assert paper_row(paper_table("mnist"), {"model": "RKN", "inference": None}) is None


def test_rendered_table_puts_the_paper_beside_each_method():
    runs = {
        "ukf": {
            "info": {"model": "SSM-LL", "inference": "ukf", "label": "SSM-LL + UKF"},
            "summary": {"ukf/clean/mse": {"mean": 0.8, "std": 1.0}, "last/clean/mse": {"mean": 2.0, "std": 1.0}},
        },
        "rkn": {
            "info": {"model": "RKN", "inference": None, "label": "RKN"},
            "summary": {"rkn/clean/mse": {"mean": 50.0, "std": 9.0}},
        },
    }
    report = render_markdown("lorenz_T1000_cpu", runs)
    assert "| SSM-LL + UKF | 0.8 ± 1 | SSM-UKF | 0.67 |" in report
    assert "| RKN | 50 ± 9 | RKN | 67.76 |" in report
    assert "| last (reference, with SSM-LL + UKF) | 2 ± 1 |  |  |" in report
    assert "| RKN | did not converge | did not converge | 67.76 | out of memory |" in report  # the whole Table 4
    assert "CPU-sized twin" in report
    assert report.index("| SSM-LL + UKF |") < report.index("| RKN | 50")  # the SSMs first, as in the paper


def test_analysis_numbers_read_as_steps_not_exponents():
    from experiments.results import _num

    assert [_num(1000.0), _num(285.4, 2), _num(811.25), _num(0.0123), _num(3.5613), _num(float("inf")), _num(None)] == [
        "1000",
        "285",
        "811",
        "0.0123",
        "3.56",
        "inf",
        "—",
    ]


def test_valid_time_row_after_a_json_round_trip():
    """Error growth keeps forecast-step order once JSON has made its keys strings ("1000" sorts before "250")."""
    import json

    vt = {
        "threshold": 0.5,
        "truth": "noiseless",
        "n_filter": 1000,
        "horizon": 1000,
        "mean_steps": 811.25,
        "std_steps": 281.0,
        "median_steps": 1000.0,
        "mean_seconds": 4.06,
        "mean_lyapunov_times": 3.56,
        "censored_share": 0.61,
        "error_at_step": {1: 0.0014, 250: 0.062, 500: 0.21, 1000: 0.32},
    }
    runs = json.loads(
        json.dumps(
            {"ukf": {"info": {"label": "SSM-LL + UKF"}, "summary": {}, "analysis": {"valid_time": vt}}}, sort_keys=True
        )
    )
    report = render_markdown("lorenz_T1000_noiseless_cpu", runs)
    assert (
        "| SSM-LL + UKF | 811 ± 281 | 1000 | 4.06 | 3.56 | 0.61 | 1: 0.0014, 250: 0.062, 500: 0.21, 1000: 0.32 |"
        in report
    )
    assert "## The paper" not in report  # no paper table for the noise-free variant


def test_hand_written_notes_survive_every_rewrite(tmp_path):
    """``<experiment>.notes.md`` beside a results file is appended to ``<experiment>.md`` each time a run or a
    pipeline rewrites it (a note written into the .md itself would be lost)."""
    from experiments.results import write_pipeline
    from ssm_ms.forecasting.results import write_results

    info = {"experiment": "toy_cpu", "method": "encoder", "model": "SSM-LL", "inference": "encoder"}
    md = render_file(write_results(tmp_path, info, {"encoder/noisy/mse": {"mean": 0.5, "std": 0.1, "n": 4}}))
    assert "## Notes" not in md.read_text()
    (tmp_path / "toy_cpu.notes.md").write_text("The SSM stage was paused 70 minutes.\n")
    write_pipeline(tmp_path, "toy_cpu", "make reproduce EXP=toy SIZE=cpu", {"stages": [], "total_seconds": 1.0})
    info2 = {**info, "method": "lstm", "model": "LSTM", "inference": None}
    text = render_file(
        write_results(tmp_path, info2, {"lstm/noisy/mse": {"mean": 0.7, "std": 0.1, "n": 4}})
    ).read_text()
    assert text.count("The SSM stage was paused 70 minutes.") == 1
    assert text.index("| 0.5 ± 0.1 |") < text.index("| 0.7 ± 0.1 |") < text.index("## Notes")


def test_an_interrupted_write_leaves_the_results_file_as_it_was(tmp_path, monkeypatch):
    """Ctrl-C (or SIGTERM, a full disk) while a results file is written leaves the file with every run it held,
    not a truncated one (which the next run would have replaced by its own row alone)."""
    import json

    from ssm_ms.forecasting.results import write_results

    info = {"experiment": "toy", "method": "encoder", "model": "SSM-LL", "inference": "encoder"}
    write_results(tmp_path, info, {"encoder/noisy/mse": {"mean": 0.5, "std": 0.1, "n": 4}})
    before = {p.name: p.read_text() for p in tmp_path.iterdir()}
    written = Path.write_text

    def cut_short(self, text, *args, **kwargs):  # half the text reaches the disk, then the interrupt
        written(self, text[: len(text) // 2], *args, **kwargs)
        raise KeyboardInterrupt

    monkeypatch.setattr(Path, "write_text", cut_short)
    with pytest.raises(KeyboardInterrupt):
        write_results(
            tmp_path,
            {**info, "method": "lstm", "model": "LSTM", "inference": None},
            {"lstm/noisy/mse": {"mean": 0.7, "std": 0.1, "n": 4}},
        )
    monkeypatch.undo()
    assert {p.name: p.read_text() for p in tmp_path.iterdir()} == before  # no half file, no leftover
    assert list(json.loads((tmp_path / "toy.json").read_text())["runs"]) == ["encoder"]


def test_an_unreadable_results_file_is_moved_aside_not_overwritten(tmp_path):
    """A results file that is not JSON (cut short by an older version, edited by hand) is kept as
    ``<name>.unreadable`` with a warning that names it; the new run starts a new file."""
    import json

    from ssm_ms.forecasting.results import write_results

    broken = '{"experiment": "toy", "runs": {"encoder": {"summary": {"encoder/noisy/mse": {"mean": 0.'
    (tmp_path / "toy.json").write_text(broken)
    info = {"experiment": "toy", "method": "lstm", "model": "LSTM", "inference": None}
    with pytest.warns(UserWarning, match=r"toy\.json is not a results file .* moved to .*toy\.json\.unreadable"):
        write_results(tmp_path, info, {"lstm/noisy/mse": {"mean": 0.7, "std": 0.1, "n": 4}})
    assert (tmp_path / "toy.json.unreadable").read_text() == broken
    assert list(json.loads((tmp_path / "toy.json").read_text())["runs"]) == ["lstm"]
    (tmp_path / "toy.json").write_text("[]")  # broken again: the first file set aside is kept beside the second
    with pytest.warns(UserWarning, match=r"moved to .*toy\.json\.unreadable-2"):
        write_results(tmp_path, info, {"lstm/noisy/mse": {"mean": 0.7, "std": 0.1, "n": 4}})
    assert (tmp_path / "toy.json.unreadable").read_text() == broken
    assert (tmp_path / "toy.json.unreadable-2").read_text() == "[]"


def test_a_resumed_stage_says_so_in_the_pipeline_table(tmp_path):
    from experiments.results import write_pipeline

    md = write_pipeline(
        tmp_path,
        "toy_cpu",
        "make reproduce EXP=toy SIZE=cpu",
        {
            "total_seconds": 9.0,
            "stages": [
                {"command": "python cli.py fit --config a.yaml", "seconds": 7.5, "runs": 3},
                {"command": "python cli.py test --config a.yaml", "seconds": 1.5},
            ],
        },
    ).read_text()
    assert "| `python cli.py fit --config a.yaml` | 7.5 (in 3 runs: resumed from its last completed epoch) |" in md
    assert "| `python cli.py test --config a.yaml` | 1.5 |" in md


def test_a_record_replaces_the_one_its_run_was_started_with_and_keeps_the_others(tmp_path):
    """Each command keeps its own record; a run resumed with a larger budget replaces its first command's."""
    import json

    from experiments.results import write_pipeline

    def pipeline(seconds):
        return {
            "total_seconds": seconds,
            "stages": [{"command": "python cli.py fit --config a.yaml", "seconds": seconds}],
        }

    write_pipeline(tmp_path, "toy", "reproduce toy --encoder-epochs 8", pipeline(8.0))
    write_pipeline(tmp_path, "toy", "reproduce toy_lstm", pipeline(3.0))
    md = write_pipeline(
        tmp_path,
        "toy",
        "reproduce toy --encoder-epochs 10",
        pipeline(10.0),
        replaces="reproduce toy --encoder-epochs 8",
    ).read_text()
    records = json.loads((tmp_path / "toy.json").read_text())["pipelines"]
    assert sorted(records) == ["reproduce toy --encoder-epochs 10", "reproduce toy_lstm"]
    assert "--encoder-epochs 8" not in md and md.count("## How this was produced") == 1


def _markdown_table(lines: list[str], first_header: str) -> list[dict[str, str]]:
    """The rows of the markdown table whose first header is ``first_header``, as {header: cell}."""
    start = next(i for i, line in enumerate(lines) if line.startswith(f"| {first_header} |"))
    header = [c.strip() for c in lines[start].strip("|").split("|")]
    rows = []
    for line in lines[start + 2 :]:
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip("|").split("|")]
        assert len(cells) == len(header), line
        rows.append(dict(zip(header, cells)))
    return rows


def test_analysis_tables_leave_out_columns_no_method_fills():
    """An image experiment's f has no x statistics (W1, both wings) and its system no known exponent in Lyapunov
    times: those columns go; in a file where one SSM has them, they stay, "—" where another has not."""
    from experiments.results import render_analysis

    def run(label, free_run, lyap_times=None):
        vt = {
            "threshold": 0.5,
            "truth": "noiseless",
            "n_filter": 50,
            "horizon": 50,
            "mean_steps": 40.0,
            "std_steps": 3.0,
            "median_steps": 41.0,
            "mean_seconds": 4.0,
            "mean_lyapunov_times": lyap_times,
            "censored_share": 0.5,
        }
        dyn = {"lyapunov": {"exponents": [0.1, -0.2], "largest": 0.1}, "free_run": free_run}
        return (label, {"info": {"label": label}, "analysis": {"valid_time": vt, "dynamics": dyn}})

    images = run("SSM-LL", {"runs": 16, "steps": 500})
    lines = render_analysis([images])
    (timed,) = _markdown_table(lines, "method")
    assert "mean (Lyapunov times)" not in timed and timed["mean ± std (steps)"] == "40 ± 3"
    (dyn,) = _markdown_table(lines, "SSM (via)")
    assert (
        list(dyn) == ["SSM (via)", "Lyapunov exponents", "largest (true)", "free runs"]
        and dyn["free runs"] == "16 x 500"
    )

    lorenz = run(
        "SSM-LL + UKF",
        {
            "runs": 64,
            "steps": 10000,
            "model_mean": [0.1],
            "model_std": [7.9],
            "reference_mean": [0.0],
            "reference_std": [7.8],
            "wasserstein": [0.42],
            "both_wings_share": 1.0,
        },
        lyap_times=3.2,
    )
    rows = _markdown_table(render_analysis([images, lorenz]), "SSM (via)")
    assert [r["W1 (x)"] for r in rows] == ["—", "0.42"] and [r["both wings"] for r in rows] == ["—", "1"]
    assert rows[1]["x: data mean ± std"] == "0 ± 7.8"


def test_edited_notes_make_the_md_stale_until_re_rendered(tmp_path, capsys):
    """`python -m experiments.results --check` names an experiment whose notes changed after its .md was
    written (and only it), and exits 1; re-rendering it puts the new note in its .md and the check passes."""
    from experiments.results import main
    from ssm_ms.forecasting.results import write_results

    for name in ("toy_cpu", "other_cpu"):
        info = {"experiment": name, "method": "encoder", "model": "SSM-LL", "inference": "encoder"}
        render_file(write_results(tmp_path, info, {"encoder/noisy/mse": {"mean": 0.5, "std": 0.1, "n": 4}}))
    (tmp_path / "summary_seeds.json").write_text('{"rows": []}')  # not a results file: left alone
    assert main(["--results-dir", str(tmp_path), "--check"]) == 0
    (tmp_path / "toy_cpu.notes.md").write_text("Paused 70 minutes.\n")
    assert main(["--results-dir", str(tmp_path), "--check"]) == 1
    err = capsys.readouterr().err
    assert "toy_cpu" in err and "other_cpu" not in err
    assert "Paused 70 minutes." not in (tmp_path / "toy_cpu.md").read_text()
    assert main(["--results-dir", str(tmp_path)]) == 0
    assert "Paused 70 minutes." in (tmp_path / "toy_cpu.md").read_text()
    assert main(["--results-dir", str(tmp_path), "--check"]) == 0


def test_committed_results_md_match_their_json_and_notes():
    """Every results/<experiment>.md is what its .json and hand-written notes render (a notes edit left
    un-rendered fails here: `python -m experiments.results` re-renders)."""
    from experiments.results import stale

    assert stale(Path(__file__).resolve().parents[1] / "results") == []
