"""Score SSM checkpoints of Cascaded Tanks by two validation judges: the held-out end alone (val_run_in 0, the state
from its first 50 samples, 155 simulated samples scored) and the free run of the whole training recording from its
first 50 samples, scored on the same held-out end (val_run_in "all": 969 steps, as long as a test run).

    .venv/bin/python studies/tanks_validation_judge/rejudge.py runs/cascaded_tanks_amortised/*/checkpoints/*.ckpt
"""

from __future__ import annotations

import sys

import torch

from datamodules.benchmarks import BenchmarkDataModule
from ssm_ms.inference.simulation import held_out_score
from ssm_ms.loading import load_ssm


def main(paths: list[str]) -> None:
    torch.set_num_threads(2)
    judges = {}
    for run_in in (0, "all"):
        dm = BenchmarkDataModule(
            "Cascaded_Tanks", dir_placement="../shared/data/nonlinear_benchmarks", val_run_in=run_in
        )
        dm.setup("fit")
        judges[run_in] = dm
    print("| checkpoint | held-out end alone (V) | whole recording, held-out end scored (V) |")
    print("|---|---|---|")
    for path in paths:
        ssm = load_ssm(path)[0].eval()
        for dm in judges.values():
            dm.load_state_dict(ssm.data_state)  # the checkpoint's normalisation, not this data module's windows'
        scores = [held_out_score(ssm, dm)[0] for dm in judges.values()]
        print(f"| `{path}` | {scores[0]:.3f} | {scores[1]:.3f} |", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
