"""MultipleShootingModule: node lookup, node initialisation, checks before training, NaN handling."""

import math

import pytest
import torch
from lightning.pytorch.callbacks import Callback, ModelCheckpoint

from ssm_ms.module import MultipleShootingModule, NonFiniteLossError
from ssm_ms.nets import ConvDecoder, LocallyLinearTransition, Projection
from tests.conftest import ExactRotation, RotationDataModule, fast_trainer, rotation_model


def test_nodes_are_looked_up_by_trajectory_index():
    model = rotation_model(num_trajectories=5, n_nodes=3, state_dim=2)
    with torch.no_grad():
        model.nodes.weight.copy_(torch.arange(30.0).view(5, 6))
    got = model.node_states(torch.tensor([3, 0, 3]))
    assert got.shape == (3, 3, 2)
    # row j holds trajectory j's nodes in order: node i of trajectory j = weight[j, 2i:2i+2]
    for b, j in enumerate([3, 0, 3]):
        for i in range(3):
            assert got[b, i].tolist() == [6.0 * j + 2 * i, 6.0 * j + 2 * i + 1]


def test_training_step_uses_the_batch_trajectories_nodes(rotation_dm):
    """The loss of a batch depends on the nodes of its trajectories only."""
    model = rotation_model(num_trajectories=8)
    rotation_dm.prepare_data()
    rotation_dm.setup("fit")
    batch = next(iter(rotation_dm.train_dataloader()))
    fit, gap = model.shooting_loss(batch)
    (fit + gap).backward()
    touched = model.nodes.weight.grad.abs().sum(1) > 0
    assert set(torch.nonzero(touched).flatten().tolist()) <= set(batch["index"].tolist())


def test_nodes_start_at_measurements(rotation_dm):
    model = rotation_model(n_nodes=3, node_init_map={1: 0})
    trainer = fast_trainer(rotation_dm.data_dir, max_epochs=0)
    trainer.fit(model, rotation_dm)
    y = torch.from_numpy(rotation_dm.load_arrays("train")["y"].copy())  # [8, 12, 1]
    nodes = model.node_states(torch.arange(8))
    torch.testing.assert_close(nodes[:, :, 1], y[:, ::4, 0])  # n = 12 / 3 = 4
    assert (nodes[:, :, 0] == 0).all()


def test_num_trajectories_comes_from_the_data(rotation_dm):
    model = rotation_model()
    assert model.nodes is None
    fast_trainer(rotation_dm.data_dir, max_epochs=1).fit(model, rotation_dm)
    assert model.nodes.num_embeddings == 8 and model.hparams.num_trajectories == 8


def test_training_reduces_the_loss(tmp_path):
    dm = RotationDataModule(data_dir=str(tmp_path), batch_size=8, val_trajectories=0, noise_std=0.0)
    model = rotation_model(lr=3e-2)
    dm.prepare_data()
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    model._make_nodes(8)
    before = sum(model.shooting_loss(batch)).item()
    fast_trainer(tmp_path, max_epochs=60).fit(model, dm)
    after = sum(model.shooting_loss(batch)).item()
    assert after < 0.2 * before


@pytest.mark.parametrize(
    "model_kwargs, dm_kwargs, match",
    [
        ({"n_nodes": 5}, {}, r"T=12 is not divisible by model.n_nodes=5"),
        ({"num_trajectories": 6}, {}, r"nodes for 6 trajectories but the training set has 8"),
        ({}, {"nan_at": (3, 7)}, r"non-finite value .* index \(3, 7, 0\)"),
    ],
)
def test_bad_configurations_stop_before_training(tmp_path, model_kwargs, dm_kwargs, match):
    dm = RotationDataModule(data_dir=str(tmp_path), **dm_kwargs)
    model = rotation_model(**model_kwargs)
    trainer = fast_trainer(tmp_path, max_epochs=1)
    with pytest.raises(ValueError, match=match):
        trainer.fit(model, dm)
    assert trainer.global_step == 0


def test_observation_shape_mismatch_stops_before_training(tmp_path):
    dm = RotationDataModule(data_dir=str(tmp_path))
    model = MultipleShootingModule(LocallyLinearTransition(2, 4, 8), ConvDecoder(2, "pendulum"), state_dim=2, n_nodes=3)
    trainer = fast_trainer(tmp_path, max_epochs=1)
    with pytest.raises(ValueError, match=r"outputs measurements of shape \(1, 24, 24\) but the data have shape \(1,\)"):
        trainer.fit(model, dm)
    assert trainer.global_step == 0


def test_constructor_rejects_impossible_settings():
    with pytest.raises(ValueError, match="unknown loss 'mae'"):
        rotation_model(loss="mae")
    with pytest.raises(ValueError, match=r"f has state_dim 3 but the model was given state_dim 2: give it once"):
        MultipleShootingModule(LocallyLinearTransition(3), Projection([0]), state_dim=2)
    # said once: f's own
    assert MultipleShootingModule(LocallyLinearTransition(3), Projection([0])).state_dim == 3
    with pytest.raises(ValueError, match="has no state_dim attribute: give state_dim"):
        MultipleShootingModule(torch.nn.Linear(2, 2), Projection([0]))
    with pytest.raises(ValueError, match=r"f maps states \[2, 2\] to shape \(2, 3\)"):
        MultipleShootingModule(torch.nn.Linear(2, 3), Projection([0]), state_dim=2)
    with pytest.raises(ValueError, match="node_init_map names state components"):
        rotation_model(node_init_map={5: 0})


@pytest.mark.parametrize("val_horizon", [None, 5])
def test_validation_rolls_out_the_first_node_over_val_horizon_steps(tmp_path, val_horizon):
    """val/rollout_mse against a plain loop: the true rotation from each validation trajectory's first node,
    over its whole length (12 steps) or over the first val_horizon steps only."""
    dm = RotationDataModule(data_dir=str(tmp_path), val_trajectories=4)
    model = MultipleShootingModule(
        ExactRotation(learnable=False),
        Projection([0]),
        state_dim=2,
        n_nodes=3,
        num_trajectories=8,
        val_horizon=val_horizon,
    )
    with torch.no_grad():
        model.nodes.weight.copy_(torch.randn(8, 6, generator=torch.Generator().manual_seed(1)))
    logged = fast_trainer(tmp_path, max_epochs=1).validate(model, dm, verbose=False)[0]
    dm.setup("validate")
    errors = []
    c, s = math.cos(0.3), math.sin(0.3)
    for batch in dm.val_dataloader():
        for j, y in zip(batch["index"].tolist(), batch["y"]):
            a, b = model.nodes.weight[j, :2].tolist()
            for t in range(val_horizon or 12):
                errors.append((a - float(y[t, 0])) ** 2)
                a, b = c * a - s * b, s * a + c * b
    assert len(errors) == 4 * (val_horizon or 12)
    assert logged["val/rollout_mse"] == pytest.approx(sum(errors) / len(errors), rel=1e-5)


def test_val_horizon_must_be_a_positive_number_of_steps():
    for bad in (0, -3, 2.5):
        with pytest.raises(ValueError, match="val_horizon must be a number of steps >= 1"):
            rotation_model(val_horizon=bad)


def test_any_module_works_as_f_and_g(tmp_path):
    dm = RotationDataModule(data_dir=str(tmp_path), noise_std=0.0, batch_size=8, val_trajectories=0)
    model = MultipleShootingModule(ExactRotation(0.1), Projection([0]), state_dim=2, n_nodes=2, lr=0.05)
    fast_trainer(tmp_path, max_epochs=150).fit(model, dm)
    assert abs(model.f.omega.item()) == pytest.approx(0.3, abs=0.02)  # the data's rotation per step


class PoisonAt(Callback):
    """Make f's parameters NaN at the start of an epoch (a diverging run)."""

    def __init__(self, epoch):
        self.epoch = epoch

    def on_train_epoch_start(self, trainer, pl_module):
        if trainer.current_epoch == self.epoch:
            with torch.no_grad():
                for p in pl_module.f.parameters():
                    p.fill_(float("nan"))


def test_nan_loss_stops_training_and_keeps_the_last_good_checkpoint(tmp_path, rotation_dm):
    ckpt = ModelCheckpoint(dirpath=tmp_path / "ckpt", save_last=True)
    trainer = fast_trainer(tmp_path, max_epochs=5, callbacks=[ckpt, PoisonAt(2)])
    with pytest.raises(NonFiniteLossError, match=r"not finite at epoch 2, .* last good checkpoint is .*last.ckpt"):
        trainer.fit(rotation_model(), rotation_dm)
    saved = torch.load(tmp_path / "ckpt" / "last.ckpt", weights_only=False)
    assert saved["epoch"] == 1
    assert all(torch.isfinite(v).all() for v in saved["state_dict"].values())


def test_checkpoint_of_another_configuration_is_refused(tmp_path, rotation_dm):
    ckpt = ModelCheckpoint(dirpath=tmp_path / "ckpt", save_last=True)
    fast_trainer(tmp_path, max_epochs=1, callbacks=[ckpt]).fit(rotation_model(), rotation_dm)
    other = rotation_model(state_dim=3, node_init_map=None)
    trainer = fast_trainer(tmp_path, max_epochs=3)
    with pytest.raises(ValueError, match=r"another configuration[\s\S]*state_dim: checkpoint 2, this run 3"):
        trainer.fit(other, rotation_dm, ckpt_path=str(tmp_path / "ckpt" / "last.ckpt"))
    assert trainer.global_step == 0


def test_load_from_checkpoint_round_trip(tmp_path, rotation_dm):
    ckpt = ModelCheckpoint(dirpath=tmp_path / "ckpt", save_last=True)
    model = rotation_model()
    fast_trainer(tmp_path, max_epochs=2, callbacks=[ckpt]).fit(model, rotation_dm)
    # built in Python: f and g are not in the hyperparameters; the checkpoint carries the networks
    for loaded in (
        MultipleShootingModule.load_from_checkpoint(tmp_path / "ckpt" / "last.ckpt"),
        MultipleShootingModule.load_from_checkpoint(
            tmp_path / "ckpt" / "last.ckpt", f=LocallyLinearTransition(2, 4, 16), g=Projection([0])
        ),
    ):
        assert loaded.state_dict().keys() == model.state_dict().keys()
        for key, value in model.state_dict().items():
            torch.testing.assert_close(loaded.state_dict()[key], value)


@pytest.mark.parametrize("node_optimizer", ["dense", "sparse"])
def test_a_float64_run_resumes_bit_for_bit_though_f_and_g_are_built_in_float32(tmp_path, node_optimizer):
    """``precision: 64-true`` as the CLI runs it: f, g and the module built in float32, Lightning converting them.
    Lightning restores a checkpoint before it converts the module, so a module still in float32 at that moment
    rounds the checkpoint's float64 weights to float32: the resumed run must equal the uninterrupted one exactly."""
    from ssm_ms.checkpointing import EpochCheckpoint

    def dm():
        return RotationDataModule(data_dir=str(tmp_path / "data"), batch_size=3, val_trajectories=0)

    args = dict(lr=3e-2, node_optimizer=node_optimizer, constraint="augmented_lagrangian")
    full = rotation_model(**args)
    assert full.f.matrices.dtype == torch.float32  # built as the CLI builds it
    fast_trainer(tmp_path / "full", max_epochs=3, precision="64-true").fit(full, dm())
    first = rotation_model(**args)
    fast_trainer(
        tmp_path / "a", max_epochs=2, precision="64-true", callbacks=[EpochCheckpoint(dirpath=str(tmp_path / "ckpt"))]
    ).fit(first, dm())
    saved = torch.load(tmp_path / "ckpt" / "last.ckpt", weights_only=True)["state_dict"]
    rounded = [k for k, v in saved.items() if v.dtype == torch.float64 and not torch.equal(v, v.float().double())]
    assert {"f.matrices", "nodes.weight"} <= set(rounded)  # float32 would change them: the test can see rounding
    resumed = rotation_model(**args)
    fast_trainer(tmp_path / "b", max_epochs=3, precision="64-true").fit(
        resumed, dm(), ckpt_path=str(tmp_path / "ckpt" / "last.ckpt")
    )
    a, b = full.state_dict(), resumed.state_dict()
    assert a.keys() == b.keys()
    for key in a:
        assert b[key].dtype == a[key].dtype and torch.equal(b[key], a[key]), key
    assert a["f.matrices"].dtype == torch.float64


def test_reconstructions_are_drawn_at_validations_every_n_epochs_apart(tmp_path, rotation_dm, monkeypatch):
    """ReconstructionLogger(every_n_epochs=6) with validation every 3 epochs of 12 (after epochs 2, 5, 8, 11):
    drawn at the first validation (2), after the first 6 epochs (5) and after 12 (11, also the last), not after 9
    (8): a picture follows the validations even though none falls on an epoch divisible by 6."""
    from ssm_ms import viz

    drawn = []

    class Recorder:
        def __init__(self, trainer):
            self.trainer = trainer

        def add_figure(self, tag, figure, step):
            drawn.append(self.trainer.current_epoch)

    monkeypatch.setattr(viz, "tensorboard_writer", Recorder)
    trainer = fast_trainer(
        tmp_path, max_epochs=12, callbacks=[viz.ReconstructionLogger(every_n_epochs=6)], check_val_every_n_epoch=3
    )
    trainer.fit(rotation_model(), rotation_dm)
    assert drawn == [2, 5, 11]


def test_reconstructions_by_default_are_twenty_over_the_run_whatever_its_length():
    """No every_n_epochs: the first validation's picture, then one each max_epochs // 20 epochs (validating every
    epoch), so a 1000-epoch config and its 180-epoch twin share one callbacks list; every 10 without an epoch count."""
    from types import SimpleNamespace

    from ssm_ms import viz

    def drawn(max_epochs, epochs):
        logger = viz.ReconstructionLogger()
        return [e for e in range(epochs) if logger._due(SimpleNamespace(current_epoch=e, max_epochs=max_epochs))]

    assert drawn(1000, 1000) == [0] + [e for e in range(1000) if (e + 1) % 50 == 0]
    assert drawn(180, 180) == [0] + [e for e in range(180) if (e + 1) % 9 == 0]
    assert drawn(10, 10) == list(range(10))  # shorter than 20 epochs: every epoch
    assert drawn(-1, 35) == [0, 9, 19, 29]  # a time budget: every 10
    assert drawn(1000, 100)[:3] == [0, 49, 99] and viz.ReconstructionLogger(every_n_epochs=7).every_n_epochs == 7


def test_weight_decay_shrinks_the_networks_and_never_the_nodes():
    """With zero gradients an AdamW step is the decay alone: every weight of f and g times (1 - lr * wd),
    the node table unchanged; without weight_decay the optimizer is the paper's plain Adam."""
    assert type(rotation_model().configure_optimizers()) is torch.optim.Adam
    model = rotation_model(lr=0.1, weight_decay=0.5)
    model._make_nodes(3)
    with torch.no_grad():
        model.nodes.weight.normal_()
    before = {n: p.detach().clone() for n, p in model.named_parameters()}
    optimizer = model.configure_optimizers()
    for p in model.parameters():
        p.grad = torch.zeros_like(p)
    optimizer.step()
    for name, p in model.named_parameters():
        expected = before[name] if name == "nodes.weight" else before[name] * (1 - 0.1 * 0.5)
        torch.testing.assert_close(p.detach(), expected, rtol=0, atol=1e-7)
    with pytest.raises(ValueError, match="weight_decay must be >= 0"):
        rotation_model(weight_decay=-1e-3)
