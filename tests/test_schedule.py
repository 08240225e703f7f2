"""The alpha / learning-rate schedule, the optimizer reset, and exact resume from checkpoints."""

import csv
import logging
import math
from fractions import Fraction

import lightning.pytorch as pl
import pytest
import torch
from lightning.pytorch.callbacks import Callback, ModelCheckpoint, Timer

from ssm_ms.schedule import ShootingSchedule
from tests.conftest import RotationDataModule, fast_trainer, rotation_model

LR = 1e-2


class Probe(Callback):
    """Record, before the first step of every epoch (after the schedule ran, whichever the order of the callbacks: a
    model's own come after the trainer's), alpha, lr and Adam's step counts."""

    def __init__(self):
        self.seen = {}

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if batch_idx:
            return
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


def _trainer_without_schedule(tmp_path, max_epochs: int, callbacks) -> pl.Trainer:
    """fast_trainer's settings, with no schedule of the trainer's own (fast_trainer adds a constant one)."""
    trainer = fast_trainer(tmp_path, max_epochs, callbacks=callbacks)
    trainer.callbacks[:] = [c for c in trainer.callbacks if not isinstance(c, ShootingSchedule)]
    return trainer


def test_the_models_schedule_runs_in_each_of_its_fits(tmp_path, rotation_dm):
    """model.schedule (how configs state it) steps alpha and lr as the trainer callback does, in a first fit and again
    in a second: each fit runs a fresh copy, the model's own never advances."""
    model = rotation_model(lr=LR, schedule=schedule())
    for run in ("first", "second"):
        probe = Probe()
        _trainer_without_schedule(tmp_path / run, 5, [probe]).fit(model, rotation_dm)
        assert [probe.seen[e][0] for e in range(5)] == [1.0, 1.0, 50.0, 50.0, 50.0]
        assert [probe.seen[e][1] for e in range(5)] == pytest.approx([LR, LR, LR / 10, LR / 10, LR / 100])
        with torch.no_grad():  # the next fit starts where the paper's would: alpha and lr at their initial values
            model.alpha.fill_(1.0)
    assert model.schedule.initial_alpha is None and model.schedule.fired == {}


def test_a_schedule_given_twice_is_refused(tmp_path, rotation_dm):
    trainer = fast_trainer(tmp_path, max_epochs=1, callbacks=[schedule()])
    with pytest.raises(ValueError, match="given twice.*keep one"):
        trainer.fit(rotation_model(lr=LR, schedule=schedule()), rotation_dm)
    with pytest.raises(ValueError, match="must be a ShootingSchedule"):
        rotation_model(schedule={"alpha": 10.0})


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

    assert_resumed_as_uninterrupted(full, full_probe, resumed, resumed_probe, stop_after)


def assert_resumed_as_uninterrupted(full, full_probe, resumed, resumed_probe, stop_after: int) -> None:
    """The resumed run's epochs saw the uninterrupted run's alpha, lr and Adam step counts, and both end with the
    same weights and Adam moments, bit for bit."""
    for epoch in range(stop_after, 5):
        assert resumed_probe.seen[epoch] == full_probe.seen[epoch]
    a, b = _params(full), _params(resumed)
    for key in a:
        torch.testing.assert_close(b[key], a[key], rtol=0, atol=0)
    for x, y in zip(adam_moments(full), adam_moments(resumed)):
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


# ---------------------------------------------------------------- milestones as parts of the run (of_epochs)
def relative(**kwargs):
    """:func:`schedule`'s milestones read as parts of 10: alpha and lr / 10 at 20% of the run, lr / 10 at 40%."""
    return schedule(of_epochs=10, **kwargs)


class Messages(logging.Handler):
    """The lines of the ``ssm_ms`` logger, as a list (the CLI's handler does not propagate them to pytest's)."""

    def __init__(self):
        super().__init__(logging.INFO)
        self.lines = []

    def emit(self, record):
        self.lines.append(record.getMessage())


@pytest.fixture
def package_log():
    log = logging.getLogger("ssm_ms")
    handler, level = Messages(), log.level
    log.addHandler(handler)
    log.setLevel(logging.INFO)
    yield handler.lines
    log.removeHandler(handler)
    log.setLevel(level)


def test_relative_milestones_fire_at_their_part_of_max_epochs(tmp_path, rotation_dm, package_log):
    """of_epochs 10, milestones 2 and 4, max_epochs 5: the first epochs whose e / 5 reaches 2 / 10 and 4 / 10, epochs
    1 and 2 (alpha raised, the optimizer reset and lr / 10 at 1, lr / 10 again at 2). One line says so at each, and
    the loggers get the epoch of each milestone."""
    from lightning.pytorch.loggers import CSVLogger

    probe = Probe()
    logger = CSVLogger(tmp_path / "csv", name="r", version=0)
    trainer = fast_trainer(tmp_path, max_epochs=5, callbacks=[relative(), probe], logger=logger)
    trainer.fit(rotation_model(lr=LR), rotation_dm)
    assert [probe.seen[e][0] for e in range(5)] == [1.0, 50.0, 50.0, 50.0, 50.0]
    assert [probe.seen[e][1] for e in range(5)] == pytest.approx([LR, LR / 10, LR / 100, LR / 100, LR / 100])
    assert [probe.seen[e][2] for e in range(5)] == [0, 0, 2, 4, 6]  # Adam cleared at epoch 1, 2 steps an epoch
    assert package_log == [
        "schedule: alpha 1 -> 50, lr x0.1, optimizer reset at epoch 1 (20% of 5 epochs)",
        "schedule: lr x0.1 at epoch 2 (40% of 5 epochs)",
    ]
    rows = list(csv.DictReader(open(tmp_path / "csv" / "r" / "version_0" / "metrics.csv")))
    logged = {k: float(v) for row in rows for k, v in row.items() if k.startswith("schedule/") and v}
    assert logged == {"schedule/milestone_2": 1.0, "schedule/milestone_4": 2.0}


class FakeTrainer:
    """What :class:`ShootingSchedule` reads of a trainer to fire its milestones, without a time budget."""

    def __init__(self, max_epochs):
        self.max_epochs, self.callbacks, self.loggers, self.is_global_zero, self.global_step = max_epochs, [], [], 1, 0


def fire_in_epochs(sched: ShootingSchedule, max_epochs: int) -> dict[int, int]:
    """The epochs at which ``sched``'s milestones fire over a run of ``max_epochs`` epochs (what it records)."""
    sched.initial_alpha = 1.0  # as on_fit_start sets it
    for epoch in range(max_epochs):
        sched._fire(FakeTrainer(max_epochs), epoch)
    return sched.fired


@pytest.mark.parametrize("of_epochs", [7, 10, 1000])
@pytest.mark.parametrize("max_epochs", [1, 3, 10, 30, 99, 300, 1001])
def test_in_epochs_a_milestone_fires_at_the_ceiling_of_its_part(of_epochs, max_epochs):
    """Milestone m of of_epochs fires at epoch ceil(m * max_epochs / of_epochs), exactly (the product 0.3 * 10 is
    3.0000000000000004 in floats: a float ceiling would say 4); the paper's 200 and 600 of 1000 in 300 epochs: 60, 180."""
    milestones = sorted({0, 1, of_epochs // 3, (3 * of_epochs) // 10, of_epochs // 2, of_epochs - 1, of_epochs})
    sched = ShootingSchedule(alpha_epoch=milestones[0], lr_milestones=milestones, of_epochs=of_epochs)
    expected = {m: math.ceil(Fraction(m * max_epochs, of_epochs)) for m in milestones}
    # 100% of the run is reached after its last epoch: that milestone never fires
    assert fire_in_epochs(sched, max_epochs) == {m: e for m, e in expected.items() if e < max_epochs}
    assert fire_in_epochs(ShootingSchedule.paper(), 300) == {200: 60, 600: 180}


class StopAfter(Callback):
    """Stop the fit after ``epochs`` epochs, as an interrupted run (its max_epochs unchanged)."""

    def __init__(self, epochs):
        self.epochs = epochs

    def on_train_epoch_end(self, trainer, pl_module):
        if trainer.current_epoch + 1 == self.epochs:
            trainer.should_stop = True


@pytest.mark.parametrize("stop_after", [2, 3])  # after the first milestone's epoch, and after both
def test_a_resumed_run_keeps_the_epochs_its_milestones_fired_at(tmp_path, stop_after):
    """Stopped after 2 or 3 of its 5 epochs and resumed, a run continues as an uninterrupted one: its milestones
    fired at epochs 1 and 2 are in the checkpoint (fired again at the resume they would reset Adam a second time)."""

    def dm():
        return RotationDataModule(data_dir=str(tmp_path / "data"), batch_size=3, val_trajectories=0)

    full_probe = Probe()
    full = rotation_model(lr=LR)
    fast_trainer(tmp_path / "full", max_epochs=5, callbacks=[relative(), full_probe]).fit(full, dm())

    ckpt = ModelCheckpoint(dirpath=tmp_path / "ckpt", save_last=True)
    stopped = fast_trainer(tmp_path / "a", max_epochs=5, callbacks=[relative(), StopAfter(stop_after), ckpt])
    stopped.fit(rotation_model(lr=LR), dm())
    saved = torch.load(tmp_path / "ckpt" / "last.ckpt", weights_only=True)
    fired = {m: e for m, e in {2: 1, 4: 2}.items() if e < stop_after}  # those of the epochs run
    assert [s["fired"] for k, s in saved["callbacks"].items() if "ShootingSchedule" in k] == [fired]

    resumed_probe = Probe()
    resumed = rotation_model(lr=LR)
    trainer = fast_trainer(tmp_path / "b", max_epochs=5, callbacks=[relative(), resumed_probe])
    trainer.fit(resumed, dm(), ckpt_path=str(tmp_path / "ckpt" / "last.ckpt"))

    assert sorted(resumed_probe.seen) == list(range(stop_after, 5))
    assert_resumed_as_uninterrupted(full, full_probe, resumed, resumed_probe, stop_after)


class Tick(Callback):
    """The time the Timer reads: 5 s later at the start of every training batch (2 an epoch: 10 s an epoch)."""

    def __init__(self):
        self.now = 0.0

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        self.now += 5.0


def test_under_a_time_budget_milestones_fire_at_their_part_of_it(tmp_path, rotation_dm, monkeypatch, package_log):
    """max_time 50 s at 10 s an epoch (a fake Timer clock), max_epochs 100: the budget is the further along, 20% of
    it at epoch 1 (10 s) and 40% at epoch 2, not the epochs 20 and 40 of max_epochs; the Timer stops the run after
    epoch 4. Replayed in epochs (absolute milestones at the epochs logged), the run has the same alpha and lr."""
    tick = Tick()
    monkeypatch.setattr(Timer, "time_elapsed", lambda self, stage="train": tick.now)
    probe, sched = Probe(), relative()
    trainer = fast_trainer(tmp_path, max_epochs=100, callbacks=[tick, sched, probe], max_time={"seconds": 50})
    trainer.fit(rotation_model(lr=LR), rotation_dm)
    assert sorted(probe.seen) == [0, 1, 2, 3, 4]
    assert [probe.seen[e][0] for e in range(5)] == [1.0, 50.0, 50.0, 50.0, 50.0]
    assert [probe.seen[e][1] for e in range(5)] == pytest.approx([LR, LR / 10, LR / 100, LR / 100, LR / 100])
    assert sched.fired == {2: 1, 4: 2}
    assert package_log == [
        "schedule: alpha 1 -> 50, lr x0.1, optimizer reset at epoch 1 (20% of the 50 s budget)",
        "schedule: lr x0.1 at epoch 2 (40% of the 50 s budget)",
    ]
    replay_probe = Probe()
    replay = ShootingSchedule(alpha=50.0, alpha_epoch=1, lr_milestones=[1, 2], lr_factor=0.1)
    fast_trainer(tmp_path / "replay", max_epochs=5, callbacks=[replay, replay_probe]).fit(
        rotation_model(lr=LR), rotation_dm
    )
    assert replay_probe.seen == probe.seen


def test_relative_milestones_need_an_end_of_the_run(tmp_path, rotation_dm):
    with pytest.raises(ValueError, match="of_epochs=10"):
        ShootingSchedule(alpha_epoch=2, lr_milestones=[12], of_epochs=10)
    with pytest.raises(ValueError, match="of_epochs >= 1"):
        ShootingSchedule(alpha_epoch=0, lr_milestones=[0], of_epochs=0)
    with pytest.raises(ValueError, match="give trainer.max_epochs or trainer.max_time"):
        fast_trainer(tmp_path, max_epochs=-1, callbacks=[relative()]).fit(rotation_model(lr=LR), rotation_dm)


def test_a_time_budgeted_fit_beside_a_busy_process_is_warned_about_once(tmp_path, rotation_dm):
    """A process spinning a core beside a fit under ``trainer.max_time``: other processes kept more than
    SHARED_CORES cores busy (one here, more where `make test`'s other worker runs), so the schedule warns once and
    its checkpointed state says how many. Without a time budget nothing is measured."""
    import subprocess
    import sys
    import time
    import warnings

    from ssm_ms.runtime.machine import SHARED_CORES

    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        time.sleep(0.5)  # its interpreter has started
        sched = relative()
        with warnings.catch_warnings(record=True) as record:
            warnings.simplefilter("always")
            trainer = fast_trainer(tmp_path, max_epochs=6, callbacks=[sched], max_time={"seconds": 600})
            trainer.fit(rotation_model(lr=LR), rotation_dm)
        others = sched.state_dict()["cpu_others"]
    finally:
        busy.kill()
        busy.wait()
    if others is None:
        pytest.skip("no /proc/stat here")
    assert others > SHARED_CORES
    shared = [w for w in record if "cores busy on average since this fit started" in str(w.message)]
    assert len(shared) == 1 and "Run one training job at a time" in str(shared[0].message)
    untimed = relative()
    fast_trainer(tmp_path / "untimed", max_epochs=2, callbacks=[untimed]).fit(rotation_model(lr=LR), rotation_dm)
    assert untimed.state_dict()["cpu_others"] is None
