"""Lightning DDP on 2 CPU processes (gloo) against one process on the same global batches.

``python -m tests.test_ddp OUT`` is the 2-process run (Lightning's ``ddp`` strategy starts the second
process by running the same command); each rank writes its final f, g, nodes, multipliers and alpha
to ``OUT/<config>-rank<r>.pt``; last, the ranks build different training sets and each writes its
refusal to ``OUT/refused-rank<r>.txt``. One test runs it in a subprocess and the 1-device reference
in its own process, in float64, and compares every tensor of every rank to the reference.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]

# 11 trajectories in global batches of 4: 4, 4, 3 -> shards 2+2, 2+2, 2+1 (an uneven last step)
CONFIGS = {
    "dense-penalty": dict(node_optimizer="dense"),
    "sparse-al": dict(
        node_optimizer="sparse",
        node_lr=0.05,
        constraint="augmented_lagrangian",
        constraint_options={"growth": 2.0, "shrink": 1.01},
    ),
}
EPOCHS = 3


def _fit(name: str, out: Path, devices: int, data_dir: Path, resume: bool = False) -> dict[str, torch.Tensor]:
    """``EPOCHS`` epochs; with ``resume``, ``EPOCHS - 1`` epochs, a checkpoint, and the last epoch resumed from
    it by a new trainer, model and schedule (as after a crash)."""
    from ssm_ms.checkpointing import EpochCheckpoint
    from ssm_ms.schedule import ShootingSchedule
    from tests.conftest import RotationDataModule, fast_trainer, rotation_model

    extra = dict(strategy="ddp", devices=2) if devices == 2 else dict(devices=1)
    ckpt = None
    for epochs in [EPOCHS - 1, EPOCHS] if resume else [EPOCHS]:
        dm = RotationDataModule(data_dir=str(data_dir), n_train=11, batch_size=4, val_trajectories=0)
        # float64 from the start: Lightning restores a checkpoint before it converts the module to 64-true
        model = rotation_model(lr=1e-2, **CONFIGS[name]).double()
        callbacks = [
            ShootingSchedule(alpha=10.0, alpha_epoch=1, lr_milestones=[2], lr_factor=0.1),
            EpochCheckpoint(dirpath=str(out / "checkpoints")),
        ]  # what the configs use
        trainer = fast_trainer(out, max_epochs=epochs, callbacks=callbacks, precision="64-true", **extra)
        trainer.fit(model, dm, ckpt_path=ckpt)
        ckpt = out / "checkpoints" / "last.ckpt"
    result = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
    result["steps"] = torch.tensor(trainer.global_step)
    return result


def main(out: str) -> None:
    from tests.conftest import RotationDataModule, fast_trainer, rotation_model

    torch.set_num_threads(1)
    out_dir = Path(out)
    rank = int(os.environ.get("LOCAL_RANK", 0))
    for name in CONFIGS:
        torch.save(_fit(name, out_dir / name, 2, out_dir / "data"), out_dir / f"{name}-rank{rank}.pt")
        torch.save(
            _fit(name, out_dir / f"{name}-resumed", 2, out_dir / "data", resume=True),
            out_dir / f"{name}-resumed-rank{rank}.pt",
        )
    # last, in the same processes (a start of two ranks is ~20 s of imports on the slowest CPUs): each rank builds
    # another training set, 11 and 12 trajectories, and each rank's refusal is written to OUT/refused-rank<r>.txt
    dm = RotationDataModule(data_dir=str(out_dir / f"data{rank}"), n_train=11 + rank, batch_size=4, val_trajectories=0)
    dm.prepare_data()  # the Trainer prepares data on local rank 0 only
    try:
        fast_trainer(out_dir / "refused", max_epochs=1, strategy="ddp", devices=2).fit(rotation_model(), dm)
    except ValueError as error:
        (out_dir / f"refused-rank{rank}.txt").write_text(str(error))


def _matches_one_process(out: Path, name: str) -> None:
    """f, g, nodes, multipliers and alpha of config ``name`` after 3 epochs (9 steps, schedule milestones inside),
    run through or resumed from a checkpoint after epoch 2, agree with the 1-process run to 1e-9 on both ranks
    (float64: the only difference is the order in which the gradient of f and g is summed), and the ranks hold
    identical tables."""
    reference = _fit(name, out / f"{name}-single", 1, out / "data")
    assert int(reference["steps"]) == 9
    for run in (name, f"{name}-resumed"):  # uninterrupted, and resumed from a checkpoint after epoch 2
        ranks = [torch.load(out / f"{run}-rank{r}.pt") for r in range(2)]
        for result in ranks:
            assert result.keys() == reference.keys()
            for key, value in reference.items():
                torch.testing.assert_close(result[key], value, rtol=1e-9, atol=1e-12, msg=f"{run}: {key}")
        for key in ranks[0]:
            assert torch.equal(ranks[0][key], ranks[1][key]), key
    if name == "sparse-al":
        assert reference["alpha_factor"] > 1 and (reference["multipliers"] != 0).all()


def test_two_processes_match_one_and_ranks_with_different_training_sets_are_refused(tmp_path):
    """One 2-rank run serves every DDP check (a start of two ranks is ~20 s of imports on the slowest CPUs): each of
    :data:`CONFIGS` matches one process (:func:`_matches_one_process`), then ranks that built different training
    sets stop with one message on each rank."""
    # the data set exists before the two ranks start (each would otherwise generate it)
    from tests.conftest import RotationDataModule

    RotationDataModule(data_dir=str(tmp_path / "data"), n_train=11, batch_size=4, val_trajectories=0).prepare_data()
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT))
    proc = subprocess.run(
        [sys.executable, "-m", "tests.test_ddp", str(tmp_path)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    for name in CONFIGS:
        _matches_one_process(tmp_path, name)
    for rank in range(2):
        refused = tmp_path / f"refused-rank{rank}.txt"
        assert refused.is_file(), f"rank {rank} was not refused"
        assert "DDP: the ranks hold different node tables (rows per rank: [11, 12])" in refused.read_text()


def test_global_batches_are_sharded_without_repeats():
    """Each global batch of the one-device order is split over the ranks, contiguously, nothing twice."""
    from datamodules.samplers import EpochSeededSampler, GlobalBatchShardSampler

    n, batch, world = 23, 9, 3  # last global batch: 5 -> shards of 2, 2, 1
    shards = [GlobalBatchShardSampler(n, batch, world, r, seed=5) for r in range(world)]
    one = EpochSeededSampler(n, seed=5)
    for epoch in (0, 4):
        for s in shards:
            s.set_epoch(epoch)
        one.set_epoch(epoch)
        order = list(one)
        streams = [list(s) for s in shards]
        local = batch // world
        for k, start in enumerate(range(0, n, batch)):
            union = [i for stream in streams for i in stream[k * local : (k + 1) * local]]
            assert union == order[start : start + batch]  # rank order = one-device order
        assert sorted(i for s in streams for i in s) == list(range(n))
    with pytest.raises(ValueError, match="batch_size=10 is the global batch, split over 3 devices"):
        GlobalBatchShardSampler(n, 10, 3, 0)
    with pytest.raises(ValueError, match="last global batch of an epoch holds 1 of 9"):
        GlobalBatchShardSampler(9, 4, 2, 0)


if __name__ == "__main__":
    main(sys.argv[1])
