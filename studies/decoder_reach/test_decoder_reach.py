"""Tests of decoder_reach.py, frozen with the study: `make test` does not collect studies/ (testpaths: tests/).
Run: `.venv/bin/python -m pytest studies/decoder_reach`."""

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))  # the repository's packages and studies/, from wherever pytest runs


def test_decoder_reach_writes_its_table_and_figure(tmp_path, monkeypatch):
    """decoder_reach.py on the pretrained simple pendulum, 2 sequences: three rows, each with the model's,
    the free codes' and the mean frame's error; codes fitted to each clean frame from the pipeline's own states draw
    it at least as close as those states do, and closer than the mean frame; with --rollout, one state per sequence
    fitted through f and g to all frames draws them closer than the mean frame, and the predicted ones at least as
    close as one fitted to the given frames alone; the figure holds three strips of frames."""
    from PIL import Image

    from studies.decoder_reach import decoder_reach

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
