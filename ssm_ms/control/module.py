"""Closed-loop control of a simulated system seen through its camera, with a learned model (``python cli.py test``).

Each test batch is a batch of episodes: the DataModule's test trajectories give their initial states, its
:meth:`environment` the system (the simulator that renders a new noisy frame every period). Every period:

1. the estimate (:mod:`ssm_ms.control.estimators`): the UKF over the learned ``f(x, u)`` and ``g`` moves its belief
   under the torque just applied and corrects it with the new frame, or the trained CNN-LSTM encoder reads the new
   frame and torque (``encoder_checkpoint``); the true model instead reads the simulator's state: the upper bound;
2. the plan: MPPI (:mod:`ssm_ms.control.mppi`) rolls sampled torque sequences out through ``f`` from the estimate
   and scores them with the swing-up cost (:mod:`ssm_ms.control.cost`) on the angle each predicted state shows:
   for a learned model, the angle its decoder draws (:mod:`ssm_ms.control.goals`, distilled into a small network
   once, at setup): its joint-angle head's where ``g`` has one (camera and angle), else the angle of the ink of the
   frame it draws; for the true model, its angle; with ``offset_gain``, on ``f`` corrected
   by its one-step error along the episode so far (offset-free planning);
3. the first torque of the plan is applied for one period.

Scored on the simulator's true angle: an episode succeeds when the pendulum stays within ``tolerance`` of upright
over its last ``success_seconds``. The results file (``results/<experiment>.md``) holds, per controller, the success
rate, the upright error over the final window, and the planning time per control step of one episode alone; a GIF
shows the first episode (the frames seen, what the model believes, the true pendulum).
"""

from __future__ import annotations

import math
import sys
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
import numpy as np
import torch

from ssm_ms.control.cost import SwingUpCost, upright_error
from ssm_ms.control.estimators import ChartUKFEstimator, EncoderEstimator, UKFEstimator, load_encoder
from ssm_ms.control.goals import DistilledFeatures, ink_angle_features
from ssm_ms.control.mppi import MPPISettings, RecedingHorizon, checked_offset_gain
from ssm_ms.control.plant import TruePendulum, angle_of_state
from ssm_ms.control.scoring import episode_stats, first_upright, wilson_interval
from ssm_ms.inference.chart import ChartSettings, StateChart
from ssm_ms.inference.ukf import UnscentedKalmanFilter
from ssm_ms.loading import load_ssm
from ssm_ms.nets.sensors import SensorLayout
from ssm_ms.runtime.machine import describe
from ssm_ms.training.shooting import decode, rollout

CONTROL_HEADING = {
    "title": "Closed-loop control results",
    "intro": "Swing-up and balance of the simple pendulum from its camera frames (ssm_ms/control/module.py); mean ± "
    "std over episodes. `episodes/success`: 1 when the true angle stays within the tolerance of upright over the "
    "final window (the episodes that succeeded, the rate and its 95% Wilson interval); `episodes/upright_error_final`: the mean angle from upright over that window (rad); "
    "`episodes/first_upright_s`: when the angle first stays up for a whole window (episodes that never do are "
    "left out); `planning/ms_per_step`: the planner's time per control step of one episode alone.",
}


@torch.no_grad()
def excited_states(
    f, nodes: torch.Tensor, steps: int, limit: float, frame_dt: float, generator: torch.Generator
) -> torch.Tensor:
    """``[N (steps + 1), d]``: a learned model's states from ``nodes [N, d]`` rolled out ``steps`` steps through
    ``f(x, u)`` under random torques, the data's kind of excitation (correlated over 0.5 s, at half the torque limit's
    scale, clipped to ``limit``): where the planner's angle readout is distilled."""
    white = torch.randn(len(nodes), steps, 1, generator=generator)
    torques = torch.empty_like(white)
    torques[:, 0] = white[:, 0]
    a = math.exp(-frame_dt / 0.5)
    for t in range(1, steps):
        torques[:, t] = a * torques[:, t - 1] + math.sqrt(1 - a * a) * white[:, t]
    torques = (0.5 * limit * torques).clamp(-limit, limit)
    return rollout(f, nodes, steps + 1, torques).reshape(-1, nodes.shape[1])


class ClosedLoop(pl.LightningModule):
    """Swing up and balance a pendulum from its camera frames with a learned SSM, or with the true model (the upper
    bound); see the module doc.

    Args:
        ssm_checkpoint: the driven SSM (``input_dim`` = the chain's joints).
        true_model: plan on the pendulum's true equations with its true state instead (no ``ssm_checkpoint``).
        seconds: length of an episode (control periods: ``seconds / frame_dt``).
        success_seconds, tolerance: an episode succeeds when the angle stays within ``tolerance`` (rad) of upright
            over its last ``success_seconds``.
        planner: :class:`~ssm_ms.control.mppi.MPPISettings` (horizon, samples, iterations, noise_std,
            temperature, u_min, u_max in N m, smoothing).
        offset_gain: offset-free planning (:class:`~ssm_ms.control.mppi.RecedingHorizon`): plan on ``f`` plus a
            running estimate of its one-step error along the episode, the newest error weighed by this gain (0: off;
            1: the last step's error alone).
        cost: the :class:`~ssm_ms.control.cost.SwingUpCost` weights ``w_velocity``, ``w_input``, and its energy
            bound ``max_energy`` (J; e.g. the data's) with its weight ``w_energy``.
        estimator: the UKF's ``process_var``, ``measurement_var`` (``None``: the data's sensor noise, per stream with
            several sensors; ``{stream: variance}``: those streams' given, the others' their noise), ``init_var`` (``None``: the spread of the SSM's shooting nodes) and ``iterations``
            (measurement updates per frame: :class:`~ssm_ms.inference.UnscentedKalmanFilter`'s), and ``chart``
            (``None``: the UKF over the whole state; ``{dims: k, ...}``, :class:`~ssm_ms.inference.chart.ChartSettings`:
            over the code of a ``k``-dimensional chart of the model's states, fitted at set-up on the states the angle
            readout is distilled on, so that the estimate stays among them; ``process_var`` and ``init_var`` are
            then in the code's standardised units); not used with ``encoder_checkpoint``.
        encoder_checkpoint: estimate the state with this CNN-LSTM encoder (the forecasting stage's, trained on
            ``ssm_checkpoint``'s latent trajectories) instead of the UKF.
        distill: settings of the distilled angle readout: ``rollout_steps`` (states per node under random torques),
            ``steps`` (fitting steps), ``pivot`` (``[x, y]`` in pixels; default: the frame's centre).
        timing_steps: control steps of one episode alone whose planning time is reported.
        exploration: standard deviation (N m) of Gaussian noise added to every planned torque before it is applied
            (clipped to the planner's bounds; default 0): exploration, for episodes recorded as training data.
        record: write the episodes to this ``.npz`` file, as training data of the pendulum data module
            (``recorded``, docs/control.md "Identification in closed loop"): the noisy frames seen, the clean ones,
            the true states and the torques applied, one row per period, and the system's parameters.
        experiment, results_dir, figures_dir, method_name: where the results go and the row's name
            (``{estimator}`` in it names the estimator: ``UKF`` or ``CNN-LSTM encoder``; ``results_dir`` unset: the
            run's own folder, the trainer's ``log_dir``; ``figures_dir`` unset: no figures, else a GIF of the first
            episode and the angle from upright along every episode).
        seed: the episodes' camera noise and the planner's sampling.
    """

    def __init__(
        self,
        ssm_checkpoint: str | None = None,
        *,
        true_model: bool = False,
        encoder_checkpoint: str | None = None,
        seconds: float = 10.0,
        success_seconds: float = 2.0,
        tolerance: float = 0.3,
        planner: dict[str, Any] | None = None,
        offset_gain: float = 0.0,
        cost: dict[str, Any] | None = None,
        estimator: dict[str, Any] | None = None,
        distill: dict[str, Any] | None = None,
        timing_steps: int = 20,
        exploration: float = 0.0,
        record: str | None = None,
        experiment: str = "pendulum_control",
        results_dir: str | None = None,
        figures_dir: str | None = None,
        method_name: str | None = None,
        seed: int = 0,
    ):
        super().__init__()
        self.settings = MPPISettings(**(planner or {}))
        self.cost_weights = dict(cost or {})
        self.estimator_settings = {
            "process_var": 1e-4, "measurement_var": None, "init_var": None, "iterations": 1, "chart": None,
            **(estimator or {}),
        }  # fmt: skip
        unknown = set(self.estimator_settings) - {"process_var", "measurement_var", "init_var", "iterations", "chart"}
        if unknown:
            raise ValueError(
                f"estimator takes process_var, measurement_var, init_var, iterations and chart, got {sorted(unknown)}"
            )
        self.distill_settings = {"rollout_steps": 25, "steps": 2000, "pivot": None, **(distill or {})}
        if not (seconds > 0 and 0 < success_seconds <= seconds and tolerance > 0 and timing_steps >= 1):
            raise ValueError(
                f"need seconds > 0, 0 < success_seconds <= seconds, tolerance > 0 and timing_steps >= 1, got "
                f"{seconds}, {success_seconds}, {tolerance}, {timing_steps}"
            )
        self.seconds, self.success_seconds, self.tolerance = float(seconds), float(success_seconds), float(tolerance)
        self.timing_steps, self.seed = int(timing_steps), int(seed)
        if not exploration >= 0:
            raise ValueError(f"exploration is a standard deviation of torque noise (N m): >= 0, got {exploration}")
        self.exploration, self.record = float(exploration), record
        self.offset_gain = checked_offset_gain(offset_gain)
        self.experiment, self.results_dir, self.figures_dir = experiment, results_dir, figures_dir
        self.ssm_checkpoint = ssm_checkpoint
        self.ssm = None
        if (ssm_checkpoint is None) != bool(true_model):
            raise ValueError(
                "give model.init_args.ssm_checkpoint (the driven SSM to plan on) or model.init_args.true_model: true "
                "(the true equations and state), not both or neither"
            )
        if ssm_checkpoint is not None:
            self.ssm, _ = load_ssm(ssm_checkpoint)
            if not self.ssm.input_dim:
                raise ValueError(
                    f"{ssm_checkpoint} is an autonomous SSM (f takes no inputs): control needs a model of the driven "
                    "system, trained on data with inputs (e.g. configs/pendulum_torque.yaml)"
                )
        if encoder_checkpoint is not None and self.ssm is None:
            raise ValueError("encoder_checkpoint estimates a learned SSM's state: give ssm_checkpoint too")
        self.encoder_checkpoint = encoder_checkpoint
        self.encoder = (
            None if encoder_checkpoint is None else load_encoder(encoder_checkpoint, ssm_checkpoint, self.ssm)
        )
        chart = self.estimator_settings["chart"]
        self.chart_settings = None
        if chart is not None and self.ssm is not None and self.encoder is None:
            self.chart_settings = ChartSettings.parse(chart, self.ssm.state_dim)
        self.estimator_name = "CNN-LSTM encoder" if self.encoder is not None else "UKF"
        if self.chart_settings is not None:
            self.estimator_name += f" on a {self.chart_settings.dims}-dimensional chart"
        name = method_name or ("true model, true state" if self.ssm is None else "SSM + {estimator}")
        self.method_name = name.replace("{estimator}", self.estimator_name)
        self._episodes: list[dict[str, torch.Tensor]] = []

    # ------------------------------------------------------------------ set-up
    def setup(self, stage: str) -> None:
        self.attach(self.trainer.datamodule)

    def attach(self, dm) -> None:
        """Set up on the data module ``dm`` (its simulator, normalisations and sensors; the learned model's estimator
        and angle readout): what ``setup`` does under a Trainer, callable without one (e.g. a benchmark running
        :meth:`controller` on episodes of its own)."""
        if not hasattr(dm, "environment"):
            raise ValueError(f"{type(dm).__name__} has no environment(): closed-loop control needs a simulated system")
        if self.ssm is not None and self.ssm.data_state is not None:
            dm.load_state_dict(self.ssm.data_state)  # the SSM's normalisations of frames and inputs
        self.env = dm.environment(self.seed)
        self.frame_dt = self.env.frame_dt
        n_links = self.env.params["n_links"]
        if n_links != 1:
            raise ValueError(f"the swing-up task is the simple pendulum's: the data have {n_links} links")
        layout = SensorLayout.from_state_dict(dm.sensor_layout) if dm.sensor_layout else None
        sensors = list(getattr(dm, "sensors", ["image"]))
        if self.record and sensors != ["image"]:
            raise ValueError(f"record writes camera data: the data's sensors are {sensors}, record needs [image]")
        self.streams = layout.split if layout is not None else (lambda y: {sensors[0]: y})
        if self.ssm is None:
            self.f, self.features = TruePendulum(self.frame_dt, self.env.params["damping"]), angle_of_state
            return
        if self.ssm.input_dim != n_links:
            raise ValueError(f"the SSM takes {self.ssm.input_dim} inputs per step, the pendulum has {n_links} joints")
        frames_norm, inputs_norm = dm.normalizer, dm.input_normalizer
        self.to_frames = (lambda y: y) if frames_norm is None else frames_norm.normalize
        self.from_frames = (lambda y: y) if frames_norm is None else frames_norm.denormalize
        self.to_inputs = to_inputs = (lambda u: u) if inputs_norm is None else inputs_norm.normalize
        ssm_f = self.ssm.f
        self.f = lambda x, u: ssm_f(x, to_inputs(u))  # the planner and the filter think in N m
        nodes = self.ssm.training_states()
        self.prior = nodes.mean(0)
        states = self.visited_states(nodes)
        if self.encoder is None:  # the UKF's settings: only where it estimates
            est = self.estimator_settings
            f, g, state_dim = self.f, self.ssm.g, self.ssm.state_dim
            if self.chart_settings is not None:  # the filter over the chart's code
                self.chart = chart = StateChart.fit(states, self.chart_settings, seed=self.seed)
                (f, g), state_dim = chart.pulled_back(f, g), chart.dims
                nodes = chart.encode(nodes)
            init_var = est["init_var"] if est["init_var"] is not None else nodes.var(0).clamp_min(1e-6).tolist()
            measurement_var = est["measurement_var"]
            if isinstance(measurement_var, dict):  # several sensors: a variance per stream (the others: their noise)
                if layout is None:
                    raise ValueError(
                        f"estimator measurement_var names streams {sorted(measurement_var)} but the data have one "
                        "sensor: give one variance"
                    )
                measurement_var = layout.variances(measurement_var).tolist()
            elif measurement_var is None:  # the sensors' own noise (several sensors: each stream's)
                measurement_var = layout.variances().tolist() if layout is not None else float(dm.noise_std) ** 2
                if sensors == ["angle"]:
                    measurement_var = float(dm.angle_noise_std) ** 2
            self.ukf = UnscentedKalmanFilter(
                f,
                g,
                process_var=est["process_var"],
                measurement_var=measurement_var,
                init_var=init_var,
                iterations=est["iterations"],
                state_dim=state_dim,
            )
        self.features, self.distill_error = self._distill(states)

    def estimator(self) -> UKFEstimator | EncoderEstimator:
        """A fresh estimator of the learned SSM's state (:mod:`ssm_ms.control.estimators`) for a batch of episodes."""
        if self.encoder is not None:
            return EncoderEstimator(self.encoder, self.to_frames, self.to_inputs)
        if self.chart_settings is not None:
            return ChartUKFEstimator(self.ukf, self.chart, self.to_frames)
        return UKFEstimator(self.ukf, self.prior, self.to_frames)

    def visited_states(self, nodes: torch.Tensor) -> torch.Tensor:
        """The learned model's own states: every shooting node rolled out ``distill.rollout_steps`` steps under random
        torques (the data's kind of excitation), where the angle readout is distilled and the UKF's chart fitted."""
        limit = max(abs(self.settings.u_min), abs(self.settings.u_max))
        generator = torch.Generator().manual_seed(self.seed)
        steps = int(self.distill_settings["rollout_steps"])
        return excited_states(self.f, nodes, steps, limit, self.frame_dt, generator)

    def _distill(self, states: torch.Tensor) -> tuple[DistilledFeatures, float]:
        """The angle the decoder draws (its angle head's where it has one: a direct reading, where the ink's centroid
        in a 24x24 frame is a coarse one), learned as a function of the state on ``states`` (:meth:`visited_states`)."""
        steps = int(self.distill_settings["steps"])
        return DistilledFeatures.fit(states, self.drawn_angle, steps=steps, seed=self.seed)

    @torch.no_grad()
    def drawn_angle(self, x: torch.Tensor) -> torch.Tensor:
        """``(sin, cos)`` ``[N, 2]`` of the angle ``g`` draws from states ``x [N, d]``: its angle head's reading where it
        has one, else the angle of the ink of the frame it draws (what the readout is distilled from)."""
        parts = self.streams(self.from_frames(decode(self.ssm.g, x, 4096)))
        if "angle" in parts:  # the (sin, cos) of the joint's angle, as g's angle head draws it
            reading = parts["angle"][:, :: parts["angle"].shape[1] // 2]
            return reading / reading.norm(dim=1, keepdim=True).clamp_min(1e-6)
        return self.ink_angle(parts["image"])

    def ink_angle(self, frames: torch.Tensor) -> torch.Tensor:
        """``(sin, cos)`` ``[N, 2]`` of the angle of the ink of frames ``[N, 1, H, W]`` about the pivot (``distill``'s
        ``pivot``, else the frame's centre): what the planner's angle readout is distilled from."""
        pivot = self.distill_settings["pivot"]
        pivot = tuple(pivot) if pivot is not None else (frames.shape[-1] / 2, frames.shape[-2] / 2)
        return ink_angle_features(frames, pivot)

    # ------------------------------------------------------------------ episodes
    def controller(self, batch: int) -> RecedingHorizon:
        """A fresh receding-horizon controller for ``batch`` episodes at once: ``controller(x) -> u`` plans on this
        loop's model (the learned ``f`` and its angle readout, or the true pendulum) from states ``x [batch, d]``."""
        cost = SwingUpCost(self.features, self.frame_dt, **self.cost_weights)
        return RecedingHorizon(self.f, cost, self.settings, batch, 1, seed=self.seed, offset_gain=self.offset_gain)

    @torch.no_grad()
    def episodes(self, start: np.ndarray, batch_idx: int = 0, pictures: bool = False) -> dict[str, Any]:
        """Episodes from the true initial states ``start [B, 2 n]`` (angles, then velocities), each period estimate,
        plan and act (the module doc): the loop of :meth:`test_step`, for scripts that run episodes of their own.

        Returns ``states [B, T+1, 2 n]`` (the simulator's), ``inputs [B, T, m]`` (as applied, exploration included)
        and ``measurements``, the ``T + 1`` measurements ``[B, ...]`` as the sensors gave them; with ``pictures``,
        ``seen``, ``truth`` and ``believed`` ``[B, T+1, 1, H, W]``: the camera's frames, their clean twins and the
        frames ``g`` draws from each estimate (``None`` without a camera, or for the true model).
        """
        n = self.env.params["n_links"]
        periods = int(round(self.seconds / self.frame_dt))
        y = torch.from_numpy(self.env.reset(start[:, :n], start[:, n:]))
        controller = self.controller(len(start))
        noise = torch.Generator().manual_seed(self.seed + 1 + batch_idx)
        estimator = self.estimator() if self.ssm is not None else None
        mean = estimator.start(y) if estimator is not None else None
        measurements, states, inputs, truth, believed = [y], [torch.from_numpy(self.env.state).float()], [], [], []

        def picture() -> None:
            if pictures:
                truth.append(torch.from_numpy(self.env.clean_frames()))
                if mean is not None:
                    believed.append(self.camera(self.from_frames(decode(self.ssm.g, mean))))

        picture()
        for _ in range(periods):
            u = controller(states[-1] if mean is None else mean, applied=inputs[-1] if inputs else None)
            if self.exploration:
                u = u + self.exploration * torch.randn(u.shape, generator=noise, dtype=u.dtype)
                u = u.clamp(self.settings.u_min, self.settings.u_max)
            y = torch.from_numpy(self.env.step(u.double().numpy()))
            if estimator is not None:
                mean = estimator.next(u, y)
            measurements.append(y)
            states.append(torch.from_numpy(self.env.state).float())
            inputs.append(u.float())
            picture()
        run = {"states": torch.stack(states, 1), "inputs": torch.stack(inputs, 1), "measurements": measurements}
        if pictures:
            seen = [self.camera(m) for m in measurements]
            run["seen"] = torch.stack(seen, 1) if seen[0] is not None else None
            run["truth"] = torch.stack(truth, 1)
            run["believed"] = torch.stack(believed, 1) if believed and believed[0] is not None else None
        return run

    def test_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> None:
        run = self.episodes(batch["state"][:, 0].double().cpu().numpy(), batch_idx, pictures=True)
        del run["measurements"]  # kept as the pictures
        self._episodes.append(run)

    def judge(self, angles: torch.Tensor) -> tuple[torch.Tensor, int, torch.Tensor, torch.Tensor]:
        """Episodes' true angles ``[E, T+1]`` (0 hanging) judged by the task: the distance from upright ``[E, T+1]``,
        the final window's length in periods, that window's distances ``[E, window]`` and success ``[E]`` (within
        ``tolerance`` of upright over the whole window)."""
        error = upright_error(angles.double())
        window = int(round(self.success_seconds / self.frame_dt))
        final = error[:, -window:]
        return error, window, final, (final < self.tolerance).all(dim=1)

    def camera(self, measurement: torch.Tensor) -> torch.Tensor | None:
        """The camera's part of a measurement (``None`` without a camera), for the pictures."""
        return self.streams(measurement).get("image")

    @torch.no_grad()
    def planning_seconds(self) -> list[float]:
        """Seconds of planning per control step of one episode alone (hanging at rest), ``timing_steps`` steps."""
        controller = self.controller(1)
        x = self.prior[None].clone() if self.ssm is not None else torch.zeros(1, 2)
        times = []
        for _ in range(self.timing_steps):
            tick = time.perf_counter()
            u = controller(x)
            times.append(time.perf_counter() - tick)
            x = self.f(x, u)
        return times

    # ------------------------------------------------------------------ results
    def on_test_epoch_end(self) -> None:
        from ssm_ms.forecasting.results import results_folder, write_results

        runs = self._episodes
        states = torch.cat([r["states"] for r in runs])  # [E, T+1, 2]
        error, window, final, success = self.judge(states[..., 0])
        success = success.double()
        times = torch.tensor(self.planning_seconds(), dtype=torch.float64) * 1000
        summary = {
            f"{self.method_name}/episodes/success": {
                **episode_stats(success),
                "ci95": list(wilson_interval(int(success.sum()), len(success))),
            },
            f"{self.method_name}/episodes/upright_error_final": episode_stats(final.mean(1)),
            f"{self.method_name}/episodes/first_upright_s": episode_stats(
                first_upright(error, self.tolerance, window) * self.frame_dt
            ),
            f"{self.method_name}/planning/ms_per_step": episode_stats(times),
        }
        info = {
            "experiment": self.experiment,
            "method": self.method_name,
            "model": "true model" if self.ssm is None else type(self.ssm.f).__name__,
            "inference": None if self.ssm is None else "encoder" if self.encoder is not None else "ukf",
            "label": self.method_name,
            "ssm_checkpoint": self.ssm_checkpoint,
            "command": " ".join(sys.argv),
            "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "machine": describe(),
            "test_sequences": len(success),
            "inference_settings": self._settings_line(),
        }
        if self.trainer.is_global_zero:
            write_results(results_folder(self.results_dir, self.trainer), info, summary, heading=CONTROL_HEADING)
            self._figures(runs[0], error)
            if self.record:
                self._record(runs)
        self.log_dict(
            {"control/success_rate": success.mean().item(), "control/ms_per_step": times.mean().item()},
            rank_zero_only=True,
        )
        self._episodes = []

    def _record(self, runs: list[dict[str, torch.Tensor]]) -> None:
        """Write the episodes as training data (``record``): per period the frame seen, its clean twin, the true
        state and the torque applied (the last frame, after the last torque, left out), uint8 frames as the data's."""
        import json

        def cat(key: str) -> np.ndarray:
            return torch.cat([r[key] for r in runs]).numpy()

        def pixels(frames: np.ndarray) -> np.ndarray:
            return np.rint(frames[:, :-1] * 255.0).clip(0, 255).astype(np.uint8)

        path = Path(self.record)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp.npz")
        u = cat("inputs").astype(np.float32)
        np.savez(
            tmp,
            y=pixels(cat("seen")),
            y_clean=pixels(cat("truth")),
            state=cat("states")[:, :-1].astype(np.float32),
            u=u,
            params=np.array(json.dumps(self.env.params, sort_keys=True, default=str)),
        )
        tmp.replace(path)
        print(f"recorded {len(u)} episodes to {path}", file=sys.stderr)

    def _settings_line(self) -> str:
        s = self.settings
        line = (
            f"MPPI: horizon {s.horizon}, {s.samples} samples, {s.iterations} iterations, noise {s.noise_std} N m, "
            f"temperature {s.temperature}, torque within [{s.u_min}, {s.u_max}] N m; episodes of {self.seconds} s, "
            f"success: within {self.tolerance} rad of upright over the last {self.success_seconds} s"
        )
        if self.offset_gain:
            line += f"; offset-free planning, gain {self.offset_gain}"
        if self.exploration:
            line += f"; exploration: N(0, {self.exploration}^2) N m added to every planned torque"
        if self.cost_weights.get("max_energy") is not None:
            line += f"; cost {self.cost_weights}"
        if self.ssm is not None:
            estimator = (
                f"UKF {self.estimator_settings}" if self.encoder is None else f"encoder {self.encoder_checkpoint}"
            )
            if self.chart_settings is not None:
                estimator += f" (the chart's held-out reconstruction MSE {self.chart.held_error:.2g}, standardised)"
            line += f"; {estimator}; angle readout distilled from g (held-out MSE {self.distill_error:.2g})"

        return line

    def _figures(self, run: dict[str, torch.Tensor], error: torch.Tensor) -> None:
        if not self.figures_dir:
            return
        from ssm_ms import drawing

        name = f"{self.experiment}_{self.method_name.replace(' ', '_').replace(',', '').replace('+', 'and')}"
        panels = {"camera (seen)": run["seen"][0]} if run["seen"] is not None else {}
        if run["believed"] is not None:
            panels["model's belief g(x)"] = run["believed"][0].clamp(0, 1)
        panels["true pendulum"] = run["truth"][0]
        torques = run["inputs"][0, :, 0].tolist() + [float("nan")]
        notes = [[f"u = {u:+.2f} N m" if math.isfinite(u) else "", ""] for u in torques]
        drawing.save_panel_gif(panels, Path(self.figures_dir) / f"{name}.gif", notes, fps=1 / self.frame_dt)
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(7, 3.2))
        t = np.arange(error.shape[1]) * self.frame_dt
        for row in error:
            ax.plot(t, row.numpy(), lw=0.8, alpha=0.7)
        ax.axhline(self.tolerance, color="k", ls="--", lw=0.8)
        ax.axvspan(self.seconds - self.success_seconds, self.seconds, color="0.9")
        ax.set(
            xlabel="time (s)",
            ylabel="angle from upright (rad)",
            ylim=(0, math.pi),
            title=f"{self.method_name}: {len(error)} episodes",
        )
        fig.tight_layout()
        drawing.save_figure(fig, Path(self.figures_dir) / f"{name}_angles.png")
        plt.close(fig)
