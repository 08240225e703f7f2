"""WeightAverage: an exponential moving average of a model's parameters over its training steps, the model that
validation scores, that the checkpoints hold and that the fit ends with (``MultipleShootingModule(weight_average=)``).

With a constant learning rate the weights after any one step carry the noise of its batch; their average over the
last ~``1 / (1 - decay)`` steps is the usual remedy (Polyak averaging). Only parameters are averaged: buffers (alpha,
the states a node encoder gave, multipliers) stay the current ones.

A checkpoint holds the average as its ``state_dict`` (what every loader reads) and the current parameters in this
callback's state, so that a resumed fit goes on from the optimizer's weights with the average it had.
"""

from __future__ import annotations

from typing import Any

import lightning.pytorch as pl
import torch


class WeightAverage(pl.Callback):
    """After every training step ``average <- decay * average + (1 - decay) * parameters`` (the average starts at the
    initial parameters); during validation the model's parameters are the average, and after the fit they stay so.

    Validation swaps the average in at its start and the current parameters back at its end (``on_validation_end``,
    after every callback's ``on_validation_epoch_end`` and before the checkpoint callbacks, which Lightning runs
    last)."""

    def __init__(self, decay: float):
        if not 0.0 < float(decay) < 1.0:
            raise ValueError(f"weight_average is an averaging decay in (0, 1), e.g. 0.999; got {decay}")
        self.decay = float(decay)
        self.average: list[torch.Tensor] | None = None
        self._current: list[torch.Tensor] | None = None  # restored from a checkpoint, put back when the fit starts
        self._swapped = False

    @property
    def state_key(self) -> str:
        return f"WeightAverage[decay={self.decay}]"

    @staticmethod
    def _parameters(pl_module: pl.LightningModule) -> list[torch.nn.Parameter]:
        return list(pl_module.parameters())

    def on_fit_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        params = self._parameters(pl_module)
        # a resumed fit: the module was loaded with the average (the checkpoint's state_dict)
        self.average = [p.detach().clone() for p in params]
        if self._current is not None:
            with torch.no_grad():
                for p, c in zip(params, self._current, strict=True):
                    p.copy_(c)
            self._current = None

    @torch.no_grad()
    def on_train_batch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule, *args: Any) -> None:
        assert self.average is not None
        for a, p in zip(self.average, self._parameters(pl_module), strict=True):
            a.lerp_(p.detach(), 1.0 - self.decay)

    @torch.no_grad()
    def _swap(self, pl_module: pl.LightningModule) -> None:
        assert self.average is not None
        for a, p in zip(self.average, self._parameters(pl_module), strict=True):
            tmp = p.detach().clone()
            p.copy_(a)
            a.copy_(tmp)
        self._swapped = not self._swapped

    def on_validation_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if self.average is not None and trainer.state.fn == "fit" and not self._swapped:
            self._swap(pl_module)

    def on_validation_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if self._swapped:
            self._swap(pl_module)

    @torch.no_grad()
    def on_train_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if self.average is not None:
            for a, p in zip(self.average, self._parameters(pl_module), strict=True):
                p.copy_(a)

    def on_save_checkpoint(
        self, trainer: pl.Trainer, pl_module: pl.LightningModule, checkpoint: dict[str, Any]
    ) -> None:
        if self.average is None or self._swapped:
            return  # outside a fit, or saved while validating (the module holds the average already)
        by_id = {id(p): a for p, a in zip(self._parameters(pl_module), self.average, strict=True)}
        state = checkpoint["state_dict"]
        for name, p in pl_module.named_parameters(remove_duplicate=False):
            if name in state and id(p) in by_id:
                state[name] = by_id[id(p)].clone()

    def setup(self, trainer: pl.Trainer, pl_module: pl.LightningModule, stage: str) -> None:
        self._module = pl_module

    def state_dict(self) -> dict[str, Any]:
        if self.average is None:
            return {}
        # the current parameters (the checkpoint's state_dict holds the average): while validating, the average's
        # list holds them
        current = self.average if self._swapped else self._parameters(self._module)
        return {"decay": self.decay, "current": [c.detach().clone() for c in current]}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        if state_dict.get("current") is not None:
            self._current = [torch.as_tensor(c).detach().clone() for c in state_dict["current"]]
