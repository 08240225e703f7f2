"""``MultipleShootingModule``: f, g and the shooting nodes, trained by multiple shooting.

``trainer.precision: 64-true`` and checkpoints: the CLI builds f and g in float32, and Lightning restores a
checkpoint into the module *before* it converts the module to float64 (``Trainer._run``: ``setup``, restore,
then the strategy's precision conversion), so a resumed float64 run would load its weights into float32
tensors, rounded. :meth:`MultipleShootingModule.setup` therefore converts the module to float64 itself under
``64-true`` (what Lightning does next anyway) before anything is restored: a resumed run continues bit for bit
like an uninterrupted one (tests/test_module.py).
"""

from __future__ import annotations

import copy
import os
from collections.abc import Mapping
from typing import Any

import lightning.pytorch as pl
import torch
import torch.nn.functional as F
from torch import nn

from ssm_ms.averaging import WeightAverage
from ssm_ms.checkpointing import (
    NETWORKS,
    check_configuration,
    keep_network_config,
    read_checkpoint,
    refuse_baseline,
    restore_float_weights,
    saved_networks,
    ssm_extras,
    write_ssm_extras,
)
from ssm_ms.nets.sensors import SensorLayout
from ssm_ms.progress import time_budget
from ssm_ms.runtime.perf import check_precision
from ssm_ms.runtime.private import built_by_lightning_cli
from ssm_ms.schedule import ShootingSchedule
from ssm_ms.training import checks, distributed
from ssm_ms.training.constraints import Penalty, make_constraint
from ssm_ms.training.nodes import NODE_UPDATES, DenseNodes
from ssm_ms.training.shooting import (
    CompiledRollout,
    decode,
    loss_function,
    multiple_shooting_loss,
    rollout,
)
from ssm_ms.units import ObservationInUnits, TransitionInUnits, Units

STATE_SAMPLE = 256  # training states an amortised-node model keeps (training_states: priors, stability reports)


class NonFiniteLossError(FloatingPointError):
    """Training produced a NaN or inf loss."""


class MultipleShootingModule(pl.LightningModule):
    """A discrete SSM ``x[t+1] = f(x[t])``, ``y[t] = g(x[t])`` learned by multiple shooting.

    The loss of a batch is ``fit + alpha * gap`` (see :func:`ssm_ms.training.shooting.multiple_shooting_loss`).
    The shooting nodes of training trajectory ``j`` are row ``j`` of ``self.nodes``, an
    ``nn.Embedding(num_trajectories, n_nodes * state_dim)`` indexed by the batch's ``"index"``.
    ``alpha`` is a buffer, stepped by the model's ``schedule`` (:class:`ssm_ms.schedule.ShootingSchedule`); a model
    given none runs the paper's (:meth:`ShootingSchedule.paper`, its milestones scaled to the run's epochs or time
    budget), so leaving the schedule out never silently trains at a constant alpha (for that:
    :meth:`ShootingSchedule.constant`).

    The model keeps the state of the data it was trained on (:attr:`data_state`: the DataModule's normalisation
    statistics, measurement shape, identity), from the DataModule when a fit starts and from the checkpoint when it
    is loaded: :attr:`units` converts between the user's units and the normalised ones ``f`` and ``g`` work in, and
    :meth:`in_units` gives ``f`` and ``g`` in the user's units.

    Args:
        f: transition model ``[N, state_dim] -> [N, state_dim]`` (e.g. ``LocallyLinearTransition``).
        g: observation model ``[N, state_dim] -> [N, *obs_shape]`` (e.g. ``ConvDecoder``, ``Projection``).
        state_dim: dimension of the latent state (``None``: ``f.state_dim``, so that it is said once).
        num_trajectories: number of training trajectories (rows of the node table). ``None``: taken
            from the DataModule's ``num_train_trajectories`` when fitting starts.
        n_nodes: shooting nodes per trajectory ``m``; the trajectory length must be a multiple of it.
        loss: ``"mse"`` or ``"bce"`` (then ``g`` must output values in [0, 1]).
        lr: Adam learning rate (the schedule lowers it at its milestones).
        schedule: alpha and the learning rate over the fit (:class:`~ssm_ms.schedule.ShootingSchedule`: its
            milestones, optimizer resets and the value alpha is raised to); ``None``: the paper's, scaled to the run
            (20% and 60% of its epochs or time budget; a run bounded by neither: the paper's epochs 200 and 600).
            A config states it as ``model.init_args.schedule``, so that an overlay changes one of its settings. Each
            fit runs a copy of it; its progress (milestones fired) is kept in the fit's checkpoints. A trainer
            callback ``ShootingSchedule`` does the same for a model given none (Lightning's way); both is an error.
        weight_decay: decoupled weight decay of ``f``, ``g`` and the node encoder (AdamW; the nodes never decay);
            0, the paper's plain Adam, by default. A regulariser for short recordings (docs/benchmarks.md).
        alpha: initial weight of the continuity gap (the schedule raises it).
        node_init_map: ``None`` to start all nodes at zero, or ``{state_index: measurement_index}`` to
            start those state components at the (flattened) measurement at each node's time, the
            others at zero (Lorenz: ``{0: 0}``).
        decode_chunk: decode at most this many states per call of ``g`` (``None``: all at once).
        node_optimizer: ``"dense"`` (the paper: one Adam over all parameters, so momentum moves every
            node at every step) or ``"sparse"`` (only the batch's nodes change: a row-wise Adam, see
            :mod:`ssm_ms.training.nodes`; also what keeps the node table out of DDP's all-reduce).
        node_lr: learning rate of the nodes (``None``: ``lr``); the schedule scales it like ``lr``.
        constraint: ``"penalty"`` (the paper's ``fit + alpha * gap``) or ``"augmented_lagrangian"``
            (multipliers per gap, in the buffer ``multipliers``; see :mod:`ssm_ms.training.constraints`).
            The two choices are strategy objects: ``self.node_update`` (:class:`~ssm_ms.training.nodes.DenseNodes`,
            :class:`~ssm_ms.training.nodes.SparseNodes`) and ``self.constraint``
            (:class:`~ssm_ms.training.constraints.Penalty`, :class:`~ssm_ms.training.constraints.AugmentedLagrangian`);
            their state stays in this module's buffers and the optimizer's.
        constraint_options: settings of the augmented Lagrangian
            (:class:`ssm_ms.training.constraints.AugmentedLagrangianOptions`: ``every_n_epochs``, ``growth``,
            ``shrink``, ``max_factor``).
        compile_rollout: ``None`` (eager) or a ``torch.compile`` mode (``"default"``, ``"reduce-overhead"``
            = CUDA graphs on a GPU, ...): the rollout of ``f`` over a sub-trajectory runs as one compiled
            graph (:class:`ssm_ms.training.shooting.CompiledRollout`).
        val_horizon: steps of the validation rollout (``val/rollout_mse``) from each validation trajectory's
            first node (``None``: its whole length). On chaotic data set it to a few Lyapunov times: a rollout
            far beyond them compares unrelated signals and the score saturates whatever the model learns.
        node_encoder: ``None`` (the paper: free shooting nodes, one row of ``nodes`` per training trajectory) or
            amortised nodes: a network of the ``history`` samples before a node's time to its state
            (:class:`ssm_ms.nets.HistoryEncoder`, or any module ``(y [N, H, *obs], u [N, H, m]) -> [N, d]`` with a
            ``history`` attribute), trained through the same loss, gap term included. A training window then
            holds ``history`` samples before its first node: ``T = history + n_nodes * n``. No node table, so
            windows may start at every sample (``stride: 1``); the state of a new recording is the encoder's
            reading of its last ``history`` samples (docs/method.md, "Amortised nodes").
        stream_weights: several sensors only: ``{stream name: factor}`` multiplying a stream's inverse noise
            variance in the fit before the weights are scaled to average 1 (``None``: every factor 1, the
            maximum-likelihood weighting; :meth:`ssm_ms.nets.sensors.SensorLayout.weights`).
        weight_average: ``None`` (the paper) or the decay of an exponential moving average of the parameters over
            the training steps (e.g. 0.999: about the last 1,000 steps), which validation scores, the checkpoints hold
            and the fit ends with (:class:`ssm_ms.averaging.WeightAverage`; docs/method.md, "Weight averaging").
        gap_scale: ``"absolute"`` (the paper: ``mean(c^2)``) or, with a ``node_encoder``, ``"node_variance"``: each
            state coordinate's gaps divided by its variance over the batch's nodes, so that states shrinking toward a
            point cannot lower the gap term (:func:`ssm_ms.training.shooting.gap_term`; docs/method.md, "Amortised
            nodes").
    """

    # validation rolls out from the shooting nodes, which only training trajectories have
    validates_on_training_trajectories = True

    def __init__(
        self,
        f: nn.Module,
        g: nn.Module,
        state_dim: int | None = None,
        num_trajectories: int | None = None,
        n_nodes: int = 4,
        loss: str = "mse",
        lr: float = 1e-3,
        alpha: float = 1.0,
        node_init_map: dict[int, int] | None = None,
        decode_chunk: int | None = None,
        node_optimizer: str = "dense",
        node_lr: float | None = None,
        constraint: str = "penalty",
        constraint_options: dict[str, float] | None = None,
        compile_rollout: str | None = None,
        val_horizon: int | None = None,
        node_encoder: nn.Module | None = None,
        weight_decay: float = 0.0,
        schedule: ShootingSchedule | None = None,
        stream_weights: dict[str, float] | None = None,
        weight_average: float | None = None,
        gap_scale: str = "absolute",
    ):
        super().__init__()
        # Built by LightningCLI, f, g and the node encoder are recorded as their config (class_path + init_args), so
        # `load_from_checkpoint` rebuilds them; built in Python, checkpoints carry the networks
        # themselves (see on_save_checkpoint).
        # (a schedule built in Python is not recorded: a model loaded from such a checkpoint runs the paper's)
        self.save_hyperparameters(ignore=[] if built_by_lightning_cli() else [*NETWORKS, "schedule"])
        if schedule is not None and not isinstance(schedule, ShootingSchedule):
            raise ValueError(
                f"schedule must be a ShootingSchedule (ssm_ms.schedule), got {type(schedule).__name__}: "
                "schedule: {class_path: ssm_ms.schedule.ShootingSchedule, init_args: {...}} in a config"
            )
        self.schedule = schedule
        self._averaging = None if weight_average is None else WeightAverage(weight_average)
        state_dim = checks.state_dim_of(f, state_dim)
        self.hparams["state_dim"] = state_dim
        loss_function(loss)  # unknown loss name: fail now, not at the first step
        checks.check_settings(state_dim, n_nodes, lr, weight_decay, num_trajectories, val_horizon, node_init_map)
        self.f, self.g = f, g
        self.state_dim, self.n_nodes = state_dim, n_nodes
        self.node_encoder = node_encoder
        self.history = checks.node_encoder_history(
            node_encoder, self.input_dim, node_optimizer, node_lr, constraint, node_init_map
        )
        # where this model's weights are restored from, when its settings came from a checkpoint (checks.check_data)
        self.checkpoint_source: str | None = None
        # the state of the data this model was trained on (DataModule.state_dict(): normalisation, shape, identity)
        self.data_state: dict[str, Any] | None = None
        self.fit_mse: float | None = None  # the last training epoch's mean fit term (normalised units)
        self.seed: int | None = None  # the seed its fit ran with (seed_everything), kept in its checkpoints
        self._fit_sums = [0.0, 0]
        self.register_buffer("alpha", torch.tensor(float(alpha)))
        checks.check_node_settings(node_optimizer, node_lr)
        self.node_update: DenseNodes = NODE_UPDATES[node_optimizer]()
        checks.check_gap_scale(gap_scale, node_encoder is not None)
        self.constraint: Penalty = make_constraint(constraint, n_nodes, constraint_options, gap_scale)
        self.constraint.attach(self)
        # each step's (index, rows updated outside autograd, residuals kept): the updates before the optimizer step
        self._pending: list[tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]] = []
        checks.check_transition(f, state_dim, self.input_dim)
        self._rollout_fn: CompiledRollout | None = None
        if compile_rollout is not None:
            try:
                self._rollout_fn = CompiledRollout(f, compile_rollout)
            except RuntimeError as err:
                raise ValueError(str(err)) from None
        self.nodes: nn.Embedding | None = None
        if node_encoder is not None:  # a sample of the states it gave in training (training_states)
            self.register_buffer("state_sample", torch.zeros(STATE_SAMPLE, state_dim))
            self.register_buffer("states_seen", torch.zeros((), dtype=torch.long))
        elif num_trajectories is not None:
            self._make_nodes(num_trajectories)

    # ------------------------------------------------------------------ construction
    @property
    def input_dim(self) -> int:
        """Inputs per step of ``f`` (``f.input_dim``; 0: an autonomous system, ``f(x)``)."""
        return int(getattr(self.f, "input_dim", 0))

    def _make_nodes(self, num_trajectories: int) -> None:
        # in the module's dtype (float64 under ``64-true``: setup converts the module before any checkpoint is
        # restored into it, see setup)
        self.nodes = nn.Embedding(num_trajectories, self.n_nodes * self.state_dim, dtype=self.alpha.dtype)
        nn.init.zeros_(self.nodes.weight)
        self.hparams["num_trajectories"] = num_trajectories
        self.node_update.prepare(self.nodes.weight)
        self.constraint.attach_table(self, num_trajectories, (self.n_nodes - 1) * self.state_dim)

    def obs_shape(self) -> tuple[int, ...]:
        """The shape of one measurement produced by g."""
        return checks.measurement_shape(self.g, self.state_dim, self.alpha.device)

    def setup(self, stage: str) -> None:
        dm = getattr(self.trainer, "datamodule", None) if self._trainer is not None else None
        if self._trainer is not None:
            check_precision(self.trainer.precision, self.trainer.strategy.root_device)
            if str(self.trainer.precision) == "64-true" and self.alpha.dtype != torch.float64:
                # Lightning restores a checkpoint into the module (Trainer._run: setup, restore, then
                # strategy.setup converts the precision), so f and g built in float32 by the CLI would round a
                # float64 checkpoint's weights to float32 on resume: convert now, as Lightning will (.double())
                self.double()
        if self.nodes is None and self.node_encoder is None:
            n = getattr(dm, "num_train_trajectories", None)
            if n is None:
                raise ValueError(
                    "model.num_trajectories is not set and the data have no num_train_trajectories: "
                    "set model.num_trajectories to the number of training trajectories"
                )
            self._make_nodes(int(n))
        if dm is not None and hasattr(dm, "seq_len"):
            if stage == "fit" and os.environ.get("PL_GLOBAL_SEED") is not None:
                self.seed = int(
                    os.environ["PL_GLOBAL_SEED"]
                )  # Lightning's seed_everything (a resume: the checkpoint's)
            if stage == "fit" and callable(getattr(dm, "state_dict", None)):
                self.data_state = dm.state_dict()  # the statistics f and g learn in (a resumed fit: the checkpoint's)
            checks.check_inputs(self.input_dim, int(getattr(dm, "input_dim", 0)))
            self.adopt_sensors(getattr(dm, "sensor_layout", None))
            checks.adopt_measurement_shape(self.g, self.hparams.get("g"), tuple(dm.obs_shape))
            checks.check_data(self, dm.seq_len, dm.obs_shape, getattr(dm, "num_train_trajectories", None))
            if stage == "fit" and self.hparams.loss == "bce" and hasattr(dm, "check_range"):
                dm.check_range(0.0, 1.0, "loss: bce")  # else torch fails mid-training
            if stage == "fit" and self.hparams.get("node_init_map"):
                self.init_nodes_from_measurements(dm.node_measurements(self.n_nodes))
        if stage == "fit" and distributed.world_size() > 1:  # before DDP compares the ranks' models
            checks.check_replicated_tables(self.nodes.weight)

    @property
    def units(self) -> Units:
        """The normalisation of the data this model was trained on (the identity where there was none)."""
        return Units.from_data_state(self.data_state)

    def in_units(self) -> tuple[TransitionInUnits, ObservationInUnits]:
        """``f`` taking inputs and ``g`` returning measurements in the user's units (the data's original units):
        hand these, not ``f`` and ``g``, to code that knows nothing of the normalisation (e.g.
        ``UnscentedKalmanFilter(*model.in_units(), measurement_var=...)`` on raw measurements)."""
        units = self.units
        return TransitionInUnits(self.f, units), ObservationInUnits(self.g, units)

    def configure_callbacks(self) -> list[pl.Callback]:
        """A fit runs a copy of the model's ``schedule``, or the trainer's :class:`~ssm_ms.schedule.ShootingSchedule`,
        or else the paper's, scaled to the run (alpha raised and lr / 10 at 20% of its epochs or time budget, lr / 10
        again at 60%; a run bounded by neither: at the paper's epochs 200 and 600): the schedule is part of the
        method. With ``weight_average``, also a fresh :class:`~ssm_ms.averaging.WeightAverage` (after the schedule)."""
        if self._trainer is None or self.trainer.state.fn != "fit":
            return []
        averaging = [] if self._averaging is None else [copy.deepcopy(self._averaging)]
        return self._schedule_callbacks() + averaging

    def _schedule_callbacks(self) -> list[pl.Callback]:
        on_trainer = any(isinstance(c, ShootingSchedule) for c in self.trainer.callbacks)
        if self.schedule is not None:
            if on_trainer:
                raise ValueError(
                    "the schedule is given twice, as the model's schedule and among the trainer's callbacks: "
                    "keep one (configs: model.init_args.schedule)"
                )
            return [copy.deepcopy(self.schedule)]  # fresh progress per fit; a resumed fit loads its own
        if on_trainer:
            return []
        bounded = (self.trainer.max_epochs or 0) > 0 or time_budget(self.trainer) is not None
        paper = ShootingSchedule.paper()
        return [paper if bounded else ShootingSchedule(paper.alpha, paper.alpha_epoch, paper.lr_milestones)]

    def adopt_sensors(self, layout: Any) -> None:
        """Several sensors (:mod:`ssm_ms.nets.sensors`): weigh each measurement component by the inverse of its
        stream's noise variance in the fit (times its factor in ``stream_weights``, scaled to average 1) and leave
        missing samples (NaN) out; a ``g`` with one head per stream must name the streams of the data, in their order
        and shapes."""
        self._missing = bool(layout)
        weights = self.hparams.get("stream_weights")
        if not layout:
            if weights:
                raise ValueError(
                    f"stream_weights {dict(weights)} weigh the streams of several sensors, and these data have one: "
                    "remove model.init_args.stream_weights"
                )
            return
        if self.node_encoder is not None:
            raise ValueError(
                "several sensors (missing samples) cannot be read by the node encoder: train amortised nodes on one "
                "sensor, or several sensors with free nodes (remove node_encoder)"
            )
        layout = SensorLayout.from_state_dict(layout) if not isinstance(layout, SensorLayout) else layout
        self.register_buffer("measurement_weights", layout.weights(weights).to(self.alpha), persistent=False)
        checks.check_sensor_heads(self.g, {s.name: tuple(s.shape) for s in layout.streams})

    def fit_options(self) -> dict[str, Any]:
        """The fit's per-component weights and missing-sample masking (several sensors), or the paper's plain fit."""
        if not getattr(self, "_missing", False):
            return {}
        return {"weights": self.measurement_weights, "missing": True}

    def states_at_measurements(self, y_at: torch.Tensor, base: torch.Tensor | None = None) -> torch.Tensor:
        """``[N, m, d]``: states at the times of the measurements ``y_at [N, m, *obs]``, ``base [d]`` (default zero)
        with the components ``node_init_map`` names read from the measurements there (how the nodes start, and where
        the forecasters start an unseen sequence)."""
        mapping = {int(k): int(v) for k, v in (self.hparams.get("node_init_map") or {}).items()}
        flat = y_at.reshape(*y_at.shape[:2], -1)
        bad = [v for v in mapping.values() if not 0 <= v < flat.shape[-1]]
        if bad:
            raise ValueError(f"node_init_map reads measurement components {bad} outside 0..{flat.shape[-1] - 1}")
        base = torch.zeros(self.state_dim) if base is None else base
        x = base.to(flat).expand(*flat.shape[:2], self.state_dim).clone()
        for state_i, obs_i in mapping.items():
            x[..., state_i] = flat[..., obs_i]
        return x

    @torch.no_grad()
    def init_nodes_from_measurements(self, y_nodes: torch.Tensor) -> None:
        """Start nodes at measurements: ``y_nodes [N, m, *obs]`` is y at each node's time."""
        nodes = self.states_at_measurements(y_nodes.reshape(y_nodes.shape[0], self.n_nodes, -1))
        self.nodes.weight.copy_(nodes.view(len(nodes), -1).to(self.nodes.weight))

    # ------------------------------------------------------------------ model
    def forward(self, x0: torch.Tensor, steps: int, u: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Roll ``f`` out ``steps`` states from ``x0 [B, d]`` (under inputs ``u [B, >= steps - 1, input_dim]`` where
        ``f`` takes them) and decode: ``(states [B, steps, d], y [B, steps, ...])``."""
        checks.check_rollout_inputs(self.input_dim, u, steps - 1)
        states = rollout(self.f, x0, steps, u) if self._rollout_fn is None else self._rollout_fn(x0, steps, u)
        return states, decode(self.g, states, self.hparams.decode_chunk)

    def node_states(self, index: torch.Tensor) -> torch.Tensor:
        """Shooting nodes ``[B, m, d]`` of the training trajectories ``index`` (free nodes)."""
        if self.node_encoder is not None:
            raise ValueError(
                "this SSM's shooting nodes come from its node encoder, not a table of training trajectories: this "
                "use needs free nodes (an SSM trained without node_encoder)"
            )
        if self.nodes is None:
            raise RuntimeError("the node table does not exist yet: set num_trajectories or call trainer.fit")
        return self.nodes(index).view(len(index), self.n_nodes, self.state_dim)

    def encode_nodes(self, y: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        """Amortised nodes ``[B, m, d]`` of windows ``y [B, H + m n, *obs]`` (inputs ``u`` beside them): node ``i``, at
        window time ``H + i n``, is the node encoder's reading of samples ``i n .. i n + H - 1``."""
        h, m = self.history, self.n_nodes
        b, t = y.shape[:2]
        n = (t - h) // m
        if n < 1 or t != h + m * n:
            raise ValueError(f"windows of {t} samples do not hold a history of {h} and {m} pieces of equal length")
        at = (torch.arange(m, device=y.device) * n)[:, None] + torch.arange(h, device=y.device)  # [m, H]
        yh = y[:, at].reshape(b * m, h, *y.shape[2:])
        uh = None if u is None or not self.input_dim else u[:, at].reshape(b * m, h, u.shape[-1])
        return self.node_encoder(yh, uh).view(b, m, self.state_dim)

    def batch_nodes(
        self, batch: Mapping[str, torch.Tensor], rows: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """``(nodes [B, m, d], y, u)``: a batch's shooting nodes and the measurements and inputs their pieces cover:
        free nodes (the table's rows of ``batch["index"]``, or ``rows`` where given: the sparse update's leaf) over
        the whole windows, or amortised nodes over the windows after their first ``history`` samples."""
        y, u = batch["y"], batch.get("u")
        if self.node_encoder is None:
            index = batch["index"]
            nodes = self.node_states(index) if rows is None else rows.view(len(index), self.n_nodes, self.state_dim)
            return nodes, y, u
        h = self.history
        return self.encode_nodes(y, u), y[:, h:], None if u is None else u[:, h:]

    def training_states(self) -> torch.Tensor:
        """``[N, d]`` states of the training data (detached): the free nodes, or the last :data:`STATE_SAMPLE`
        states the node encoder gave in training. Where the filters' prior and the stability report come from."""
        if self.node_encoder is None:
            if self.nodes is None:
                raise RuntimeError("the node table does not exist yet: set num_trajectories or call trainer.fit")
            return self.nodes.weight.detach().view(-1, self.state_dim)
        seen = int(self.states_seen)
        if seen == 0:
            raise ValueError("the node encoder has given no training states yet: train the model first")
        return self.state_sample[: min(seen, STATE_SAMPLE)].detach()

    @torch.no_grad()
    def _record_states(self, nodes: torch.Tensor) -> None:
        """Keep the newest amortised nodes in the ring ``state_sample`` (no host sync)."""
        flat = nodes.detach().reshape(-1, self.state_dim)[-STATE_SAMPLE:]
        at = (self.states_seen + torch.arange(len(flat), device=flat.device)) % STATE_SAMPLE
        self.state_sample[at] = flat.to(self.state_sample)
        self.states_seen += len(flat)

    def shooting_loss(self, batch: Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        nodes, y, u = self.batch_nodes(batch)
        return multiple_shooting_loss(
            self.f,
            self.g,
            nodes,
            y,
            self.hparams.loss,
            self.hparams.decode_chunk,
            self._rollout_fn,
            u,
            **self.fit_options(),
            gap_scale=self.constraint.gap_scale,
        )

    # ------------------------------------------------------------------ training
    def training_step(self, batch: Mapping[str, torch.Tensor], batch_idx: int) -> torch.Tensor:
        """The paper's objective ``mean fit(g(f^k(s_i)), y) + alpha * mean ||s_{i+1} - f^n(s_i)||^2`` on the batch's
        trajectories (or its augmented Lagrangian: :attr:`constraint`), their nodes as :attr:`node_update` keeps
        them."""
        index = batch["index"]
        rows = None if self.nodes is None else self.node_update.rows(self.nodes.weight, index)
        checks.check_rollout_inputs(self.input_dim, batch.get("u"), 1)
        nodes, y, u = self.batch_nodes(batch, rows)
        if self.node_encoder is not None:
            self._record_states(nodes)
        args = (self.f, self.g, nodes, y, self.hparams.loss, self.hparams.decode_chunk, self._rollout_fn, u)
        loss, fit, gap, residual = self.constraint.loss(self, args, self.fit_options(), index)
        if not torch.isfinite(loss):
            raise NonFiniteLossError(self._nan_message(fit, gap))
        if rows is not None or residual is not None:
            self._pending.append((index, rows, residual))
        if distributed.world_size() > 1:  # shards of unequal size: weight so DDP's average is the global mean
            loss = loss * distributed.shard_weight(len(index), loss.device)
        bs = len(index)
        self._fit_sums[0] = self._fit_sums[0] + fit.detach() * bs  # a tensor: no device sync in the step
        self._fit_sums[1] += bs
        self.log_dict({"train/fit": fit, "train/gap": gap, "train/loss": loss}, batch_size=bs, prog_bar=True)
        self.log("alpha", self.constraint.weight(self), batch_size=bs)
        self.log("lr", self.optimizers().param_groups[0]["lr"], batch_size=bs)
        return loss

    def _nan_message(self, fit: torch.Tensor, gap: torch.Tensor) -> str:
        ckpt = getattr(self.trainer.checkpoint_callback, "last_model_path", "") if self._trainer else ""
        return (
            f"the training loss is not finite at epoch {self.current_epoch}, step {self.global_step} "
            f"(fit={fit.item():.4g}, gap={gap.item():.4g}, alpha={self.alpha.item():.4g}). Training stopped; "
            + (f"the last good checkpoint is {ckpt}. " if ckpt else "no checkpoint was written yet. ")
            + "Lower the learning rate or alpha (or raise alpha later), check the data for outliers, "
            "and resume with --ckpt_path."
        )

    def validation_step(self, batch: Mapping[str, torch.Tensor], batch_idx: int) -> dict[str, torch.Tensor]:
        """Roll training trajectories out from their first node over ``val_horizon`` steps (default: their
        whole length after the node encoder's history) and score the rollout against the measurements (and the clean
        signal, where given)."""
        nodes, y, u = self.batch_nodes(batch)
        horizon = self.hparams.get("val_horizon") or y.shape[1]
        y = y[:, :horizon]
        _, y_hat = self(nodes[:, 0], y.shape[1], None if u is None else u[:, :horizon])
        bs = len(y)
        self.log("val/rollout_mse", _masked_mse(y_hat, y), batch_size=bs, prog_bar=True)
        out = {"index": batch["index"], "y": y, "y_hat": y_hat}
        if "y_clean" in batch:
            y_clean = batch["y_clean"][:, self.history :][:, :horizon]
            self.log("val/rollout_mse_clean", _masked_mse(y_hat, y_clean), batch_size=bs)
            out["y_clean"] = y_clean
        return out

    def configure_optimizers(self) -> torch.optim.Optimizer:
        node_lr, decay = self.hparams.get("node_lr"), float(self.hparams.get("weight_decay", 0.0))
        # weight decay shrinks the networks' weights only: the nodes are states, not weights
        if self.nodes is None or not (self.node_update.own_group or node_lr is not None or decay):
            groups = [{"params": list(self.parameters())}]
        else:
            others = [p for p in self.parameters() if p is not self.nodes.weight]
            # the nodes in a group of their own (their lr; in sparse mode Adam skips them: no .grad)
            groups = [{"params": others}, {"params": [self.nodes.weight], "lr": node_lr or self.hparams.lr}]
            if decay:
                groups[1]["weight_decay"] = 0.0
        if not decay:
            return torch.optim.Adam(groups, lr=self.hparams.lr)
        return torch.optim.AdamW(groups, lr=self.hparams.lr, weight_decay=decay)

    # ------------------------------------------------------------------ sparse nodes, multipliers, DDP
    def on_fit_start(self) -> None:
        if self.nodes is not None:
            self.node_update.check(self.trainer.optimizers, self.nodes.weight)

    def on_train_epoch_start(self) -> None:
        self._pending.clear()
        self.constraint.start_epoch()
        self._fit_sums = [0.0, 0]

    @torch.no_grad()
    def on_before_optimizer_step(self, optimizer: torch.optim.Optimizer) -> None:
        """Sparse node rows and multipliers, from every rank's batch (the same update on every rank)."""
        if not self._pending:
            return
        index = torch.cat([p[0] for p in self._pending])
        sparse = self._pending[0][1] is not None
        grads = torch.cat([p[1].grad.flatten(1) for p in self._pending]) if sparse else index.new_zeros(len(index), 0)
        kept = self._pending[0][2] is not None
        residual = torch.cat([p[2] for p in self._pending]) if kept else grads[:, :0]
        self._pending.clear()
        w = distributed.world_size()
        index, grads, residual = distributed.all_gather_rows(index, grads, residual)
        if sparse:
            self.node_update.step(optimizer, self.nodes.weight, index, grads / w if w > 1 else grads)
        if kept:
            self.constraint.update(self, index, residual)

    def on_train_epoch_end(self) -> None:
        if self._fit_sums[1]:
            self.fit_mse = float(self._fit_sums[0]) / self._fit_sums[1]
        self.constraint.end_epoch(self)

    # ------------------------------------------------------------------ checkpoints
    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        # built in Python ("f" not in its config): keep the networks so the checkpoint reloads on its own
        networks = None if "f" in self.hparams else {name: getattr(self, name) for name in NETWORKS}
        write_ssm_extras(checkpoint, self.fit_mse, self.seed, self.data_state, networks)

    @classmethod
    def load_from_checkpoint(cls, checkpoint_path: Any, *args: Any, **kwargs: Any) -> MultipleShootingModule:
        """Lightning's loader; for a model built in Python (f and g not in its config), the networks
        pickled in the checkpoint are used unless ``f=`` and ``g=`` are given (trust the file)."""
        checkpoint = read_checkpoint(checkpoint_path)
        if "f" not in kwargs or "g" not in kwargs:
            for name, network in saved_networks(checkpoint).items():
                kwargs.setdefault(name, network)
        model = super().load_from_checkpoint(checkpoint_path, *args, **kwargs)
        if "f" not in kwargs and "g" not in kwargs:
            keep_network_config(model.hparams, checkpoint)
        return model

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Refuse a checkpoint of another configuration with a message that says what differs."""
        restore_float_weights(checkpoint)
        for name, value in ssm_extras(checkpoint).items():  # data_state, fit_mse, seed: those it holds
            setattr(self, name, value)
        refuse_baseline(checkpoint)
        state = checkpoint.get("state_dict", {})
        if self.nodes is None and "nodes.weight" in state:
            self._make_nodes(int(state["nodes.weight"].shape[0]))
        check_configuration(checkpoint, self.hparams, self.state_dict())


def _masked_mse(y_hat: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """MSE over the measured elements (a sensor's missing samples are NaN)."""
    observed = torch.isfinite(y)
    return F.mse_loss(y_hat, y) if bool(observed.all()) else F.mse_loss(y_hat[observed], y[observed])
