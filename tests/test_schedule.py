"""The alpha / learning-rate schedule, the optimizer reset, and exact resume from checkpoints."""

import pytest
import torch
from lightning.pytorch.callbacks import Callback, ModelCheckpoint

from ssm_ms.schedule import ShootingSchedule
from tests.conftest import RotationDataModule, fast_trainer, rotation_model

LR = 1e-2


class Probe(Callback):
    """Record, at the start of every epoch (after the schedule ran), alpha, lr and Adam's step counts."""

    def __init__(self):
        self.seen = {}

    def on_train_epoch_start(self, trainer, pl_module):
        opt = trainer.optimizers[0]
        steps = [float(s["step"]) for s in opt.state.values()]
        self.seen[trainer.current_epoch] = (pl_module.alpha.item(), opt.param_groups[0]["lr"], max(steps, default=0))


def schedule(**kwargs):
    # the optimizer reset defaults to the epoch alpha is raised
    return ShootingSchedule(alpha=50.0, alpha_epoch=2, lr_milestones=[2, 4], lr_factor=0.1, **kwargs)


def test_schedule_steps_alpha_lr_and_resets_the_optimizer(tmp_path, rotation_dm):
    probe = Probe()
    fast_trainer(tmp_path, max_epochs=5, callbacks=[schedule(), probe]).fit(rotation_model(lr=LR), rotation_dm)
    steps_per_epoch = 2  # 8 trajectories, batch 4
    alpha = [probe.seen[e][0] for e in range(5)]
    lr = [probe.seen[e][1] for e in range(5)]
    adam_steps = [probe.seen[e][2] for e in range(5)]
    assert alpha == [1.0, 1.0, 50.0, 50.0, 50.0]
    assert lr == pytest.approx([LR, LR, LR / 10, LR / 10, LR / 100])
    # Adam counts steps per parameter: cleared at epoch 2 only, then counts again from zero
    assert adam_steps == [0, steps_per_epoch, 0, steps_per_epoch, 2 * steps_per_epoch]


def test_optimizer_resets_where_configured(tmp_path, rotation_dm):
    """The reference code's variant: a fresh Adam at both learning-rate milestones."""
    probe = Probe()
    trainer = fast_trainer(tmp_path, max_epochs=5, callbacks=[schedule(reset_optimizer_at=[2, 4]), probe])
    trainer.fit(rotation_model(lr=LR), rotation_dm)
    assert [probe.seen[e][2] for e in range(5)] == [0, 2, 0, 2, 0]


def _params(model):
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


@pytest.mark.parametrize("stop_after", [2, 3])  # stop just before the milestone epoch, and just after it
def test_resume_continues_exactly_like_an_uninterrupted_run(tmp_path, stop_after):
    def dm():
        return RotationDataModule(data_dir=str(tmp_path / "data"), batch_size=3, val_trajectories=0)

    full_probe = Probe()
    full = rotation_model(lr=LR)
    fast_trainer(tmp_path / "full", max_epochs=5, callbacks=[schedule(), full_probe]).fit(full, dm())

    ckpt = ModelCheckpoint(dirpath=tmp_path / "ckpt", save_last=True)
    first = rotation_model(lr=LR)
    fast_trainer(tmp_path / "a", max_epochs=stop_after, callbacks=[schedule(), ckpt]).fit(first, dm())

    resumed_probe = Probe()
    resumed = rotation_model(lr=LR)  # a fresh process would build the model from the config again
    trainer = fast_trainer(tmp_path / "b", max_epochs=5, callbacks=[schedule(), resumed_probe])
    trainer.fit(resumed, dm(), ckpt_path=str(tmp_path / "ckpt" / "last.ckpt"))

    for epoch in range(stop_after, 5):
        assert resumed_probe.seen[epoch] == full_probe.seen[epoch]
    a, b = _params(full), _params(resumed)
    for key in a:
        torch.testing.assert_close(b[key], a[key], rtol=0, atol=0)
    opt_full = adam_moments(full)
    opt_resumed = adam_moments(resumed)
    for x, y in zip(opt_full, opt_resumed):
        torch.testing.assert_close(y, x, rtol=0, atol=0)


def adam_moments(model):
    """Adam's first and second moments of every parameter, in order."""
    opt = model.trainer.optimizers[0]
    return [t for p in opt.param_groups[0]["params"] for t in (opt.state[p]["exp_avg"], opt.state[p]["exp_avg_sq"])]


def test_bad_schedules_are_refused():
    with pytest.raises(ValueError, match="lr_factor > 0"):
        ShootingSchedule(lr_factor=0.0)
    with pytest.raises(ValueError, match="epochs >= 0"):
        ShootingSchedule(lr_milestones=[-1])


class NodeProbe(Callback):
    """At the start of every epoch: the node group's lr and the largest per-row Adam step count."""

    def __init__(self):
        self.seen = {}

    def on_train_epoch_start(self, trainer, pl_module):
        opt = trainer.optimizers[0]
        state = opt.state.get(pl_module.nodes.weight, {})
        steps = float(state["step"].max()) if "step" in state else 0.0
        self.seen[trainer.current_epoch] = (opt.param_groups[1]["lr"], steps)


def test_sparse_nodes_follow_the_schedule_and_resume_exactly(tmp_path):
    """node_lr is scaled at the lr milestones, the optimizer reset clears the rows' Adam state, and a
    run resumed after the reset continues bit for bit (parameters, row moments and step counts)."""

    def dm():
        return RotationDataModule(data_dir=str(tmp_path / "data"), batch_size=3, val_trajectories=0)

    def model():
        return rotation_model(lr=LR, node_optimizer="sparse", node_lr=0.1)

    full_probe = NodeProbe()
    full = model()
    fast_trainer(tmp_path / "full", max_epochs=5, callbacks=[schedule(), full_probe]).fit(full, dm())
    # each trajectory is in one batch per epoch: its row counts 1 step per epoch, 0 again after the reset
    assert [full_probe.seen[e][0] for e in range(5)] == pytest.approx([0.1, 0.1, 0.01, 0.01, 0.001])
    assert [full_probe.seen[e][1] for e in range(5)] == [0, 1, 0, 1, 2]
    ckpt = ModelCheckpoint(dirpath=tmp_path / "ckpt", save_last=True)
    fast_trainer(tmp_path / "a", max_epochs=3, callbacks=[schedule(), ckpt]).fit(model(), dm())
    resumed = model()
    trainer = fast_trainer(tmp_path / "b", max_epochs=5, callbacks=[schedule()])
    trainer.fit(resumed, dm(), ckpt_path=str(tmp_path / "ckpt" / "last.ckpt"))
    a, b = _params(full), _params(resumed)
    for key in a:
        torch.testing.assert_close(b[key], a[key], rtol=0, atol=0)
    sa = full.trainer.optimizers[0].state[full.nodes.weight]
    sb = resumed.trainer.optimizers[0].state[resumed.nodes.weight]
    for key in ("exp_avg", "exp_avg_sq", "step"):
        torch.testing.assert_close(sb[key], sa[key], rtol=0, atol=0)


def test_a_run_too_short_to_raise_alpha_is_warned_about(tmp_path, rotation_dm):
    """max_epochs <= alpha_epoch: the schedule would never enforce continuity; the user is told before training."""
    probe = Probe()
    with pytest.warns(UserWarning, match=r"raises alpha at epoch 2 but training stops after 2 epochs"):
        fast_trainer(tmp_path, max_epochs=2, callbacks=[schedule(), probe]).fit(rotation_model(lr=LR), rotation_dm)
    assert [probe.seen[e][0] for e in range(2)] == [1.0, 1.0]  # what the warning says happens


def test_a_run_that_reaches_the_raise_is_not_warned_about(tmp_path, rotation_dm):
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        warnings.filterwarnings("ignore", message=r"(?!ShootingSchedule)")  # Lightning's own hints are not ours
        fast_trainer(tmp_path, max_epochs=3, callbacks=[schedule()]).fit(rotation_model(lr=LR), rotation_dm)
