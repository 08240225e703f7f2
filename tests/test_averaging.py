"""Weight averaging (MultipleShootingModule(weight_average=)): the exponential moving average of the parameters, against
a naive loop over the parameters each step left; validation and checkpoints see the average; a resumed fit goes on
exactly as an uninterrupted one."""

import pytest
import torch
from lightning.pytorch.callbacks import Callback, ModelCheckpoint

from ssm_ms.loading import load_ssm
from tests.conftest import RotationDataModule, fast_trainer, rotation_model

DECAY = 0.8
LR = 1e-2


class Steps(Callback):
    """Each training step's parameters (after the optimizer step), the initial ones first, and the parameters the
    validation epochs saw."""

    def __init__(self):
        self.steps, self.validated = [], []

    def on_fit_start(self, trainer, pl_module):
        if not self.steps:
            self.steps.append(_named(pl_module))

    def on_train_batch_end(self, trainer, pl_module, *args):
        self.steps.append(_named(pl_module))

    def on_validation_epoch_end(self, trainer, pl_module):
        if not trainer.sanity_checking:
            self.validated.append((len(self.steps), _named(pl_module)))


def _named(model):
    return {k: p.detach().clone() for k, p in model.named_parameters()}


def naive_average(steps, until=None):
    """The average after the first ``until`` steps: a = p0, then a = decay * a + (1 - decay) * p_k."""
    steps = steps[: (until or len(steps))]
    average = dict(steps[0])
    for params in steps[1:]:
        average = {k: DECAY * average[k] + (1 - DECAY) * params[k] for k in average}
    return average


def _close(a, b):
    assert a.keys() == b.keys()
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=1e-5, atol=1e-6)


def test_validation_checkpoints_and_the_end_of_the_fit_hold_the_average(tmp_path):
    dm = RotationDataModule(data_dir=str(tmp_path / "data"), batch_size=4, val_trajectories=2)
    steps = Steps()
    ckpt = ModelCheckpoint(dirpath=tmp_path / "ckpt", save_last=True)
    model = rotation_model(lr=LR, weight_average=DECAY)
    fast_trainer(tmp_path, max_epochs=4, callbacks=[steps, ckpt]).fit(model, dm)

    assert len(steps.steps) == 1 + 4 * 2  # 8 trajectories in batches of 4
    # the parameters moved, and the average is not the last step's
    last, average = steps.steps[-1], naive_average(steps.steps)
    assert any(not torch.allclose(last[k], average[k]) for k in last)
    for n, seen in steps.validated:  # every validation scored the average of the steps so far
        _close(seen, naive_average(steps.steps, n))
    _close(_named(model), average)  # the fit ends with the average
    _close(_named(load_ssm(tmp_path / "ckpt" / "last.ckpt")[0]), average)  # and its checkpoint holds it


def test_a_resumed_fit_goes_on_as_an_uninterrupted_one(tmp_path):
    def dm():
        return RotationDataModule(data_dir=str(tmp_path / "data"), batch_size=3, val_trajectories=2)

    full = rotation_model(lr=LR, weight_average=DECAY)
    fast_trainer(tmp_path / "full", max_epochs=5).fit(full, dm())

    ckpt = ModelCheckpoint(dirpath=tmp_path / "ckpt", save_last=True)
    fast_trainer(tmp_path / "a", max_epochs=2, callbacks=[ckpt]).fit(rotation_model(lr=LR, weight_average=DECAY), dm())
    resumed = rotation_model(lr=LR, weight_average=DECAY)
    trainer = fast_trainer(tmp_path / "b", max_epochs=5)
    trainer.fit(resumed, dm(), ckpt_path=str(tmp_path / "ckpt" / "last.ckpt"))

    a, b = _named(full), _named(resumed)
    for k in a:
        torch.testing.assert_close(b[k], a[k], rtol=0, atol=0)


@pytest.mark.parametrize("decay", [0.0, 1.0, 1.5, -0.1])
def test_a_decay_outside_zero_one_is_refused(decay):
    with pytest.raises(ValueError, match=r"weight_average is an averaging decay in \(0, 1\)"):
        rotation_model(weight_average=decay)
