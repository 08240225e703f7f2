"""node_optimizer: sparse -- only the batch's nodes change, each row following its own Adam."""

import pytest
import torch
from lightning.pytorch.callbacks import Callback

from ssm_ms.training.nodes import row_adam_
from tests.conftest import fast_trainer, rotation_model


def test_row_adam_is_adam_on_each_rows_own_gradient_sequence():
    """Row 0 is in every step, row 1 in steps 0 and 2 only, row 2 never: compare with torch's Adam run
    on each row alone, over the steps in which that row is present."""
    torch.manual_seed(0)
    table = torch.randn(3, 4, dtype=torch.float64)
    grads = [torch.randn(3, 4, dtype=torch.float64) for _ in range(3)]
    present = [[0, 1], [0], [0, 1]]
    weight, state = table.clone(), {}
    for g, rows in zip(grads, present):
        idx = torch.tensor(rows)
        row_adam_(weight, state, idx, g[idx], lr=0.1)
    for row in range(3):
        p = table[row].clone().requires_grad_()
        adam = torch.optim.Adam([p], lr=0.1)
        for g, rows in zip(grads, present):
            if row in rows:
                p.grad = g[row].clone()
                adam.step()
        torch.testing.assert_close(weight[row], p.detach(), rtol=1e-12, atol=1e-14)
    assert torch.equal(weight[2], table[2])  # never present: bit for bit


def test_repeated_indices_add_their_gradients():
    weight, state = torch.zeros(2, 3), {}
    g = torch.tensor([[1.0, 2.0, 3.0], [0.5, -4.0, 1.0]])
    row_adam_(weight, state, torch.tensor([1, 1]), g, lr=0.1)
    reference, ref_state = torch.zeros(2, 3), {}
    row_adam_(reference, ref_state, torch.tensor([1]), g.sum(0, keepdim=True), lr=0.1)
    assert torch.equal(weight, reference)


class NodeWatcher(Callback):
    """For every training batch: the node table before and after the step, and the batch's indices."""

    def __init__(self):
        self.steps = []

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        self._before = pl_module.nodes.weight.detach().clone()

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        self.steps.append((batch["index"].tolist(), self._before, pl_module.nodes.weight.detach().clone()))


def _outside_changes(watcher):
    """Per step: how many node rows outside the batch changed."""
    out = []
    for index, before, after in watcher.steps:
        outside = [j for j in range(len(before)) if j not in index]
        out.append(sum(not torch.equal(before[j], after[j]) for j in outside))
    return out


def test_sparse_mode_leaves_every_node_outside_the_batch_unchanged(tmp_path, rotation_dm):
    """8 trajectories, batch 4, 3 epochs: 6 steps. Dense Adam's momentum moves the nodes of the
    trajectories not in the batch from the second step on; sparse mode never does, and moves every
    node of the batch."""
    dense, sparse = NodeWatcher(), NodeWatcher()
    fast_trainer(tmp_path / "d", max_epochs=3, callbacks=[dense]).fit(rotation_model(), rotation_dm)
    fast_trainer(tmp_path / "s", max_epochs=3, callbacks=[sparse]).fit(
        rotation_model(node_optimizer="sparse"), rotation_dm
    )
    assert len(sparse.steps) == len(dense.steps) == 6
    assert _outside_changes(sparse) == [0] * 6
    dense_changes = _outside_changes(dense)
    assert dense_changes[0] == 0 and all(c == 4 for c in dense_changes[1:])
    for index, before, after in sparse.steps:
        assert all(not torch.equal(before[j], after[j]) for j in index)


def test_node_lr_is_the_node_groups_learning_rate(tmp_path, rotation_dm):
    model = rotation_model(node_optimizer="sparse", lr=1e-2, node_lr=0.5)
    fast_trainer(tmp_path, max_epochs=1).fit(model, rotation_dm)
    groups = model.trainer.optimizers[0].param_groups
    assert [g["lr"] for g in groups] == [1e-2, 0.5]
    assert groups[1]["params"][0] is model.nodes.weight
    # Adam's first step moves every coordinate with a nonzero gradient by lr: nodes of the first
    # batch moved by 0.5 (or by ~0.5 twice less, ... ) -- at least one coordinate moved by exactly ~0.5
    moved = model.nodes.weight.detach().abs().max()
    assert 0.4 < moved < 1.01


def test_an_optimizer_that_replaces_the_models_own_is_refused(tmp_path, rotation_dm):
    """What LightningCLI does with an `optimizer:` section: one optimizer over all parameters."""
    model = rotation_model(node_optimizer="sparse")
    model.configure_optimizers = lambda: torch.optim.SGD(model.parameters(), lr=0.1)
    trainer = fast_trainer(tmp_path, max_epochs=1)
    with pytest.raises(ValueError, match=r"node_optimizer='sparse' .* SGD .* remove that section"):
        trainer.fit(model, rotation_dm)
    assert trainer.global_step == 0


def test_unknown_node_optimizer_and_bad_node_lr_are_refused():
    with pytest.raises(ValueError, match="unknown node_optimizer 'lazy'"):
        rotation_model(node_optimizer="lazy")
    with pytest.raises(ValueError, match="node_lr must be > 0"):
        rotation_model(node_lr=0.0)
