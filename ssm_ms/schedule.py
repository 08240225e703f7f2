"""The paper's training schedule as a callback: alpha and learning rate stepped at epoch milestones.

Paper defaults: alpha starts at the model's value (1) and is raised once, at epoch 200 of 1000, to the
configured value (1e3 simple pendulum, 1e4 quadruple pendulum) together with an optimizer reset
(fresh Adam moments) and lr / 10; the learning rate is divided by 10 again at epoch 600.
(The paper's reference code also recreates Adam at epoch 600: set ``reset_optimizer_at: [200, 600]``
to do the same.)

The milestones are epochs, or with ``of_epochs`` fractions of the run (:meth:`ShootingSchedule.paper`:
200 and 600 of 1000 epochs, 20% and 60% of any run): of its ``max_epochs``, or of its time budget
(``trainer.max_time``), whichever is the further along. Alpha and the learning rate are pure functions of the
epoch and of the epochs at which the milestones fired, recomputed at the start of every epoch; the callback's state
(initial alpha and learning rates, resets already applied, the epochs the milestones fired at) is saved in
checkpoints. A run stopped at any epoch and resumed with ``--ckpt_path`` therefore continues with the
same alpha, learning rate and optimizer state as an uninterrupted one.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import Any

import lightning.pytorch as pl
from lightning.pytorch.callbacks import Callback
from lightning.pytorch.utilities import rank_zero_warn

from ssm_ms.progress import duration, time_budget
from ssm_ms.runtime.machine import SHARED_CORES, CpuWatch

_log = logging.getLogger("ssm_ms")


class ShootingSchedule(Callback):
    """Raise alpha and lower the learning rate at epoch milestones, resetting the optimizer.

    With ``of_epochs`` the milestones are read as fractions ``milestone / of_epochs`` of the run's budget. The run's
    progress at the start of an epoch is the larger of ``epoch / trainer.max_epochs`` (where ``max_epochs`` > 0) and
    the training time elapsed over ``trainer.max_time`` (where the trainer has a time budget: Lightning's ``Timer``);
    a milestone fires at the first epoch whose progress reaches its fraction. In epochs that is epoch
    ``ceil(milestone * max_epochs / of_epochs)``: ``of_epochs=1000, alpha_epoch=200`` raises alpha at epoch 60 of a
    300-epoch run. Under a time budget the epoch depends on the machine's speed; the epochs the milestones fired at
    are logged (one INFO line of the ``ssm_ms`` logger, and ``schedule/milestone_<m>`` to the trainer's loggers) and
    kept in the checkpoint, so that a resumed run keeps them and the run can be replayed in epochs (the absolute
    milestones those epochs are, without ``of_epochs``).

    Under a time budget the schedule also watches the CPU (:class:`~ssm_ms.runtime.machine.CpuWatch`): where other
    processes kept more than ``SHARED_CORES`` cores busy on average since the fit started, it warns once (at the first
    milestone or at the end of training), since such a fit trains fewer epochs in its budget and fires its milestones
    at earlier epochs than it would alone. The average, as measured at each checkpoint, is kept in the checkpoint
    (``cpu_others``; a resumed run measures from its own start), and the benchmarks' results files report it.

    Args:
        alpha: value alpha is raised to at ``alpha_epoch`` (before it, the model's initial alpha).
        alpha_epoch: the epoch at which alpha is raised (``None``: never; :meth:`constant`).
        lr_milestones: epochs at which the learning rate is multiplied by ``lr_factor``.
        lr_factor: the factor applied at each learning-rate milestone.
        reset_optimizer_at: epochs at which the optimizer state (Adam's moments) is cleared
            (default: ``[alpha_epoch]``, the paper's reset when alpha is raised).
        of_epochs: None: the milestones are epochs. An int: the milestones (0 to ``of_epochs``) are that many parts
            of ``of_epochs`` of the run's budget, as above.
    """

    def __init__(
        self,
        alpha: float = 1e3,
        alpha_epoch: int | None = 200,
        lr_milestones: Sequence[int] = (200, 600),
        lr_factor: float = 0.1,
        reset_optimizer_at: Sequence[int] | None = None,
        of_epochs: int | None = None,
    ):
        if reset_optimizer_at is None:
            reset_optimizer_at = () if alpha_epoch is None else (alpha_epoch,)
        if alpha < 0 or lr_factor <= 0:
            raise ValueError(f"alpha must be >= 0 and lr_factor > 0, got {alpha} and {lr_factor}")
        if (
            (alpha_epoch is not None and alpha_epoch < 0)
            or any(e < 0 for e in lr_milestones)
            or any(e < 0 for e in reset_optimizer_at)
        ):
            raise ValueError("schedule milestones must be epochs >= 0")
        self.alpha = float(alpha)
        self.alpha_epoch = None if alpha_epoch is None else int(alpha_epoch)
        self.lr_milestones = sorted(int(e) for e in lr_milestones)
        self.lr_factor = float(lr_factor)
        self.reset_optimizer_at = sorted(int(e) for e in reset_optimizer_at)
        self.of_epochs = None if of_epochs is None else int(of_epochs)
        if self.of_epochs is not None:
            beyond = sorted(m for m in self.milestones() if m > self.of_epochs)
            if self.of_epochs < 1 or beyond:
                raise ValueError(
                    f"with of_epochs={of_epochs} the milestones are parts of of_epochs of the run: give of_epochs >= 1 "
                    f"and milestones from 0 to of_epochs, got {beyond or of_epochs}"
                )
        self.initial_alpha: float | None = None
        self.initial_lrs: list[float] | None = None
        self.resets_done: list[int] = []
        self.fired: dict[int, int] = {}  # with of_epochs: milestone -> the epoch it fired at
        self._watch: CpuWatch | None = None  # under a time budget: other processes' CPU use since the fit started
        self._warned = False

    @classmethod
    def paper(cls, alpha: float = 1e3) -> ShootingSchedule:
        """The paper's schedule scaled to the run: alpha raised to ``alpha`` with an optimizer reset and lr / 10 at
        20% of it, lr / 10 again at 60% (epochs 200 and 600 of its 1000)."""
        return cls(alpha=alpha, alpha_epoch=200, lr_milestones=(200, 600), lr_factor=0.1, of_epochs=1000)

    @classmethod
    def constant(cls) -> ShootingSchedule:
        """No milestones: alpha and the learning rate stay the model's own (what a fit runs when it should not get
        the paper's schedule, e.g. a test of the optimisation alone)."""
        return cls(alpha_epoch=None, lr_milestones=())

    # ---------------------------------------------------------------- the schedule
    def milestones(self) -> list[int]:
        """Every milestone, once each, in order."""
        alpha = () if self.alpha_epoch is None else (self.alpha_epoch,)
        return sorted({*alpha, *self.lr_milestones, *self.reset_optimizer_at})

    def epoch_of(self, milestone: int) -> float:
        """The epoch from which ``milestone`` holds: itself; with ``of_epochs`` the epoch it fired at (inf before)."""
        return milestone if self.of_epochs is None else self.fired.get(milestone, math.inf)

    def alpha_at(self, epoch: int) -> float:
        assert self.initial_alpha is not None
        if self.alpha_epoch is None:
            return self.initial_alpha
        return self.alpha if epoch >= self.epoch_of(self.alpha_epoch) else self.initial_alpha

    def lr_scale_at(self, epoch: int) -> float:
        return self.lr_factor ** sum(1 for e in self.lr_milestones if epoch >= self.epoch_of(e))

    def resets_at(self, epoch: int) -> bool:
        return any(self.epoch_of(e) == epoch for e in self.reset_optimizer_at)

    # ---------------------------------------------------------------- hooks
    def on_fit_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if not hasattr(pl_module, "alpha"):
            raise TypeError(f"ShootingSchedule needs a model with an `alpha` buffer, got {type(pl_module).__name__}")
        if len(trainer.optimizers) != 1:
            raise ValueError(f"ShootingSchedule expects one optimizer, the model has {len(trainer.optimizers)}")
        # Restored from a checkpoint these are already set (on_fit_start runs after the callback
        # state is loaded and before the optimizer state is, so param groups hold the initial lr).
        if self.initial_alpha is None:
            self.initial_alpha = float(pl_module.alpha)
        if self.initial_lrs is None:
            self.initial_lrs = [float(g["lr"]) for g in trainer.optimizers[0].param_groups]
        if time_budget(trainer) is not None:
            self._watch, self._warned = CpuWatch(), False
        if self.of_epochs is not None:
            if not (trainer.max_epochs or 0) > 0 and time_budget(trainer) is None:
                raise ValueError(
                    f"ShootingSchedule(of_epochs={self.of_epochs}) reads its milestones as parts of the run, which has "
                    "no end: give trainer.max_epochs or trainer.max_time"
                )
        elif (
            self.alpha_epoch is not None
            and trainer.max_epochs is not None
            and 0 <= trainer.max_epochs <= self.alpha_epoch
        ):
            rank_zero_warn(
                f"ShootingSchedule raises alpha at epoch {self.alpha_epoch} but training stops after "
                f"{trainer.max_epochs} epochs: alpha stays {self.initial_alpha:g} and the continuity gap is barely "
                f"enforced. Scale the milestones with the run (of_epochs: 1000 reads the paper's 200/600 as 20% and "
                f"60% of it; or alpha_epoch, lr_milestones: configs/quad.yaml scales them to 20/60 of 100 epochs)."
            )

    def on_train_epoch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        epoch = trainer.current_epoch
        if self.of_epochs is not None:
            self._fire(trainer, epoch)
        optimizer = trainer.optimizers[0]
        if self.resets_at(epoch) and epoch not in self.resets_done:
            optimizer.state.clear()  # fresh moments and step counts, as a newly built optimizer
            self.resets_done.append(epoch)
        pl_module.alpha.fill_(self.alpha_at(epoch))
        scale = self.lr_scale_at(epoch)
        for group, lr0 in zip(optimizer.param_groups, self.initial_lrs):
            group["lr"] = lr0 * scale

    def _fire(self, trainer: pl.Trainer, epoch: int) -> None:
        """Record ``epoch`` for every milestone not yet fired whose part of the run the progress has reached."""
        pending = [m for m in self.milestones() if m not in self.fired]
        if not pending:
            return
        max_epochs = trainer.max_epochs or 0
        budget = time_budget(trainer)
        elapsed = budget[0] if budget is not None else 0.0
        # epoch / max_epochs >= m / of_epochs, in integers; elapsed / budget >= m / of_epochs
        by_epochs = [m for m in pending if max_epochs > 0 and epoch * self.of_epochs >= m * max_epochs]
        by_time = [m for m in pending if budget is not None and elapsed * self.of_epochs >= m * budget[1]]
        now = sorted(set(by_epochs) | set(by_time))
        if budget is not None:  # each process has its own clock: all do as the first says
            now = trainer.strategy.broadcast(now, src=0)
        if not now:
            return
        before = self.alpha_at(epoch)
        self.fired.update({m: epoch for m in now})
        if not trainer.is_global_zero:
            return
        changes = [f"alpha {before:g} -> {self.alpha_at(epoch):g}"] if self.alpha_epoch in now else []
        steps = sum(1 for e in self.lr_milestones if e in now)
        changes += [f"lr x{self.lr_factor**steps:g}"] if steps else []
        changes += ["optimizer reset"] if self.resets_at(epoch) else []
        by_epoch = epoch / max_epochs if max_epochs > 0 else 0.0
        if budget is not None and elapsed / budget[1] > by_epoch:
            where = f"{elapsed / budget[1]:.0%} of the {duration(budget[1])} budget"
        else:
            where = f"{by_epoch:.0%} of {max_epochs} epochs"
        _log.info("schedule: %s at epoch %d (%s)", ", ".join(changes), epoch, where)
        self._warn_if_shared(epoch)
        for logger in trainer.loggers:
            logger.log_metrics({f"schedule/milestone_{m}": float(epoch) for m in now}, step=trainer.global_step)

    def on_train_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if trainer.is_global_zero:
            self._warn_if_shared(trainer.current_epoch)

    def cpu_others(self) -> float | None:
        """Average number of cores other processes kept busy since this process's fit started, under a time budget
        (``None``: no budget, or not measurable here)."""
        return None if self._watch is None else self._watch.others()

    def _warn_if_shared(self, epoch: int) -> None:
        others = self.cpu_others()
        if self._warned or others is None or others <= SHARED_CORES:
            return
        self._warned = True
        rank_zero_warn(
            f"other processes kept {others:.2f} cores busy on average since this fit started (epoch {epoch} now): "
            "under trainer.max_time it trains fewer epochs than alone and its milestones fire at earlier epochs, so "
            "its scores do not compare with a fit run alone. Run one training job at a time."
        )

    # ---------------------------------------------------------------- checkpointing
    def state_dict(self) -> dict[str, Any]:
        others = self.cpu_others()
        return {
            "initial_alpha": self.initial_alpha,
            "initial_lrs": self.initial_lrs,
            "resets_done": list(self.resets_done),
            "fired": dict(self.fired),
            "cpu_others": None if others is None else round(others, 3),
        }

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.initial_alpha = state_dict["initial_alpha"]
        self.initial_lrs = state_dict["initial_lrs"]
        self.resets_done = list(state_dict["resets_done"])
        self.fired = dict(state_dict.get("fired", {}))  # a checkpoint written before milestones could fire has none
