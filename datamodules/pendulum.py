"""The n-link planar pendulum of the paper as a data set: :class:`PendulumDataModule`, noisy images (or joint
encoder readings) of simulated trajectories, free or driven by torques.

Its parts, one job each:

- :mod:`datamodules.pendulum_sim`: the system, its Pinocchio model, RK4 integration (the choice of ``dt``) and energy;
- :mod:`datamodules.pendulum_render`: the two renderings (``"paper"``, ``"analytic"``), the pixel noise, the
  joint encoders' reading;
- :mod:`datamodules.pendulum_excitation`: the torques: the random excitation, the swing-up controller, the data's
  torques in feedback;
- :mod:`datamodules.pendulum_generation`: trajectories generated in chunks by a pool of processes, their random
  streams;
- :mod:`datamodules.pendulum_env`: the pendulum as a system to control, and the episodes recorded on it.
"""

from __future__ import annotations

import math
import os
from typing import TYPE_CHECKING, Any

import numpy as np
from tqdm.auto import tqdm

from datamodules.base import TrajectoryDataModule
from datamodules.pendulum_env import PendulumEnvironment, file_digest, read_recorded
from datamodules.pendulum_excitation import SWING_UP, data_policy, torques_of
from datamodules.pendulum_generation import available_cores, chunk_tasks, initial_states, run_tasks
from datamodules.pendulum_render import RENDERINGS, chain_length_pixels, default_line_width, quantize, render
from datamodules.pendulum_sim import GRAVITY, pendulum_model, simulate

if TYPE_CHECKING:
    import torch

SPLIT_IDS = {"train": 0, "test": 1}
GENERATOR_VERSION = 2  # bump when the generated arrays change for the same parameters


class PendulumDataModule(TrajectoryDataModule):
    """Noisy images of an n-link pendulum (defaults: the paper's simple pendulum).

    Batches: ``"y"`` and ``"y_clean"`` float ``[B, 100, 1, H, W]`` in [0, 1] (stored as uint8),
    ``"state"`` float32 ``[B, 100, 2 * n_links]``: joint angles (relative, not wrapped) then joint
    velocities at every frame. The quadruple pendulum of the paper is ``n_links=4, image_size=48,
    n_train=2000, n_test=2000, damping=0.1, max_velocity=0.0``. With ``torque_limit > 0`` the chain is driven:
    batches also hold ``"u"`` float32 ``[B, 100, n_links]``, the joint torques (N m) applied from each frame to
    the next (:func:`~datamodules.pendulum_excitation.excitation`), cached beside the images; a model learns
    ``x[t+1] = f(x[t], u[t])``.

    Args:
        n_links: number of links (>= 1).
        image_size: image height and width in pixels.
        n_train, n_test: trajectories per split.
        damping: viscous joint damping (``tau = -damping * theta_dot``).
        max_angle: initial joint angles ~ U[-max_angle, max_angle] (each joint).
        max_velocity: initial joint velocities ~ U[-max_velocity, max_velocity].
        duration: simulated time per trajectory (s); frames at ``0, frame_dt, ..., duration - frame_dt``.
        frame_dt: time between frames (s); a multiple of ``dt``.
        noise_std: std of the Gaussian pixel noise (added, then clipped to [0, 1]).
        dt: RK4 integrator step (s); its accuracy: :mod:`datamodules.pendulum_sim`.
        rendering: ``"paper"`` (the paper generator's images) or ``"analytic"`` (round-capped lines, shorter
            chain): see :mod:`datamodules.pendulum_render`.
        line_width: thickness of the drawn links, in pixels (default: the rendering's, 1/16 of the image for
            ``"paper"``, 2 for ``"analytic"``).
        seed: seed of the generator (and of the training-set shuffling).
        workers: processes generating trajectories in parallel (default: the available cores).
        torque_limit: the largest joint torque of the excitation, in N m (0, the default: a free chain, the
            paper's). One unit mass on a unit link weighs 9.81 N m against gravity at the horizontal: a limit of
            3 lifts it to about 18 degrees, and anything higher takes pumping energy.
            The correlated excitation does pump: the default data's pendulum turns over, its angle reaching
            137 rad within 10 s.
        torque_correlation: correlation time of the excitation, in seconds (default 0.5 s: five frames).
        max_energy: an energy bound on the excitation, J above hanging at rest
            (:func:`~datamodules.pendulum_sim.chain_energy`; the simple pendulum upright at rest has
            ``2 g = 19.62``): above it, a torque that would add energy is not applied that frame
            (:func:`~datamodules.pendulum_sim.simulate`), so the data cover the speeds that reach upright without
            spinning far beyond them. ``None`` (the default): no bound.
        closed_loop_share: the share of trajectories identified in closed loop (simple pendulum only; default 0,
            none): a classic controller (:func:`~datamodules.pendulum_excitation.swing_up_balance`) swings them up
            and holds them upright, with ``closed_loop_noise`` times their excitation added for exploration, so the
            data show the pendulum caught and held upright, which random torques within a low limit almost never
            do. Which trajectories: :func:`~datamodules.pendulum_excitation.closed_loop`, by index.
        closed_loop_noise: the share of the excitation added to the controller's torque (default 0.5: a standard
            deviation of ``torque_limit / 4``).
        closed_loop_override: in the closed-loop share, the frames whose excitation exceeds this share of the
            torque limit get the excitation alone, the controller off (default ``None``: never): open-loop pushes at
            the states the controller holds, where its own torque is tied to the state and cannot show what a
            torque does (studies/torque_authority).
        closed_loop_balance: whether the closed-loop share's controller holds the pendulum upright (default true);
            false: it only pumps energy, and within its catch of upright the excitation alone drives the pendulum,
            which falls and is swung up again (no torque near upright depends on the state).
        sensors: what measures the chain, packed per step in this order: ``["image"]`` (the default, the camera),
            ``["angle"]`` (the joint encoders alone) or both. The encoders report
            :func:`~datamodules.pendulum_render.angle_reading` of the noised angles, ``[sin q, cos q]``
            (``2 n_links`` values per step).
        angle_noise_std: std of the encoders' Gaussian noise on each angle (rad), before the sine and cosine.
        angle_every: the encoders sample every ``angle_every`` frames (NaN between).
        recorded: ``.npz`` files of episodes recorded on this system (the closed loop's ``record``: a learned
            controller's episodes, for identification in closed loop, docs/control.md), appended to the training
            split after the ``n_train`` generated trajectories, in order. Camera data only; each file's system
            (:data:`~datamodules.pendulum_env.RECORDED_SYSTEM`) and length must be the data's. The cache key holds
            each file's hash.
        **kwargs: the :class:`~datamodules.base.TrajectoryDataModule` arguments (``data_dir``,
            ``batch_size``, ``eval_batch_size``, ``num_workers``, ``val_trajectories``, ``normalize``,
            ``shuffle``).
    """

    name = "pendulum"
    split_params = {"train": ("n_train", "recorded"), "test": ("n_test",)}

    def __init__(
        self,
        n_links: int = 1,
        image_size: int = 24,
        n_train: int = 1000,
        n_test: int = 1000,
        damping: float = 0.0,
        max_angle: float = math.pi,
        max_velocity: float = 1.0,
        duration: float = 10.0,
        frame_dt: float = 0.1,
        noise_std: float = 0.2,
        dt: float = 5e-3,
        rendering: str = "paper",
        line_width: float | None = None,
        seed: int = 0,
        workers: int | None = None,
        torque_limit: float = 0.0,
        torque_correlation: float = 0.5,
        max_energy: float | None = None,
        closed_loop_share: float = 0.0,
        closed_loop_noise: float = 0.5,
        closed_loop_override: float | None = None,
        closed_loop_balance: bool = True,
        sensors: list[str] | None = None,
        angle_noise_std: float = 0.05,
        angle_every: int = 1,
        recorded: list[str] | None = None,
        **kwargs: Any,
    ):
        super().__init__(seed=seed, **kwargs)
        self.recorded = [str(r) for r in recorded or []]
        self._recorded_info: list[dict[str, Any]] | None = None
        self.torque_limit, self.torque_correlation = float(torque_limit), float(torque_correlation)
        self.max_energy = None if max_energy is None else float(max_energy)
        self.closed_loop_share, self.closed_loop_noise = float(closed_loop_share), float(closed_loop_noise)
        self.closed_loop_override = None if closed_loop_override is None else float(closed_loop_override)
        self.closed_loop_balance = bool(closed_loop_balance)
        self.sensors = list(sensors or ["image"])
        self.angle_noise_std, self.angle_every = float(angle_noise_std), int(angle_every)
        self.n_links = int(n_links)
        self.image_size = int(image_size)
        self.n_train, self.n_test = int(n_train), int(n_test)
        self.damping = float(damping)
        self.max_angle, self.max_velocity = float(max_angle), float(max_velocity)
        self.duration, self.frame_dt, self.dt = float(duration), float(frame_dt), float(dt)
        self.noise_std = float(noise_std)
        self.rendering = str(rendering)
        if self.rendering not in RENDERINGS:
            raise ValueError(f"rendering must be one of {list(RENDERINGS)}, got {rendering!r}")
        self.line_width = (
            default_line_width(self.rendering, self.image_size) if line_width is None else float(line_width)
        )
        self.workers = available_cores() if workers is None else int(workers)
        check_arguments(self)

    # ------------------------------------------------------------------ TrajectoryDataModule
    @property
    def num_train_trajectories(self) -> int:
        return self.n_train + sum(r["episodes"] for r in self.recorded_info())

    def recorded_info(self) -> list[dict[str, Any]]:
        """Per ``recorded`` file (checked once, on first use): its name, hash and number of episodes."""
        if self._recorded_info is None:
            params = self.system_params()
            self._recorded_info = [
                {"file": os.path.basename(path), "sha1": file_digest(path), "episodes": len(arrays["u"])}
                for path in self.recorded
                for arrays in [read_recorded(path, params, self.n_frames)]
            ]
        return self._recorded_info

    def system_params(self) -> dict[str, Any]:
        """The generator parameters without the recorded files (what a recorded file is checked against)."""
        return self.generator_params(with_recorded=False)

    @property
    def n_frames(self) -> int:
        return int(round(self.duration / self.frame_dt))

    def generator_params(self, with_recorded: bool = True) -> dict[str, Any]:
        return {
            "version": GENERATOR_VERSION,
            "n_links": self.n_links,
            "image_size": self.image_size,
            "n_train": self.n_train,
            "n_test": self.n_test,
            "damping": self.damping,
            "max_angle": self.max_angle,
            "max_velocity": self.max_velocity,
            "duration": self.duration,
            "frame_dt": self.frame_dt,
            "noise_std": self.noise_std,
            "dt": self.dt,
            "rendering": self.rendering,
            "line_width": self.line_width,
            "gravity": GRAVITY,
            "seed": self.seed,
            # a driven chain only: a free chain's parameters (and cache, and checkpoints' records) stay as they were
            **(
                {"torque_limit": self.torque_limit, "torque_correlation": self.torque_correlation}
                if self.torque_limit
                else {}
            ),
            **({"max_energy": self.max_energy} if self.max_energy is not None else {}),
            **(
                {
                    "closed_loop_share": self.closed_loop_share,
                    "closed_loop_noise": self.closed_loop_noise,
                    "closed_loop_gains": dict(SWING_UP),
                    **(
                        {"closed_loop_override": self.closed_loop_override}
                        if self.closed_loop_override is not None
                        else {}
                    ),
                    **({} if self.closed_loop_balance else {"closed_loop_balance": False}),
                }
                if self.closed_loop_share
                else {}
            ),
            # other sensors than the camera only: the camera's data stay as they were
            **(
                {
                    "sensors": self.sensors,
                    "angle_noise_std": self.angle_noise_std,
                    "angle_every": self.angle_every,
                    "angle_reading": "sin_cos",
                }
                if self.sensors != ["image"]
                else {}
            ),
            **({"recorded": self.recorded_info()} if self.recorded and with_recorded else {}),
        }

    @property
    def sample_period(self) -> float:
        """Seconds between frames."""
        return self.frame_dt

    @property
    def known_largest_exponent(self) -> float | None:
        """0 for the undamped simple pendulum (integrable: no exponential divergence); unknown otherwise."""
        return 0.0 if self.n_links == 1 and self.damping == 0.0 else None

    def true_measurements(self, split: str, index, n_frames: int) -> torch.Tensor:
        """Noiseless frames ``[len(index), n_frames, 1, H, W]`` in [0, 1] of trajectories ``index`` of a split,
        simulated from their exact initial states for ``n_frames`` frames (any horizon, e.g. beyond the data's)."""
        import torch

        if split not in SPLIT_IDS:
            raise ValueError(f"unknown split {split!r}: the pendulum data set has splits {sorted(SPLIT_IDS)}")
        params = self.generator_params()
        if split == "train" and max(index, default=-1) >= self.n_train:
            raise ValueError(
                f"training trajectories from {self.n_train} on are recorded episodes: their continuation cannot be "
                "simulated"
            )
        rngs, q0, v0 = initial_states(params, SPLIT_IDS[split], index)
        u = torques_of(params, rngs, int(n_frames))  # the same torques as the data's (and feedback), continued
        model = pendulum_model(self.n_links)
        steps = int(round(self.frame_dt / self.dt))
        policy = data_policy(params, index) if u is not None else None
        q, _, _ = simulate(model, model.createData(), q0, v0, int(n_frames), steps, self.dt, self.damping, u, policy)
        frames = np.stack(
            [quantize(render(q[j], self.image_size, self.line_width, self.rendering)) for j in range(len(q))]
        )
        return torch.from_numpy(frames).float().div_(255.0)

    @property
    def sensor_layout(self) -> list[dict[str, Any]] | None:
        """Camera and joint encoders together: the image (pixel noise ``noise_std``) and the angles (noise
        ``angle_noise_std``), packed in the order of ``sensors``; ``None`` for one sensor."""
        if len(self.sensors) == 1:
            return None
        streams = {
            "image": {"name": "image", "shape": [1, self.image_size, self.image_size], "noise_std": self.noise_std},
            "angle": {"name": "angle", "shape": [2 * self.n_links], "noise_std": self.angle_noise_std},
        }
        return [streams[s] for s in self.sensors]

    def environment(self, seed: int | None = None) -> PendulumEnvironment:
        """This data set's pendulum as a system to control, frame by frame
        (:class:`~datamodules.pendulum_env.PendulumEnvironment`)."""
        return PendulumEnvironment(self.generator_params(), self.seed if seed is None else seed)

    def generate(self, split: str) -> dict[str, np.ndarray]:
        if split not in SPLIT_IDS:
            raise ValueError(f"unknown split {split!r}: the pendulum data set has splits {sorted(SPLIT_IDS)}")
        params = self.generator_params()
        count = self.n_train if split == "train" else self.n_test
        n, size, frames = self.n_links, self.image_size, self.n_frames
        out = {"state": np.empty((count, frames, 2 * n), np.float32)}
        if "image" in self.sensors:
            out["y"] = np.empty((count, frames, 1, size, size), np.uint8)
            out["y_clean"] = np.empty((count, frames, 1, size, size), np.uint8)
        if "angle" in self.sensors:
            key, clean_key = ("y", "y_clean") if self.sensors[0] == "angle" else ("y_angle", "y_clean_angle")
            out[key] = np.empty((count, frames, 2 * n), np.float32)
            out[clean_key] = np.empty((count, frames, 2 * n), np.float32)
        if self.torque_limit:
            out["u"] = np.empty((count, frames, n), np.float32)
        tasks = chunk_tasks(params, SPLIT_IDS[split], count)
        workers = min(self.workers, len(tasks))
        bar = tqdm(total=count, desc=f"pendulum {split} ({n} link{'s' * (n > 1)}, {workers} workers)", unit="traj")

        def store(start: int, arrays: dict[str, np.ndarray]) -> None:
            for key, a in arrays.items():
                out[key][start : start + len(a)] = a
            bar.update(len(arrays["y"]))

        try:
            run_tasks(tasks, workers, store)  # a failure: one DataGenerationError, the pool ended
        finally:
            bar.close()
        if split == "train" and self.recorded:  # the recorded episodes after the generated trajectories
            params = self.system_params()
            files = [read_recorded(path, params, frames) for path in self.recorded]
            out = {key: np.concatenate([a, *(f[key] for f in files)]) for key, a in out.items()}
        return out


def check_arguments(dm: PendulumDataModule) -> None:
    """Refuse the arguments of ``dm`` that make no data set: a ``ValueError`` with one line naming the argument, its
    value and what it must be."""

    def need(ok: bool, message: str) -> None:
        if not ok:
            raise ValueError(message)

    need(dm.n_links >= 1, f"n_links must be >= 1, got {dm.n_links}")
    need(
        dm.n_train >= 1 and dm.n_test >= 1,
        f"n_train and n_test must be >= 1, got {dm.n_train}, {dm.n_test}",
    )
    need(dm.line_width > 0, f"line_width must be > 0 pixels, got {dm.line_width}")
    need(dm.image_size >= 1, f"image_size must be a positive number of pixels, got {dm.image_size}")
    if dm.rendering == "paper":
        link, smallest = dm.image_size / 2 / dm.n_links, 2 * dm.n_links
    else:
        link = chain_length_pixels(dm.image_size, dm.line_width) / dm.n_links
        smallest = math.ceil(2 * (dm.n_links + dm.line_width / 2 + 1))
    need(
        link >= 1.0,
        f"image_size {dm.image_size} is too small for {dm.n_links} links of width {dm.line_width} "
        f"({dm.rendering} rendering): each link would be {link:.2f} pixels long (needs >= 1); use "
        f"image_size >= {smallest}" + (" or a thinner line_width" if dm.rendering == "analytic" else ""),
    )
    need(dm.damping >= 0, f"damping must be >= 0 (tau = -damping * velocity), got {dm.damping}")
    need(
        dm.sensors in (["image"], ["angle"], ["image", "angle"], ["angle", "image"]),
        f"sensors must be [image], [angle] or both (in the order they are packed), got {dm.sensors}",
    )
    need(
        dm.angle_noise_std > 0 and dm.angle_every >= 1,
        f"angle_noise_std must be > 0 (rad) and angle_every >= 1 (frames), got {dm.angle_noise_std}, {dm.angle_every}",
    )
    need(
        dm.sensors == ["image"] or not dm.normalize,
        "several sensors (or an angle alone) are served unnormalised: set normalize: false",
    )
    need(
        dm.torque_limit >= 0 and dm.torque_correlation > 0,
        f"torque_limit must be >= 0 (N m; 0: a free chain) and torque_correlation > 0 (s), got "
        f"{dm.torque_limit}, {dm.torque_correlation}",
    )
    need(
        dm.max_energy is None or (dm.max_energy > 0 and dm.torque_limit > 0),
        f"max_energy bounds the excitation's work: it needs torque_limit > 0 and must be > 0 (J above hanging "
        f"at rest), got max_energy {dm.max_energy} with torque_limit {dm.torque_limit}",
    )
    need(
        0.0 <= dm.closed_loop_share <= 1.0 and dm.closed_loop_noise >= 0,
        f"closed_loop_share must be in [0, 1] and closed_loop_noise >= 0, got {dm.closed_loop_share}, "
        f"{dm.closed_loop_noise}",
    )
    need(
        dm.closed_loop_override is None or (dm.closed_loop_share and 0 <= dm.closed_loop_override < 1),
        f"closed_loop_override hands frames of the closed-loop share to the excitation: it needs "
        f"closed_loop_share > 0 and a share of the torque limit in [0, 1), got {dm.closed_loop_override} with "
        f"closed_loop_share {dm.closed_loop_share}",
    )
    need(
        dm.closed_loop_balance or dm.closed_loop_share,
        "closed_loop_balance: false lets the closed-loop share's pendulum fall near upright: it needs "
        "closed_loop_share > 0",
    )
    need(
        not dm.closed_loop_share or (dm.n_links == 1 and dm.torque_limit > 0),
        f"closed_loop_share drives the simple pendulum by a swing-up controller: it needs n_links: 1 and "
        f"torque_limit > 0, got n_links {dm.n_links} with torque_limit {dm.torque_limit}",
    )
    need(
        dm.max_angle >= 0 and dm.max_velocity >= 0,
        f"max_angle and max_velocity are half-widths of uniform ranges and must be >= 0, got "
        f"{dm.max_angle}, {dm.max_velocity}",
    )
    need(dm.noise_std >= 0, f"noise_std must be >= 0, got {dm.noise_std}")
    need(
        dm.dt > 0 and dm.frame_dt > 0 and dm.duration > 0,
        f"dt, frame_dt and duration must be > 0, got {dm.dt}, {dm.frame_dt}, {dm.duration}",
    )
    steps = dm.frame_dt / dm.dt
    need(
        abs(steps - round(steps)) < 1e-6 * max(1.0, steps),
        f"frame_dt ({dm.frame_dt}) must be a whole multiple of the integrator step dt ({dm.dt}): "
        f"use dt = frame_dt / k for an integer k, e.g. {dm.frame_dt / max(1, math.ceil(steps))}",
    )
    frames = dm.duration / dm.frame_dt
    need(
        abs(frames - round(frames)) < 1e-6 * max(1.0, frames) and round(frames) >= 2,
        f"duration ({dm.duration}) must be a whole multiple (>= 2) of frame_dt ({dm.frame_dt}): "
        f"the trajectory has duration / frame_dt frames",
    )
    need(dm.workers >= 1, f"workers must be >= 1 (or null for all available cores), got {dm.workers}")
    need(
        not dm.recorded or dm.sensors == ["image"],
        f"recorded episodes are camera data: they need sensors [image], got {dm.sensors}",
    )
    need(dm.seed >= 0, f"seed must be >= 0 (it seeds numpy's SeedSequence), got {dm.seed}")
