"""The checks of a :class:`~ssm_ms.module.MultipleShootingModule`'s settings, networks and data, as plain functions:
each fails before training (at construction, or when a fit or the Python API meets the data) with one message that
says what differs and what to change. They take what they check, not the module."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Protocol

import torch
from torch import nn

from ssm_ms.nets.history import HistoryEncoder
from ssm_ms.training import distributed
from ssm_ms.training.nodes import NODE_UPDATES
from ssm_ms.training.shooting import check_scale


def state_dim_of(f: nn.Module, state_dim: int | None) -> int:
    """The latent dimension: as given, else ``f.state_dim``; the two must agree where both are known."""
    own = getattr(f, "state_dim", None)
    if state_dim is None:
        if not isinstance(own, int):
            raise ValueError(
                f"state_dim is not given and f ({type(f).__name__}) has no state_dim attribute: give state_dim"
            )
        return own
    if isinstance(own, int) and own != state_dim:
        raise ValueError(
            f"f has state_dim {own} but the model was given state_dim {state_dim}: give it once (leave the model's "
            "unset, or interpolate f's from it: ${model.init_args.state_dim})"
        )
    return int(state_dim)


def check_settings(
    state_dim: int,
    n_nodes: int,
    lr: float,
    weight_decay: float,
    num_trajectories: int | None,
    val_horizon: int | None,
    node_init_map: Mapping[int, int] | None,
) -> None:
    """The model's numeric settings, each in its range."""
    if state_dim < 1 or n_nodes < 1:
        raise ValueError(
            f"state_dim and n_nodes must be >= 1, got {state_dim} and {n_nodes}: set model.init_args.state_dim "
            "to the latent size and n_nodes to a divisor of the trajectory length"
        )
    if not lr > 0:
        raise ValueError(f"the learning rate must be > 0, got {lr}: set model.init_args.lr (the paper: 1e-3)")
    if not weight_decay >= 0:
        raise ValueError(
            f"weight_decay must be >= 0, got {weight_decay}: set model.init_args.weight_decay (0: the paper's Adam)"
        )
    if num_trajectories is not None and num_trajectories < 1:
        raise ValueError(f"num_trajectories must be >= 1, got {num_trajectories}")
    if val_horizon is not None and (int(val_horizon) != val_horizon or val_horizon < 1):
        raise ValueError(
            f"val_horizon must be a number of steps >= 1 (or unset: the whole trajectory), got {val_horizon!r}"
        )
    if node_init_map is not None:
        bad = [k for k in node_init_map if not 0 <= int(k) < state_dim]
        if bad:
            raise ValueError(f"node_init_map names state components {bad} outside 0..{state_dim - 1}")


def check_node_settings(node_optimizer: str, node_lr: float | None) -> None:
    """The free nodes' update: a known ``node_optimizer``, a positive ``node_lr`` where given."""
    if node_optimizer not in NODE_UPDATES:
        raise ValueError(f"unknown node_optimizer {node_optimizer!r}: choose one of {list(NODE_UPDATES)}")
    if node_lr is not None and node_lr <= 0:
        raise ValueError(f"node_lr must be > 0 (or unset to use lr), got {node_lr}")


def check_gap_scale(gap_scale: str, amortised: bool) -> None:
    """``gap_scale`` is one of :data:`~ssm_ms.training.shooting.GAP_SCALES`; a gap measured relative to the nodes'
    variance needs amortised nodes (free nodes all start at zero)."""
    check_scale(gap_scale)
    if gap_scale == "node_variance" and not amortised:
        raise ValueError(
            "gap_scale: node_variance divides the gaps by the nodes' variance over a batch, but free nodes all start "
            "at zero (no variance): use it with amortised nodes (model.init_args.node_encoder), or gap_scale: absolute"
        )


def check_transition(f: nn.Module, state_dim: int, input_dim: int) -> None:
    """``f`` maps a batch of states (and inputs, where it takes them) to a batch of states."""
    with torch.no_grad():
        x = torch.zeros(2, state_dim)
        try:
            out = f(x) if input_dim == 0 else f(x, torch.zeros(2, input_dim))
        except Exception as e:
            raise ValueError(
                f"f fails on a state batch of shape [2, {state_dim}]"
                + (f" and inputs [2, {input_dim}]" if input_dim else "")
                + f" ({e}); check that f's state_dim equals model.state_dim={state_dim}"
            ) from e
    if tuple(out.shape) != (2, state_dim):
        raise ValueError(
            f"f maps states [2, {state_dim}] to shape {tuple(out.shape)}: a transition must return "
            f"[N, state_dim]; check that f's state_dim equals model.state_dim={state_dim}"
        )


def node_encoder_history(
    encoder: nn.Module | None,
    input_dim: int,
    node_optimizer: str,
    node_lr: float | None,
    constraint: str,
    node_init_map: Any,
) -> int:
    """The samples an amortised-node model reads before each node (0: free nodes), or one message for a
    setting that belongs to free nodes (``input_dim``: the inputs per step ``f`` takes)."""
    if encoder is None:
        return 0
    history = getattr(encoder, "history", None)
    if not isinstance(history, int) or history < 1:
        raise ValueError(
            f"the node encoder ({type(encoder).__name__}) needs a 'history' attribute, the samples it reads "
            "before a node (>= 1): use ssm_ms.nets.HistoryEncoder"
        )
    given = {
        "node_optimizer: sparse": node_optimizer != "dense",
        "node_lr": node_lr is not None,
        "constraint: augmented_lagrangian": constraint != "penalty",
        "node_init_map": bool(node_init_map),
    }
    bad = [k for k, v in given.items() if v]
    if bad:
        raise ValueError(
            f"{', '.join(bad)} set the free shooting nodes, but this model's nodes come from its node_encoder: "
            "remove them (or remove node_encoder for free nodes)"
        )
    if int(getattr(encoder, "input_dim", 0)) != input_dim:
        raise ValueError(
            f"the node encoder reads {int(getattr(encoder, 'input_dim', 0))} inputs per sample but f takes "
            f"{input_dim}: give them the same input_dim"
        )
    return history


def measurement_shape(g: nn.Module, state_dim: int, device: torch.device) -> tuple[int, ...]:
    """The shape of one measurement ``g`` gives (a state on ``device``), or one message where g fails on a state."""
    with torch.no_grad():
        try:
            out = g(torch.zeros(1, state_dim, device=device))
        except Exception as e:
            raise ValueError(
                f"g fails on a state batch of shape [1, {state_dim}] ({e}); check that g's state_dim "
                f"equals model.state_dim={state_dim}"
            ) from e
    return tuple(out.shape[1:])


def check_rollout_inputs(input_dim: int, u: torch.Tensor | None, steps: int) -> None:
    """One message for a rollout of ``steps`` transitions without the inputs ``f`` needs (or with some it
    does not take)."""
    if input_dim and (u is None or u.shape[-2] < steps):
        have = "none" if u is None else f"{u.shape[-2]}"
        raise ValueError(f"f takes inputs: a rollout of {steps} steps needs u [B, >= {steps}, {input_dim}], got {have}")
    if not input_dim and u is not None:
        raise ValueError("f takes no inputs (input_dim 0): give no u")


def check_inputs(input_dim: int, data_inputs: int) -> None:
    """Fail before training when ``f`` (``input_dim`` inputs per step) and the data disagree on the inputs per
    step."""
    if data_inputs == input_dim:
        return
    if input_dim == 0:
        fix = f"give f input_dim: {data_inputs} (model.init_args.f.init_args.input_dim) to learn f(x, u)"
    elif data_inputs == 0:
        fix = (
            "give the data its inputs (FileDataModule: the array 'u' [N, T, input_dim] beside 'y'), or set "
            "f's input_dim to 0 for an autonomous system"
        )
    else:
        fix = f"set f's input_dim to {data_inputs}"
    raise ValueError(f"f takes {input_dim} inputs per step but the data have {data_inputs}: {fix}")


def check_sensor_heads(g: nn.Module, streams: Mapping[str, tuple[int, ...]]) -> None:
    """A ``g`` with one head per sensor stream (a ``shapes`` attribute) names the data's ``streams``
    (``{name: shape}``), in their order and shapes."""
    shapes = getattr(g, "shapes", None)
    if shapes is None:
        return
    if list(shapes) != list(streams) or any(tuple(shapes[k]) != streams[k] for k in streams):
        raise ValueError(
            f"g's heads give the streams {dict(shapes)} but the data's sensors are {streams}: give g one head "
            "per sensor, in the data's order and shapes"
        )


def adopt_measurement_shape(g: nn.Module, g_config: Any, obs_shape: tuple[int, ...]) -> None:
    """Hand the data's measurement shape to a g that takes its size from the data (e.g.
    ``LinearReadout(out_features=None)``), and record the size it fixed in g's config (``g_config``: the model's
    ``hparams["g"]``, where the CLI built g)."""
    adopt = getattr(g, "adopt_measurement_shape", None)
    fixed = adopt(obs_shape) if callable(adopt) else {}
    if fixed and isinstance(g_config, Mapping) and isinstance(g_config.get("init_args"), dict):
        g_config["init_args"].update(fixed)  # hparams.yaml and checkpoints rebuild g at this size


class ShootingModel(Protocol):
    """What :func:`check_data` reads of a :class:`~ssm_ms.module.MultipleShootingModule`."""

    n_nodes: int
    history: int  # the node encoder's (0: free nodes)
    node_encoder: nn.Module | None
    nodes: nn.Embedding | None  # the node table (None: none yet, or amortised nodes)
    checkpoint_source: str | None

    def obs_shape(self) -> tuple[int, ...]: ...


def check_data(model: ShootingModel, seq_len: int, obs_shape: tuple[int, ...], num_train: int | None = None) -> None:
    """Fail before training when the data and the model disagree (shapes, T, trajectory count).

    With ``model.checkpoint_source`` set (the CLI sets it under ``--ckpt_path``, having rebuilt the model from the
    checkpoint's settings), a disagreement means the checkpoint belongs to another model or data: the message says
    that first, then the detail, and points to the checkpoint's own config."""
    problem = None
    shot = seq_len - model.history  # the samples the pieces cover (amortised nodes: after the first's history)
    if shot < model.n_nodes:
        problem = (
            f"trajectory length T={seq_len} leaves no sample to shoot over after the node encoder's history of "
            f"{model.history}",
            f"give windows of history + n_nodes * n samples (e.g. window: {model.history + model.n_nodes * 10})",
        )
    elif shot % model.n_nodes != 0:
        divisors = [k for k in range(1, shot + 1) if shot % k == 0]
        problem = (
            f"trajectory length T={seq_len}"
            + (f" less the node encoder's history of {model.history} = {shot}" if model.history else "")
            + f" is not divisible by model.n_nodes={model.n_nodes}",
            f"choose n_nodes among {divisors}"
            + (f", or a window of {model.history} + a multiple of {model.n_nodes}" if model.history else ""),
        )
    elif tuple(out := model.obs_shape()) != tuple(obs_shape):
        problem = (
            f"the observation model g outputs measurements of shape {out} but the data have shape {tuple(obs_shape)}",
            "adapt g (e.g. ConvDecoder's image_size to the data's, a linear g's out_features to the "
            "channel count, or the Projection indices to the measured components)",
        )
    elif isinstance(model.node_encoder, HistoryEncoder) and model.node_encoder.obs_shape != tuple(obs_shape):
        shape = tuple(obs_shape)
        problem = (
            f"the node encoder reads measurements of shape {model.node_encoder.obs_shape}, the data have {shape}",
            f"set the node encoder's obs_dim to {shape[0] if len(shape) == 1 else list(shape)}"
            + (" (and frames, its per-frame CNN's preset)" if len(shape) == 3 else ""),
        )
    elif num_train is not None and model.nodes is not None and model.nodes.num_embeddings != num_train:
        problem = (
            f"the model holds shooting nodes for {model.nodes.num_embeddings} trajectories but the "
            f"training set has {num_train}",
            f"set model.num_trajectories to {num_train} (or leave it unset)",
        )
    if problem is None:
        return
    if model.checkpoint_source:
        raise ValueError(
            f"the checkpoint {model.checkpoint_source} was trained for another model or other data than "
            f"this command's: {problem[0]}; resume it with the config saved beside it (config.yaml in its run "
            "folder), or start a fresh run without --ckpt_path"
        )
    raise ValueError(f"{problem[0]}: {problem[1]}")


def check_replicated_tables(table: torch.Tensor) -> None:
    """Under DDP every rank must hold the same node ``table``, sized for the same data set."""
    signatures = distributed.table_signature(table)
    if any(not torch.equal(s, signatures[0]) for s in signatures):
        raise ValueError(
            f"DDP: the ranks hold different node tables (rows per rank: {[int(s[0]) for s in signatures]}), "
            "so their training sets differ: every rank must build the same training set (same data config, "
            "files and seed) with the same model.num_trajectories, and resume from the same checkpoint"
        )
