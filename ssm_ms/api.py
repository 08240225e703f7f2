"""The Python API: learn a state-space model from arrays, then simulate, forecast and filter in the user's units.

::

    from ssm_ms import Recordings, SSM, fit

    data = Recordings(y=y, u=u, dt=0.05)        # arrays in memory: [T, D], [N, T, D], or a list of any lengths
    model = SSM(data, state_dim=8)              # SSM-LL, g sized from the data, the paper's defaults
    fit(model, data, epochs=300)                # Lightning: the paper's schedule, progress, TensorBoard, checkpoints
    y_sim = model.simulate(u_new[50:], y_init=y_new[:50], u_init=u_new[:50])   # original units
    x, P = model.filter(y_new[:50], u=u_new[:50])                               # states of a sequence

:class:`SSM` wraps the :class:`~ssm_ms.module.MultipleShootingModule` that ``cli.py`` trains (``model.module``), so a
checkpoint of either loads in the other (:meth:`SSM.load`). Every array in and out of its methods is in the data's
own units (the model keeps the normalisation it was trained with): numpy arrays in, numpy arrays out (torch tensors
in, tensors out). Time runs along the first axis of one sequence (``[T, ...]``), the second of a batch
(``[B, T, ...]``); inputs ``u[t]`` are those at the time of ``y[t]``, acting between ``t`` and ``t + 1``.
docs/python.md is the guide.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
import numpy as np
import torch
from torch import nn

from datamodules.base import TrajectoryDataModule
from datamodules.recordings import Recordings
from ssm_ms.arrays import as_output, input_tensor, stream_tensor
from ssm_ms.inference import StateEncoderModule
from ssm_ms.inference.simulation import divergence_bound, estimate_states, free_run
from ssm_ms.module import MultipleShootingModule
from ssm_ms.nets import (
    ConvDecoder,
    FullyConnectedTransition,
    LinearReadout,
    LocallyLinearTransition,
    SensorHeads,
)
from ssm_ms.trainer import train
from ssm_ms.training import checks
from ssm_ms.units import Units

__all__ = ["SSM", "Recordings", "fit"]

TRANSITIONS = {"ll": LocallyLinearTransition, "fc": FullyConnectedTransition}
MAX_PIECE = 25  # the paper's pieces: 100-frame pendulum sequences in 4 of 25 samples


def default_nodes(seq_len: int) -> int:
    """The fewest shooting nodes ``m`` dividing ``T`` whose pieces have at most :data:`MAX_PIECE` samples."""
    return next(m for m in range(1, seq_len + 1) if seq_len % m == 0 and seq_len // m <= MAX_PIECE)


def default_observation(state_dim: int, data: TrajectoryDataModule) -> nn.Module:
    """``g`` for the data: a linear read-out of vectors, the paper's decoder for square grey images, one such head per
    sensor for several."""
    layout = getattr(data, "sensor_layout", None)
    if layout:
        return SensorHeads(state_dim, {s["name"]: _head(state_dim, tuple(s["shape"])) for s in layout})
    return _head(state_dim, tuple(data.obs_shape))


def _head(state_dim: int, shape: tuple[int, ...]) -> nn.Module:
    if len(shape) == 1:
        return LinearReadout(state_dim, out_features=shape[0])
    if len(shape) == 3 and shape[0] == 1 and shape[1] == shape[2]:
        return ConvDecoder(state_dim, preset="pendulum", image_size=shape[1])
    raise ValueError(
        f"no default g for measurements of shape {shape}: give SSM(..., g=<an nn.Module [N, state_dim] -> [N, "
        f"{', '.join(map(str, shape))}]>)"
    )


class SSM:
    """A discrete state-space model ``x[t+1] = f(x[t], u[t])``, ``y[t] = g(x[t])``, learned by multiple shooting.

    Args:
        data: the training data (:class:`Recordings`, or any of this project's DataModules): they size ``g`` (their
            measurement shape), ``f``'s inputs, the shooting nodes (one row per training window) and ``n_nodes``.
        state_dim: the latent dimension ``d``, said here only (``f`` and ``g`` are built with it).
        f: ``"ll"`` (the paper's SSM-LL, :class:`~ssm_ms.nets.LocallyLinearTransition`), ``"fc"`` (SSM-FC,
            :class:`~ssm_ms.nets.FullyConnectedTransition`), or an ``nn.Module`` of your own (then ``state_dim`` may
            be left out: its ``state_dim`` attribute).
        f_options: keyword arguments of the transition class (default: the paper's: SSM-LL 32 matrices and a
            1024-wide beta network, SSM-FC three 512-wide layers), e.g. ``{"n_matrices": 8, "hidden": 128}``.
        g: the observation model (default :func:`default_observation`: a linear read-out of vectors, the paper's
            transposed-convolution decoder for square grey images, one head per sensor for several).
        n_nodes: shooting nodes per training window (default :func:`default_nodes`: the fewest whose pieces have at
            most 25 samples); must divide the window length.
        seed: the seed of the networks' initial weights (``lightning.seed_everything``, as ``seed_everything`` of a
            config: the same seed and settings build the same model as ``cli.py``).
        **options: the other arguments of :class:`~ssm_ms.module.MultipleShootingModule` (``loss``, ``lr``,
            ``alpha``, ``node_init_map``, ``node_optimizer``, ``constraint``, ``val_horizon``, ...).
    """

    def __init__(
        self,
        data: TrajectoryDataModule,
        state_dim: int | None = None,
        *,
        f: str | nn.Module = "ll",
        f_options: Mapping[str, Any] | None = None,
        g: nn.Module | None = None,
        n_nodes: int | None = None,
        seed: int | None = 0,
        **options: Any,
    ):
        if not isinstance(data, TrajectoryDataModule):
            raise ValueError(
                f"data must be the training data as a DataModule (ssm_ms.Recordings(y=..., u=...)), got "
                f"{type(data).__name__}"
            )
        if seed is not None:
            pl.seed_everything(seed, verbose=False)
        input_dim = int(data.input_dim)
        if isinstance(f, str):
            if f not in TRANSITIONS:
                raise ValueError(f"f must be one of {sorted(TRANSITIONS)} or an nn.Module, got {f!r}")
            if state_dim is None:
                raise ValueError("give state_dim, the latent dimension (e.g. SSM(data, state_dim=8))")
            f = TRANSITIONS[f](state_dim, input_dim=input_dim, **dict(f_options or {}))
        elif f_options:
            raise ValueError("f_options configure a transition named by f ('ll', 'fc'): build your f with them instead")
        state_dim = state_dim or getattr(f, "state_dim", None)
        if g is None:
            if state_dim is None:
                raise ValueError("give state_dim, the latent dimension (e.g. SSM(data, state_dim=8))")
            g = default_observation(state_dim, data)
        n_nodes = default_nodes(int(data.seq_len)) if n_nodes is None else n_nodes
        module = MultipleShootingModule(
            f, g, state_dim, num_trajectories=int(data.num_train_trajectories), n_nodes=n_nodes, **options
        )
        checks.check_inputs(module.input_dim, input_dim)
        checks.check_data(module, int(data.seq_len), tuple(data.obs_shape), int(data.num_train_trajectories))
        data.setup("fit")  # the training split's statistics: the model works in the data's units from the start
        module.data_state = data.state_dict()
        self._attach(module)

    def _attach(self, module: MultipleShootingModule, encoder: StateEncoderModule | None = None) -> None:
        self.module, self.encoder = module, encoder
        self.trainer: pl.Trainer | None = None
        self.checkpoint_path: Path | None = None  # the last checkpoint its fit wrote

    @classmethod
    def from_module(cls, module: MultipleShootingModule, encoder: StateEncoderModule | None = None) -> SSM:
        """An ``SSM`` around a ``MultipleShootingModule`` (e.g. one ``cli.py`` trained, loaded from its checkpoint)."""
        if not isinstance(module, MultipleShootingModule):
            raise ValueError(f"from_module takes a MultipleShootingModule, got {type(module).__name__}")
        model = cls.__new__(cls)
        model._attach(module, encoder)
        return model

    # ------------------------------------------------------------------ what it is
    @property
    def f(self) -> nn.Module:
        """The transition, in the model's (normalised) units: :meth:`in_units` gives it in the user's."""
        return self.module.f

    @property
    def g(self) -> nn.Module:
        """The observation model, in the model's (normalised) units."""
        return self.module.g

    @property
    def state_dim(self) -> int:
        return self.module.state_dim

    @property
    def input_dim(self) -> int:
        return self.module.input_dim

    @property
    def units(self) -> Units:
        """The normalisation it was trained with (``units.y_to_user``, ``units.u_to_model``, ...)."""
        return self.module.units

    def in_units(self) -> tuple[nn.Module, nn.Module]:
        """``f`` and ``g`` in the user's units (inputs in, measurements out)."""
        return self.module.in_units()

    def __repr__(self) -> str:
        return (
            f"SSM({type(self.f).__name__}, {type(self.g).__name__}, state_dim={self.state_dim}, "
            f"input_dim={self.input_dim}, n_nodes={self.module.n_nodes}"
            + (", with an encoder" if self.encoder is not None else "")
            + ")"
        )

    # ------------------------------------------------------------------ files
    def save(self, path: str | Path) -> Path:
        """Write the model to ``path`` (a checkpoint ``cli.py`` and :meth:`load` read; its encoder, if any, beside
        it as ``<path stem>_encoder.ckpt``)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        torch.save(_checkpoint_of(self.module), path)
        if self.encoder is not None:
            self.encoder.hparams["ssm_checkpoint"] = str(path)
            torch.save(_checkpoint_of(self.encoder), _encoder_path(path))
        return path

    @classmethod
    def load(cls, path: str | Path) -> SSM:
        """A model from a checkpoint: one written by :meth:`save`, by :func:`fit` or by ``cli.py fit`` (its
        ``last.ckpt``), or a file of ``pretrained/``; with its encoder where ``<stem>_encoder.ckpt`` is beside it."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such checkpoint")
        module = MultipleShootingModule.load_from_checkpoint(path, map_location="cpu", weights_only=False).eval()
        encoder = None
        if _encoder_path(path).is_file():
            encoder = StateEncoderModule.load_from_checkpoint(
                _encoder_path(path), map_location="cpu", weights_only=False, ssm_checkpoint=module
            ).eval()
        return cls.from_module(module, encoder)

    # ------------------------------------------------------------------ states
    def filter(
        self, y: Any, u: Any = None, method: str = "ukf", **options: Any
    ) -> tuple[np.ndarray | torch.Tensor, np.ndarray | torch.Tensor | None]:
        """The latent states of measurements ``y`` (``[T, *obs]`` or a batch ``[B, T, *obs]``, the user's units) under
        inputs ``u`` (``[T, m]`` or ``[T - 1, m]``; a batch ``[B, T, m]``).

        Args:
            method: ``"ukf"`` (an unscented Kalman filter on ``f`` and ``g``: nothing to train), ``"fit"`` (one state
                fitted through ``f`` and ``g`` by the shooting objective, its rollout the states) or ``"encoder"``
                (the CNN-LSTM of :meth:`fit_encoder`).
            **options: the method's settings: UKF (:class:`~ssm_ms.inference.UnscentedKalmanFilter`) ``measurement_var``
                in the user's units, per component or one for all (default: the variance of the model's fit residual
                at the end of training, which holds the measurement noise; 0.5 in normalised units, the paper's, for a
                checkpoint without it), ``process_var`` (default the paper's 1e-6), ``init_var`` (in the state's
                units); fit (:class:`~ssm_ms.inference.OptimisationForecaster`) ``steps``, ``lr``,
                ``n_nodes``, ``start``.

        Returns:
            ``(x, P)``: the states ``[T, d]`` (``[B, T, d]``) and, for the UKF, their covariances ``[T, d, d]``
            (else ``None``).
        """
        y_t, batched, as_numpy = self._measurements(y, "y")
        u_t = self._inputs(u, y_t.shape[0], y_t.shape[1] - 1, "u", batched)
        with torch.no_grad():
            x, covs = self._infer(y_t, u_t, method, options, want_covs=True)
        return as_output(x, batched, as_numpy), (None if covs is None else as_output(covs, batched, as_numpy))

    def _infer(
        self, y: torch.Tensor, u: torch.Tensor | None, method: str, options: Mapping[str, Any], want_covs: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """States ``[B, k, d]`` (and the UKF's covariances) of normalised measurements ``y [B, k, *obs]``
        (:func:`~ssm_ms.inference.simulation.estimate_states`; a UKF ``measurement_var`` given in the user's units)."""
        options = dict(options)
        if method == "ukf" and "measurement_var" in options:
            var = torch.as_tensor(options["measurement_var"], dtype=torch.float64)
            std = self.units.measurement_std(tuple(y.shape[2:]))
            scaled = var / std.pow(2)  # per component: a variance in the user's units over the data's variance
            options["measurement_var"] = scaled.tolist() if scaled.numel() > 1 else float(scaled)
        if method == "encoder" and self.encoder is None:
            raise ValueError("method 'encoder' needs a trained encoder: call model.fit_encoder(data) first")
        states, covs = estimate_states(self.module, y, u, method, options, self.encoder)
        return states, (covs if want_covs else None)

    # ------------------------------------------------------------------ forecasts
    def simulate(
        self,
        u: Any = None,
        *,
        steps: int | None = None,
        y_init: Any = None,
        u_init: Any = None,
        x0: Any = None,
        method: str = "ukf",
        chunk: int = 10_000,
        **options: Any,
    ) -> np.ndarray | torch.Tensor:
        """A free-run simulation: ``f`` iterated under the inputs ``u`` alone, decoded by ``g``, in the user's units.

        Args:
            u: the inputs ``[T, m]`` (a batch ``[B, T, m]``) at the simulated samples' times; the simulation has as
                many samples as ``u`` (an autonomous model: give ``steps`` instead).
            steps: the samples to simulate of an autonomous model.
            y_init, u_init: measurements ``[k, *obs]`` and inputs ``[k, m]`` just before the simulation: its state
                is estimated from them (``method``, ``options``: as :meth:`filter`), and the simulation continues
                from the last one (``u_init[k - 1]`` the transition into the first simulated sample).
            x0: else the latent state of the first simulated sample, ``[d]`` (``[B, d]``); neither: the mean
                shooting node.
            chunk: samples rolled out per call (memory stays bounded on long simulations).

        Returns:
            ``[T, *obs]`` (``[B, T, *obs]``): the simulated measurements (images with their channel axis); several
            sensors: ``{stream: [T, *shape]}``.
        """
        batched, as_numpy = False, isinstance(u, np.ndarray) or u is None
        if u is not None:
            if not self.input_dim:
                raise ValueError("this model is autonomous (its f takes no inputs): give steps, not u")
            u_t, batched, as_numpy = input_tensor(u, self.input_dim, "u")
            steps = u_t.shape[1]
        elif self.input_dim:
            raise ValueError(
                f"this model is driven by {self.input_dim} inputs per step: give u, the inputs to simulate"
            )
        elif steps is None or steps < 1:
            raise ValueError(f"give steps >= 1, the samples to simulate, got {steps}")
        else:
            u_t = None
        if y_init is not None:
            if x0 is not None:
                raise ValueError("give y_init (a state estimated from measurements) or x0, not both")
            y0, init_batched, init_numpy = self._measurements(y_init, "y_init")
            if u is not None and (init_batched != batched or y0.shape[0] != u_t.shape[0]):
                raise ValueError(f"y_init holds {y0.shape[0]} sequences but u holds {u_t.shape[0]}: give one each")
            batched, as_numpy = init_batched, init_numpy if u is None else as_numpy
            k = y0.shape[1]
            ui = self._inputs(u_init, y0.shape[0], k, "u_init", batched)
            with torch.no_grad():
                states, _ = self._infer(y0, None if ui is None else ui[:, : k - 1], method, options)
                last = states[:, -1]
                x = self.f(last) if ui is None else self.f(last, ui[:, k - 1])
        elif u_init is not None:
            raise ValueError("u_init goes with y_init (the samples the state is estimated from): give y_init too")
        elif x0 is not None:
            x = torch.as_tensor(np.asarray(x0) if not isinstance(x0, torch.Tensor) else x0, dtype=torch.float32)
            if x.shape[-1] != self.state_dim or x.ndim > 2:
                raise ValueError(f"x0 must be [d] or [B, d] with d = {self.state_dim}, got {list(x.shape)}")
            batched = batched or x.ndim == 2
            x = x.reshape(-1, self.state_dim)
        else:
            nodes = self.module.training_states()
            x = nodes.mean(0, keepdim=True).expand(1 if u_t is None else u_t.shape[0], -1)
        if u_t is not None and x.shape[0] != u_t.shape[0]:
            raise ValueError(f"{x.shape[0]} initial states for {u_t.shape[0]} input sequences: give one each")
        with torch.no_grad():
            y = self.units.y_to_user(
                self._free_run(x, steps, None if u_t is None else self.units.u_to_model(u_t), chunk)
            )
        if self.streams is not None:  # several sensors: one array per stream
            return {name: as_output(part, batched, as_numpy) for name, part in self._split(y).items()}
        return as_output(y, batched, as_numpy)

    def _split(self, y: torch.Tensor) -> dict[str, torch.Tensor]:
        """Packed measurements ``[B, T, P]`` -> ``{stream: [B, T, *shape]}``."""
        out, start = {}, 0
        for name, shape in self.streams.items():
            size = int(np.prod(shape))
            out[name] = y[..., start : start + size].reshape(*y.shape[:-1], *shape)
            start += size
        return out

    def forecast(self, y: Any, steps: int, u: Any = None, method: str = "ukf", **options: Any):
        """The ``steps`` measurements after ``y`` (``[k, *obs]``, a batch ``[B, k, *obs]``): its state estimated
        (``method``, ``options``: as :meth:`filter`), then :meth:`simulate` on; a driven model takes the inputs ``u``
        of the given samples and of the forecast, ``[k + steps, m]`` (at least ``k + steps - 1``)."""
        if steps < 1:
            raise ValueError(f"steps must be >= 1, got {steps}")
        k = self._measurements(y, "y")[0].shape[1]
        if not self.input_dim:
            return self.simulate(steps=steps, y_init=y, method=method, **options)
        if u is None:
            raise ValueError(f"this model is driven: give u, the inputs of the {k} given and {steps} forecast samples")
        u_t, batched, _ = input_tensor(u, self.input_dim, "u")
        if u_t.shape[1] < k + steps - 1:
            raise ValueError(
                f"u holds {u_t.shape[1]} inputs: a forecast of {steps} samples after {k} needs {k + steps - 1}"
            )
        u_future = u_t[:, k : k + steps]
        if u_future.shape[1] < steps:  # the input after the last sample moves nothing that is returned
            u_future = torch.cat([u_future, u_t[:, -1:].expand(-1, steps - u_future.shape[1], -1)], 1)
        as_numpy = isinstance(u, np.ndarray)
        u_future = u_future.numpy() if as_numpy else u_future
        u_given = u_t[:, :k].numpy() if as_numpy else u_t[:, :k]
        if not batched:
            u_future, u_given = u_future[0], u_given[0]
        return self.simulate(u_future, y_init=y, u_init=u_given, method=method, **options)

    def _free_run(self, x: torch.Tensor, steps: int, u: torch.Tensor | None, chunk: int) -> torch.Tensor:
        """``g`` of ``x`` and of its ``steps - 1`` successors under ``u [B, >= steps - 1, m]`` (model units), rolled
        out ``chunk`` samples at a time (:func:`~ssm_ms.inference.simulation.free_run`); a run that diverges gets a
        warning that says where."""
        y, diverged = free_run(
            self.f, self.g, x, steps, u, chunk, self.module.hparams.decode_chunk, divergence_bound(self.module)
        )
        for b, at in enumerate(diverged.tolist()):
            if at >= 0:
                warnings.warn(
                    f"the simulation{f' of sequence {b}' if len(diverged) > 1 else ''} diverged at sample {at} "
                    "(it left the finite range, or 100 training standard deviations from the data's mean)",
                    stacklevel=3,
                )
        return y

    # ------------------------------------------------------------------ the encoder
    def fit_encoder(self, data: TrajectoryDataModule, epochs: int = 100, **options: Any) -> SSM:
        """Train the CNN-LSTM encoder (:class:`~ssm_ms.inference.StateEncoderModule`: the paper's second stage) on
        the data this model learned, for :meth:`filter` and :meth:`simulate` with ``method="encoder"``.

        ``options``: :func:`fit`'s (``time``, ``name``, ``save_dir``, ...) and the encoder's (``encoder``, ``lr``).
        """
        encoder_keys = {"encoder", "lr", "validate_held_out"}
        encoder_options = {k: options.pop(k) for k in list(options) if k in encoder_keys}
        if "encoder" not in encoder_options and len(self.module.obs_shape()) == 1:
            encoder_options["encoder"] = {"preset": "vector", "hidden": 128}
        encoder = StateEncoderModule(self.module, n_filter=int(data.seq_len), **encoder_options)
        options.setdefault("name", "encoder")
        train(encoder, data, epochs=epochs, **options)
        self.encoder = encoder.eval()
        return self

    # ------------------------------------------------------------------ arrays in, arrays out
    @property
    def streams(self) -> dict[str, tuple[int, ...]] | None:
        """Several sensors: each stream's sample shape, in the order ``g`` packs them (``None``: one sensor)."""
        shapes = getattr(self.g, "shapes", None)
        return {name: tuple(shape) for name, shape in shapes.items()} if shapes else None

    def _measurements(self, y: Any, what: str) -> tuple[torch.Tensor, bool, bool]:
        """``y`` (one sequence or a batch, user's units; several sensors: a dict of streams) -> ``([B, T, *obs]``
        normalised, batched, was numpy)."""
        streams = self.streams
        if streams is not None:
            if not isinstance(y, Mapping) or list(y) != list(streams):
                got = list(y) if isinstance(y, Mapping) else type(y).__name__
                raise ValueError(
                    f"{what}: this model reads the sensors {list(streams)}: give a dict of them, got {got}"
                )
            parts = [
                stream_tensor(y[name], shape, f"{what}['{name}']", missing=i > 0)
                for i, (name, shape) in enumerate(streams.items())
            ]
            if len({(p[0].shape[0], p[0].shape[1], p[1]) for p in parts}) > 1:
                raise ValueError(f"{what}: every stream must hold the same sequences and samples")
            packed = torch.cat([p[0].flatten(2) for p in parts], -1)
            return self.units.y_to_model(packed), parts[0][1], parts[0][2]
        if isinstance(y, Mapping):
            raise ValueError(f"{what}: this model reads one sensor: give its array, not a dict")
        t, batched, as_numpy = stream_tensor(y, tuple(self.module.obs_shape()), what)
        return self.units.y_to_model(t), batched, as_numpy

    def _inputs(self, u: Any, batch: int, needed: int, what: str, batched: bool) -> torch.Tensor | None:
        """Inputs beside measurements: ``[B, >= needed, m]`` normalised (``None`` for an autonomous model)."""
        if not self.input_dim:
            if u is not None:
                raise ValueError(f"this model is autonomous (its f takes no inputs): give no {what}")
            return None
        if u is None:
            raise ValueError(f"this model is driven by {self.input_dim} inputs per step: give {what}")
        t, u_batched, _ = input_tensor(u, self.input_dim, what)
        if u_batched != batched or t.shape[0] != batch:
            raise ValueError(f"{what} must hold one input sequence per measured sequence ({batch}), got {t.shape[0]}")
        if t.shape[1] < needed:
            raise ValueError(f"{what} holds {t.shape[1]} inputs per sequence, the measurements need {needed}")
        return self.units.u_to_model(t)


def _encoder_path(path: Path) -> Path:
    return path.with_name(f"{path.stem}_encoder{path.suffix or '.ckpt'}")


def _checkpoint_of(module: pl.LightningModule) -> dict[str, Any]:
    """What Lightning's checkpoint of ``module`` holds for inference: weights, hyperparameters, the module's own
    additions (its data state, its networks when built in Python)."""
    checkpoint = {
        "state_dict": module.state_dict(),
        "hyper_parameters": dict(module.hparams),
        "pytorch-lightning_version": pl.__version__,
    }
    module.on_save_checkpoint(checkpoint)
    return checkpoint


def fit(model: SSM, data: TrajectoryDataModule, epochs: int | None = None, **options: Any) -> SSM:
    """Train ``model`` on ``data`` by multiple shooting, as ``python cli.py fit`` does.

    The paper's schedule runs (alpha raised and lr / 10 at 20% of the budget, lr / 10 again at 60%: of ``epochs``, or
    of ``time``, whichever runs out first) unless the model has its own (``SSM(..., schedule=ShootingSchedule(...))``). The
    run writes TensorBoard events and ``checkpoints/last.ckpt`` (every epoch) to ``<save_dir>/<name>/version_N/``;
    ``model.checkpoint_path`` names it after the fit, and ``fit(..., ckpt_path=that)`` resumes an interrupted run.
    On a terminal a progress bar, in a log file one line per epoch.

    Args:
        epochs: training epochs; ``time``: a budget (seconds, ``"12min"``, ``"1.5h"``, a ``timedelta``); one of
            them or both (training stops at the first reached).
        **options: ``time``, ``name`` (default ``"ssm"``), ``save_dir`` (``"runs"``), ``callbacks`` (further
            Lightning callbacks), ``ckpt_path``, and other ``lightning.Trainer`` arguments (``accelerator``,
            ``check_val_every_n_epoch``, ``logger=False``, ...).
    """
    if not isinstance(model, SSM):
        raise ValueError(
            f"fit trains an ssm_ms.SSM, got {type(model).__name__}: build one with SSM(data, state_dim=...)"
        )
    if data is None or not isinstance(data, TrajectoryDataModule):
        raise ValueError("fit needs the training data: fit(model, Recordings(y=..., u=...), epochs=...)")
    checks.check_inputs(model.module.input_dim, int(data.input_dim))
    checks.check_data(model.module, int(data.seq_len), tuple(data.obs_shape), int(data.num_train_trajectories))
    model.module.train()
    model.trainer = train(model.module, data, epochs, **options)
    last = getattr(model.trainer.checkpoint_callback, "last_model_path", "")
    model.checkpoint_path = Path(last) if last else None
    model.module.eval()
    return model
