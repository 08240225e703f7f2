"""The numerics of training by multiple shooting, as plain functions on tensors (no Lightning):

- :mod:`~ssm_ms.training.shooting`: rollouts, the multiple-shooting loss and the gaps between pieces;
- :mod:`~ssm_ms.training.nodes`: sparse per-row updates of the shooting nodes;
- :mod:`~ssm_ms.training.constraints`: the augmented Lagrangian (multipliers and their updates);
- :mod:`~ssm_ms.training.distributed`: what several devices share (weights of shards, gathered node rows);
- :mod:`~ssm_ms.training.checks`: the model's checks of its settings, networks and data, one message each.

:class:`ssm_ms.module.MultipleShootingModule` is the thin LightningModule around them.
"""
