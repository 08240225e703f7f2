"""The n-link planar pendulum of the paper, simulated with Pinocchio and rendered to noisy images.

The system: ``n_links`` unit-length, massless links joined by revolute joints, a unit point mass at
the end of every link, gravity ``g = 9.81``. Joint ``k``'s angle is relative to link ``k - 1``
(Pinocchio's chain of revolute joints), so the absolute angle of link ``k`` is the cumulative sum
``phi_k = theta_1 + ... + theta_k``; all angles zero is the chain hanging straight down. Optional
viscous joint damping applies the torque ``tau = -damping * theta_dot``. The forward dynamics are
Pinocchio's ``pin.aba``, integrated with classical RK4 at a fixed step ``dt``.

Choice of ``dt`` (default ``5e-3``): the largest step, among those that divide the frame period,
that keeps both paper systems comfortably accurate. Measured maximum energy error over 10 s,
undamped, relative to the potential-energy scale ``g * sum of mass heights`` (``g`` for one link,
``10 g`` for four), median / max over 48 initial states drawn like the paper's
(``benchmarks/bench_pendulum_data.py`` re-measures the two middle rows)::

    dt       1 link, theta_dot ~ U[-1, 1]   4 links, angles ~ U[-pi, pi], at rest
    2e-2     2e-7 / 5e-7                    9e-3 / 1.2e-1   (40 states)
    1e-2     9e-9 / 2e-8                    7e-4 / 7.8e-3   above 0.1 % for some states
    5e-3     4e-10 / 1e-9                   2e-5 / 2.4e-4   the default
    2.5e-3   2e-11 / 5e-11                  4e-7 / 9e-6     (40 states)

(the reference implementation's scheme, semi-implicit Euler at ``dt = 1e-3``, is symplectic: its energy
error stays bounded, at most 0.26 % of ``m g l`` over 10 s, median 0.17 %, over 2000 simple-pendulum initial
states drawn like the paper's; measured 2026-11-26, an earlier text here said it lost 40 %). Cost: ~7 ms (1 link) and ~16 ms (4 links) of dynamics per
trajectory, ~1 ms rendering, 1-2 ms noise, on one core of this project's machine.

Images, two renderings (``rendering``):

- ``"paper"`` (the default; the paper's public generator, ``ssm_ms/data/n_link.py`` of
  machines-in-motion/ssm_multiple_shooting): drawn with the generator's own calls, PIL's
  ``ImageDraw.line(width=8)`` on a ``128 x 128`` float canvas, pivot at canvas point ``(64, 64)``, the whole
  chain ``64`` canvas pixels long (a straight chain reaches the edge of the frame), then
  ``Image.resize(..., Image.LANCZOS)`` to ``image_size`` (which rings: clean values reach about -0.1 and 1.2).
  PIL's conventions are kept with it: a coordinate names a pixel index (pixel ``64`` is lit at the pivot,
  whose centre is 64.5 canvas pixels from the edge), end points are truncated to whole pixels, and an
  8-pixel line covers 3 pixels on one side of its axis and 4 on the other, so a hanging chain lights
  columns 61-68. Equal to the reference's ``create_image`` (without its noise) to the last bit on 2000
  random states per system (``tests/test_pendulum.py`` pins the pivot pixel against a closed form).
  ``line_width`` is in output pixels (default ``image_size / 16``, the paper's 8 of 128), drawn as the
  nearest whole number of canvas pixels.
- ``"analytic"`` (this project's first rendering, kept for the CPU twins' committed results):
  anti-aliased thick lines with round caps; a pixel's intensity is
  ``clip(line_width / 2 + 0.5 - distance, 0, 1)`` where ``distance`` is from the pixel centre to the
  nearest link segment (an analytic coverage estimate, max over segments). The whole chain spans
  ``image_size / 2 - line_width / 2 - 1`` pixels, so that the tip, its cap and its anti-aliasing ramp
  stay inside the image. Default ``line_width`` 2.

In both, every link has the same length in pixels, image right is the direction of positive angles
(``theta = pi / 2`` with one link points right), image down is gravity. Noise, as the paper's generator:
``y = clip(clean + N(0, noise_std^2), 0, 1)``, drawn on the float clean image (before any clipping);
then ``y`` and ``y_clean = clip(clean, 0, 1)`` are quantised to ``uint8`` (step ``1/255``; its error
std ``1/(255 sqrt 12) ~ 1.1e-3`` is negligible next to ``noise_std = 0.2``).

Generation is deterministic given ``seed``: trajectory ``i`` of split ``s`` draws its initial state
and its noise from ``np.random.default_rng([seed, s, i])`` (``s = 0`` train, ``1`` test), and the
simulation of a trajectory involves only element-wise arithmetic and its own ``pin.aba`` calls,
so the arrays do not depend on ``workers`` or on how trajectories are grouped. On another installation
(numpy build, CPU) the noise may differ: numpy guarantees its streams only within one build and
machine (docs/datasets.md has a measured case).
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
import signal
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from typing import TYPE_CHECKING, Any

import numpy as np
from tqdm.auto import tqdm

from datamodules.base import TrajectoryDataModule

if TYPE_CHECKING:
    import torch

GRAVITY = 9.81
SPLIT_IDS = {"train": 0, "test": 1}
CHUNK_SIZE = 32  # trajectories per worker task (simulated together to amortise Python overhead)
GENERATOR_VERSION = 2  # bump when the generated arrays change for the same parameters


# ---------------------------------------------------------------------------------------- model
def pendulum_model(n_links: int):
    """Pinocchio model of the chain: revolute joints about x, unit links along -z, unit point masses.

    The mass of link ``k`` sits at ``(0, sum sin phi_j, -sum cos phi_j)`` (``phi`` the cumulative
    angles): world ``+y`` is image right, world ``-z`` image down. Gravity is Pinocchio's default,
    ``(0, 0, -9.81)``.
    """
    import pinocchio as pin

    if n_links < 1:
        raise ValueError(f"n_links must be >= 1, got {n_links}")
    model = pin.Model()
    model.gravity.linear = np.array([0.0, 0.0, -GRAVITY])
    parent = 0
    for k in range(n_links):
        offset = np.array([0.0, 0.0, 0.0 if k == 0 else -1.0])  # joint k sits at the mass of link k-1
        joint = model.addJoint(parent, pin.JointModelRX(), pin.SE3(np.eye(3), offset), f"joint{k + 1}")
        mass = pin.Inertia(1.0, np.array([0.0, 0.0, -1.0]), np.zeros((3, 3)))  # point mass at the link end
        model.appendBodyToJoint(joint, mass, pin.SE3.Identity())
        parent = joint
    return model


# ------------------------------------------------------------------------------------ dynamics
def simulate(
    model,
    data,
    q0: np.ndarray,
    v0: np.ndarray,
    n_frames: int,
    steps_per_frame: int,
    dt: float,
    damping: float = 0.0,
    torques: np.ndarray | None = None,
    policy: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """RK4-integrate a batch of trajectories; returns angles, velocities and applied torques at every frame.

    Args:
        model, data: a Pinocchio model (see :func:`pendulum_model`) and its data.
        q0, v0: initial joint angles and velocities ``[B, n]``.
        n_frames: frames to record; frame 0 is the initial state.
        steps_per_frame: RK4 steps between frames (frame period ``steps_per_frame * dt``).
        dt: RK4 step.
        damping: viscous joint damping, ``tau = -damping * v``.
        torques: applied joint torques ``[B, >= n_frames - 1, n]`` (N m), held from frame ``t`` to frame ``t + 1``
            (a zero-order hold: what a controller acting once per frame applies); added to the damping torque.
        policy: with ``torques``, what is applied from each frame in feedback: ``policy(q, v, u) -> [B, n]``, given
            the chain's angles and velocities at the frame and the frame's given torques ``u [B, n]`` (the data's:
            :func:`data_policy`). ``None``: the torques as given. Torques past the last frame are left as given.

    Returns:
        ``q, v`` of shape ``[B, n_frames, n]`` (float64; angles are not wrapped) and the torques applied
        (float64, the shape of ``torques``; ``None`` without torques).

    The batch dimension only amortises NumPy's per-call overhead: every operation on the batch is
    element-wise and ``pin.aba`` runs per trajectory, so each trajectory's result is bit-identical
    to simulating it alone.
    """
    import pinocchio as pin

    aba = pin.aba
    q = np.array(q0, dtype=np.float64, ndmin=2)
    v = np.array(v0, dtype=np.float64, ndmin=2)
    if q.shape != v.shape or q.shape[1] != model.nq:
        raise ValueError(f"q0 and v0 must both be [B, {model.nq}], got {q.shape} and {v.shape}")
    batch, n = q.shape
    out_q = np.empty((batch, n_frames, n))
    out_v = np.empty((batch, n_frames, n))
    # stage inputs are written in place into these buffers, so the per-trajectory rows are fixed views
    qs, vs, tau = np.empty((batch, n)), np.empty((batch, n)), np.zeros((batch, n))
    rows = list(zip(qs, vs, tau))
    neg_damping, damped = -float(damping), damping != 0.0
    h2, h6 = 0.5 * dt, dt / 6.0
    if torques is not None:
        torques = np.asarray(torques, dtype=np.float64)
        if torques.ndim != 3 or torques.shape[0] != batch or torques.shape[2] != n or torques.shape[1] < n_frames - 1:
            raise ValueError(f"torques must be [{batch}, >= {n_frames - 1}, {n}], got {torques.shape}")
        torques = torques.copy()  # the policy's torques are written in place below
    elif policy is not None:
        raise ValueError("a policy acts on given torques: pass torques too")
    applied = np.zeros((batch, n))

    driven = torques is not None

    def accel() -> np.ndarray:
        if damped:
            np.multiply(vs, neg_damping, out=tau)
            if driven:
                np.add(tau, applied, out=tau)
        elif driven:
            np.copyto(tau, applied)
        return np.array([aba(model, data, qr, vr, tr) for qr, vr, tr in rows])

    for frame in range(n_frames):
        out_q[:, frame] = q
        out_v[:, frame] = v
        if policy is not None and frame < torques.shape[1]:  # the frame's torque, in feedback on its state
            torques[:, frame] = policy(q, v, torques[:, frame])
        if frame == n_frames - 1:
            break
        if torques is not None:
            applied[:] = torques[:, frame]
        for _ in range(steps_per_frame):
            qs[:] = q
            vs[:] = v
            a1 = accel()
            np.add(q, h2 * v, out=qs)
            np.add(v, h2 * a1, out=vs)
            v2 = vs.copy()
            a2 = accel()
            np.add(q, h2 * v2, out=qs)
            np.add(v, h2 * a2, out=vs)
            v3 = vs.copy()
            a3 = accel()
            np.add(q, dt * v3, out=qs)
            np.add(v, dt * a3, out=vs)
            v4 = vs.copy()
            a4 = accel()
            q = q + h6 * (v + 2.0 * v2 + 2.0 * v3 + v4)
            v = v + h6 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
    return out_q, out_v, torques


def chain_energy(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The chain's mechanical energy above hanging at rest (J), ``[...]`` of angles and velocities ``[..., n]``
    (:func:`pendulum_model`'s chain: unit point masses at the ends of unit links, relative joint angles):
    kinetic ``1/2 sum_k |p_k'|^2`` plus potential ``g sum_k (k - depth_k)``, mass ``k`` at depth
    ``sum_{j<=k} cos phi_j`` below the pivot. One link: ``v^2 / 2 + g (1 - cos q)``; upright at rest ``2 g``."""
    phi, omega = np.cumsum(q, axis=-1), np.cumsum(v, axis=-1)
    vy, vz = np.cumsum(omega * np.cos(phi), axis=-1), np.cumsum(omega * np.sin(phi), axis=-1)
    depth = np.cumsum(np.cos(phi), axis=-1)
    k = np.arange(1, q.shape[-1] + 1)
    return 0.5 * np.sum(vy**2 + vz**2, axis=-1) + GRAVITY * np.sum(k - depth, axis=-1)


# ----------------------------------------------------------------------------------- rendering
RENDERINGS = ("paper", "analytic")
PAPER_CANVAS = 128  # the paper's generator draws on a 128 x 128 canvas, 8 pixels wide, then resizes


def default_line_width(rendering: str, image_size: int) -> float:
    """Line thickness in output pixels when none is given: the paper's 8 of 128, or 2 (analytic)."""
    return 8.0 * image_size / PAPER_CANVAS if rendering == "paper" else 2.0


def paper_canvas_width(line_width: float, image_size: int) -> int:
    """The line width in canvas pixels that PIL draws (a whole number): ``line_width`` output pixels scaled to the
    128-pixel canvas (the paper's 8 for ``image_size / 16``)."""
    return max(1, int(round(line_width * PAPER_CANVAS / image_size)))


def render_paper(angles: np.ndarray, image_size: int, line_width: float | None = None) -> np.ndarray:
    """Render chains as the paper's generator does, with its own drawing calls (see the module doc): PIL's
    ``ImageDraw.line`` on a 128 x 128 float canvas, pivot at canvas point ``(64, 64)``, the chain half the canvas
    long, then ``Image.resize(..., Image.LANCZOS)`` to ``image_size``.

    Args:
        angles: joint angles ``[T, n]`` (relative, as in :func:`pendulum_model`).
        image_size: output height and width in pixels.
        line_width: thickness in output pixels (default ``image_size / 16``, the paper's 8 canvas pixels); drawn
            as :func:`paper_canvas_width` whole canvas pixels.

    Returns:
        float32 ``[T, 1, H, W]``, not clipped (the filter rings slightly outside [0, 1]).
    """
    from PIL import Image, ImageDraw  # Pillow: a dependency of matplotlib, listed in pyproject.toml

    angles = np.asarray(angles, dtype=np.float64)
    if angles.ndim != 2:
        raise ValueError(f"angles must be [T, n_links], got shape {angles.shape}")
    if line_width is None:
        line_width = default_line_width("paper", image_size)
    width = paper_canvas_width(line_width, image_size)
    frames, n = angles.shape
    phi = np.cumsum(angles, axis=-1)
    # joint positions in canvas coordinates (x right, y down: image down is gravity); PIL lights the pixel whose
    # index is the (truncated) coordinate, so the pivot (64, 64) is pixel 64, as in the reference generator
    steps = np.stack([np.sin(phi), np.cos(phi)], axis=-1) * (PAPER_CANVAS / 2 / n)
    pts = np.concatenate([np.zeros((frames, 1, 2)), np.cumsum(steps, axis=-2)], axis=-2) + PAPER_CANVAS / 2
    out = np.empty((frames, 1, image_size, image_size), np.float32)
    for t in range(frames):
        canvas = Image.new("F", (PAPER_CANVAS, PAPER_CANVAS), 0.0)
        draw = ImageDraw.Draw(canvas)
        for s in range(n):
            draw.line([tuple(pts[t, s]), tuple(pts[t, s + 1])], fill=1.0, width=width)
        out[t, 0] = np.asarray(canvas.resize((image_size, image_size), resample=Image.LANCZOS))
    return out


def chain_length_pixels(image_size: int, line_width: float) -> float:
    """Length of the whole chain in pixels in the analytic rendering: half the image minus room for the tip's
    cap and ramp (the paper's rendering: half the image)."""
    return image_size / 2.0 - line_width / 2.0 - 1.0


def joint_positions(angles: np.ndarray, image_size: int, line_width: float) -> np.ndarray:
    """Pixel coordinates ``[..., n + 1, 2]`` (x right, y down; pixel ``(i, j)`` spans
    ``[j, j + 1] x [i, i + 1]``) of the pivot (the image centre) and the end of every link."""
    n = angles.shape[-1]
    link = chain_length_pixels(image_size, line_width) / n
    phi = np.cumsum(angles, axis=-1)
    steps = np.stack([np.sin(phi), np.cos(phi)], axis=-1) * link  # down is +y in the image
    pts = np.concatenate([np.zeros((*angles.shape[:-1], 1, 2)), np.cumsum(steps, axis=-2)], axis=-2)
    return pts + image_size / 2.0


def render_analytic(angles: np.ndarray, image_size: int, line_width: float | None = None) -> np.ndarray:
    """Render chains to anti-aliased images with round caps (the ``"analytic"`` rendering).

    Args:
        angles: joint angles ``[T, n]`` (relative, as in :func:`pendulum_model`).
        image_size: image height and width in pixels.
        line_width: line thickness in pixels.

    Returns:
        float32 ``[T, 1, H, W]`` in [0, 1]: ``clip(line_width / 2 + 0.5 - distance, 0, 1)``, with
        ``distance`` from the pixel centre to the nearest link segment.

    Each segment is evaluated only on a ``K x K`` window around it (``K`` = link length + line
    width + 3 pixels), which holds every pixel it can light; the windows are merged with ``max``.
    """
    angles = np.asarray(angles, dtype=np.float64)
    if angles.ndim != 2:
        raise ValueError(f"angles must be [T, n_links], got shape {angles.shape}")
    if line_width is None:
        line_width = default_line_width("analytic", image_size)
    frames, n = angles.shape
    reach = line_width / 2.0 + 0.5  # farthest a lit pixel centre can be from a segment
    link = chain_length_pixels(image_size, line_width) / n
    k = min(int(math.ceil(link + 2.0 * reach)) + 2, image_size)
    pts = joint_positions(angles, image_size, line_width).astype(np.float32)
    a, b = pts[:, :-1], pts[:, 1:]  # segment ends [T, n, 2]
    # window origins: the first pixel whose centre may lie within `reach` of the segment
    origin = np.floor(np.minimum(a, b) - np.float32(reach + 0.5)).astype(np.int64)
    np.clip(origin, 0, image_size - k, out=origin)
    idx = origin[..., None] + np.arange(k)  # pixel indices [T, n, 2, K]
    centres = idx.astype(np.float32) + np.float32(0.5)
    d = b - a
    inv_len2 = (1.0 / (d**2).sum(-1))[..., None, None]
    rx = centres[:, :, 0, None, :] - a[..., 0, None, None]  # [T, n, 1, K]
    ry = centres[:, :, 1, :, None] - a[..., 1, None, None]  # [T, n, K, 1]
    dx, dy = d[..., 0, None, None], d[..., 1, None, None]
    t = rx * (dx * inv_len2) + ry * (dy * inv_len2)  # projection on the segment [T, n, K, K]
    np.clip(t, 0.0, 1.0, out=t)
    ex = rx - t * dx
    ey = ry - t * dy
    val = np.float32(reach) - np.sqrt(ex * ex + ey * ey)
    np.clip(val, 0.0, 1.0, out=val)
    img = np.zeros((frames, image_size, image_size), np.float32)
    rows = np.arange(frames)[:, None, None]
    for s in range(n):  # windows of one segment lie in different frames: no clash within an assignment
        where = (rows, idx[:, s, 1, :, None], idx[:, s, 0, None, :])
        img[where] = np.maximum(img[where], val[:, s])
    return img[:, None]


RENDERERS = {"paper": render_paper, "analytic": render_analytic}


def render(
    angles: np.ndarray, image_size: int, line_width: float | None = None, rendering: str = "paper"
) -> np.ndarray:
    """Clean frames ``[T, 1, H, W]`` (float32) of chains with joint angles ``[T, n]``, in either rendering."""
    if rendering not in RENDERERS:
        raise ValueError(f"unknown rendering {rendering!r}: choose among {list(RENDERERS)}")
    return RENDERERS[rendering](angles, image_size, line_width)


def quantize(img: np.ndarray) -> np.ndarray:
    """Floats -> uint8 0..255 (clipped to [0, 1], rounded)."""
    return np.rint(np.clip(img, 0.0, 1.0) * 255.0).astype(np.uint8)


def angle_reading(q: np.ndarray) -> np.ndarray:
    """What the joint encoders report for angles ``[..., n]``: ``[sin q_1 .. sin q_n, cos q_1 .. cos q_n]``
    (float32, ``[..., 2 n]``). The sine and cosine, not the angle: a driven joint turns over and over (the
    torque-driven data reach 137 rad), and an angle without bound is one no network extrapolates; this reading is
    bounded, continuous through upright (a wrapped angle jumps there) and the observation of gym's Pendulum."""
    return np.concatenate([np.sin(q), np.cos(q)], axis=-1).astype(np.float32)


# ---------------------------------------------------------------------------------- generation
_WORKER: dict[str, Any] = {}
PINOCCHIO_HINT = (
    "Pinocchio is the PyPI package `pin`, one of pyproject.toml's dependencies: install it in this environment "
    "with `pip install 'pin>=3.4'` or `make install`"
)


class DataGenerationError(ValueError):
    """Generating a data set failed, in this process or in a worker: one message naming the cause.

    A ``ValueError`` so that ``cli.py`` prints it as one ``error:`` line (a user-error type of ``ssm_ms/cli.py``):
    a worker's failure is mostly the installation's (a missing ``pin`` package) or the machine's (a worker killed
    for memory). The original exception is its ``__cause__``, with a worker's own traceback under it
    (``SSM_MS_TRACEBACK=1`` shows them).
    """


def _init_worker(n_links: int) -> None:
    """Build this process's Pinocchio model (nothing is pickled): :func:`generate_chunk` calls it on a process's
    first task, so a failure here (``pinocchio`` missing) is that task's exception."""
    model = pendulum_model(n_links)
    _WORKER.update(n_links=n_links, model=model, data=model.createData())


def initial_states(params: dict[str, Any], split_id: int, indices) -> tuple[list, np.ndarray, np.ndarray]:
    """The random streams and initial angles / velocities ``[len(indices), n]`` of trajectories ``indices``
    (each trajectory's stream is seeded by ``(seed, split, index)``, so any one can be regenerated alone)."""
    n = params["n_links"]
    rngs = [np.random.default_rng([params["seed"], split_id, int(i)]) for i in indices]
    q0 = np.stack([r.uniform(-params["max_angle"], params["max_angle"], n) for r in rngs])
    v0 = np.stack([r.uniform(-params["max_velocity"], params["max_velocity"], n) for r in rngs])
    return rngs, q0, v0


def excitation(rngs: list, n_frames: int, n: int, limit: float, correlation: float, frame_dt: float) -> np.ndarray:
    """Random joint torques ``[len(rngs), n_frames, n]`` (N m), one value per frame held until the next: smoothed
    Gaussian noise, an AR(1) process ``w[t] = a w[t-1] + sqrt(1 - a^2) e[t]`` with ``a = exp(-frame_dt /
    correlation)`` (stationary, unit variance, correlation time ``correlation`` seconds), scaled to a standard
    deviation of ``limit / 2`` and clipped to ``[-limit, limit]``. Drawn from each trajectory's stream after its
    initial state, ``n_frames x n`` normals in row order, so a longer horizon extends the same torques."""
    a = math.exp(-frame_dt / correlation)
    e = np.stack([r.standard_normal((n_frames, n)) for r in rngs])
    w = np.empty_like(e)
    w[:, 0] = e[:, 0]
    for t in range(1, n_frames):
        w[:, t] = a * w[:, t - 1] + math.sqrt(1.0 - a * a) * e[:, t]
    return np.clip(0.5 * limit * w, -limit, limit)


def torques_of(params: dict[str, Any], rngs: list, n_frames: int) -> np.ndarray | None:
    """The torques of trajectories whose streams are ``rngs`` (``None`` for a free chain: ``torque_limit`` 0)."""
    if not params.get("torque_limit"):
        return None
    return excitation(
        rngs, n_frames, params["n_links"], params["torque_limit"], params["torque_correlation"], params["frame_dt"]
    )


# Gains of swing_up_balance: energy pumping (1 / (J s)), the catch (rad from upright), and the linear feedback that
# places the linearised upright pendulum, d'' = g d + u, at a double pole of 3 rad/s (k_angle = 9 + g, k_velocity = 6).
SWING_UP = {"k_energy": 1.0, "catch": 0.5, "k_angle": 9.0 + GRAVITY, "k_velocity": 6.0}


def swing_up_balance(q: np.ndarray, v: np.ndarray, limit: float) -> np.ndarray:
    """A classic controller that swings the simple pendulum up and balances it, the torques ``[B, 1]`` (N m, within
    ``+-limit``) at angles and velocities ``[B, 1]``: within ``catch`` rad of upright it holds the pendulum by linear
    feedback, ``u = -k_angle d - k_velocity v`` (``d`` the angle from upright, wrapped to ``[-pi, pi)``); elsewhere it
    pumps energy towards upright at rest, ``u = k_energy (2 g - E) v`` (``E`` :func:`chain_energy`, ``dE/dt = u v``).
    Held once per frame (0.1 s), with ``limit = 3`` it swings every pendulum of the data's initial states up within
    10 s and holds it there (78% of the frames within 0.3 rad of upright, 200 states)."""
    k = SWING_UP
    d = np.mod(q[:, 0], 2.0 * math.pi) - math.pi
    pump = k["k_energy"] * (2.0 * GRAVITY - chain_energy(q, v)) * v[:, 0]
    hold = -k["k_angle"] * d - k["k_velocity"] * v[:, 0]
    return np.clip(np.where(np.abs(d) < k["catch"], hold, pump), -limit, limit)[:, None]


def closed_loop(indices, share: float) -> np.ndarray:
    """Which trajectories of a split the controller drives (bool per index): trajectory ``i`` iff ``floor((i + 1)
    share) > floor(i share)``, a share ``share`` spread evenly over the indices, decided by the index alone."""
    i = np.asarray(list(indices), dtype=np.int64)
    return np.floor((i + 1) * share) > np.floor(i * share)


def data_policy(params: dict[str, Any], indices) -> Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None:
    """The data's torques in feedback (:func:`simulate`'s ``policy``) for trajectories ``indices`` of a split, or
    ``None`` where they are the excitation's as drawn. Two parts, in this order: with ``closed_loop_share``, the
    trajectories :func:`closed_loop` picks get :func:`swing_up_balance` plus ``closed_loop_noise`` times their
    excitation (exploration), clipped to ``+-torque_limit``, except, with ``closed_loop_override``, the frames whose
    excitation exceeds that share of the limit, and, with ``closed_loop_balance`` false, those within the controller's
    catch of upright: those get the excitation alone; with ``max_energy``, a chain above the
    bound gets no torque that would do positive work (``u . v > 0``: that frame's torque is 0)."""
    share, bound = params.get("closed_loop_share", 0.0), params.get("max_energy")
    if not share and bound is None:
        return None
    closed = closed_loop(indices, share)
    limit, noise = params["torque_limit"], params.get("closed_loop_noise", 0.0)
    override, balance = params.get("closed_loop_override"), params.get("closed_loop_balance", True)

    def policy(q: np.ndarray, v: np.ndarray, u: np.ndarray) -> np.ndarray:
        if closed.any():
            u = u.copy()
            given = u[closed]
            held = np.clip(swing_up_balance(q[closed], v[closed], limit) + noise * given, -limit, limit)
            free = np.zeros(len(given), dtype=bool) if override is None else np.abs(given[:, 0]) > override * limit
            if not balance:  # near upright the excitation alone: pumped up, let fall, pumped up again
                free |= np.abs(np.mod(q[closed, 0], 2.0 * math.pi) - math.pi) < SWING_UP["catch"]
            u[closed] = np.where(free[:, None], given, held)
        if bound is not None:
            pumping = (chain_energy(q, v) > bound) & (np.sum(u * v, axis=1) > 0)
            u = np.where(pumping[:, None], 0.0, u)
        return u

    return policy


def generate_chunk(params: dict[str, Any], split_id: int, start: int, stop: int) -> dict[str, np.ndarray]:
    """Trajectories ``start..stop-1`` of a split: ``{"y", "y_clean", "state"}`` (see the module doc).

    ``params`` is :meth:`PendulumDataModule.generator_params`. Runs in a pool worker (or in the
    main process after :func:`_init_worker`).
    """
    if _WORKER.get("n_links") != params["n_links"]:
        _init_worker(params["n_links"])
    size = params["image_size"]
    n_frames = int(round(params["duration"] / params["frame_dt"]))
    steps = int(round(params["frame_dt"] / params["dt"]))
    rngs, q0, v0 = initial_states(params, split_id, range(start, stop))
    u = torques_of(params, rngs, n_frames)
    q, v, u = simulate(
        _WORKER["model"],
        _WORKER["data"],
        q0,
        v0,
        n_frames,
        steps,
        params["dt"],
        params["damping"],
        u,
        data_policy(params, range(start, stop)),
    )
    count = stop - start
    sensors = params.get("sensors", ["image"])
    out: dict[str, np.ndarray] = {"state": np.concatenate([q, v], axis=-1).astype(np.float32)}
    if "image" in sensors:
        y = np.empty((count, n_frames, 1, size, size), np.uint8)
        y_clean = np.empty_like(y)
        for j, r in enumerate(rngs):
            clean = render(q[j], size, params["line_width"], params["rendering"])
            noise = r.standard_normal(clean.shape, dtype=np.float32)
            noise *= np.float32(params["noise_std"])
            noise += clean
            np.clip(noise, 0.0, 1.0, out=noise)
            y[j] = quantize(noise)
            y_clean[j] = quantize(clean)
        out.update(y=y, y_clean=y_clean)
    if "angle" in sensors:  # joint encoders: the angles with noise, every angle_every frames (NaN between)
        noise = np.stack([r.standard_normal(q[j].shape) for j, r in enumerate(rngs)])
        angle = angle_reading(q + params["angle_noise_std"] * noise)
        angle[:, np.arange(n_frames) % params["angle_every"] != 0] = np.nan
        key, clean_key = ("y", "y_clean") if sensors[0] == "angle" else ("y_angle", "y_clean_angle")
        out.update({key: angle, clean_key: angle_reading(q)})
    if u is not None:
        out["u"] = u.astype(np.float32)
    return out


def _run_chunk(task: tuple[dict[str, Any], int, int, int]) -> tuple[int, dict[str, np.ndarray]]:
    params, split_id, start, stop = task
    return start, generate_chunk(params, split_id, start, stop)


def _worker_signals() -> None:
    """Pool worker initializer: Ctrl-C is the parent's to handle (it ends the pool), and SIGTERM ends the worker
    (a handler inherited through fork, e.g. Lightning's, would keep it alive when the pool ends it)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _failure(exc: BaseException, processes: list = ()) -> DataGenerationError:
    """The one message for a failed generation (the same from a worker as from this process); ``processes``: the
    pool's, ended, for a dead worker's exit code."""
    if isinstance(exc, BrokenProcessPool):
        # the pool ends the other workers with SIGTERM: the codes left are the dead worker's
        codes = sorted({p.exitcode for p in processes if p.exitcode not in (None, 0, -signal.SIGTERM)})
        how = f" (exit code {', '.join(map(str, codes))})" if codes else ""
        cause = f"a worker process died{how}: killed (e.g. by the out-of-memory killer: try fewer `workers`) or crashed"
    else:
        cause = f"{type(exc).__name__}: {exc}"
        if isinstance(exc, ImportError) and "pinocchio" in f"{exc.name} {exc}":
            cause += f" ({PINOCCHIO_HINT})"
    return DataGenerationError(f"pendulum data generation failed: {cause}")


def _run_tasks(tasks: list, workers: int, store: Callable[[int, dict[str, np.ndarray]], None]) -> None:
    """Run :func:`_run_chunk` on every task, here (``workers == 1``) or in a pool of ``workers`` processes, and
    ``store(start, arrays)`` each result as it comes (in completion order: where a chunk goes depends only on its
    ``start``).

    Any failure stops the generation at once with one :class:`DataGenerationError` naming the cause: a task's
    exception (re-raised here from its worker), a worker that died (``BrokenProcessPool``). The pool is ended
    before this returns or raises (also on Ctrl-C): tasks not started are dropped, a worker finishes the chunk it
    is on (about a second) and exits; a worker that died makes the pool end the others at once.
    """
    if workers <= 1:
        for task in tasks:
            try:
                start, arrays = _run_chunk(task)
            except Exception as exc:
                raise _failure(exc) from exc
            store(start, arrays)
        return
    # fork: workers start instantly (no re-import of torch); spawn elsewhere
    ctx = mp.get_context("fork" if "fork" in mp.get_all_start_methods() else None)
    pool = ProcessPoolExecutor(workers, mp_context=ctx, initializer=_worker_signals)
    try:
        futures = [pool.submit(_run_chunk, task) for task in tasks]
        # for a dead worker's exit code in the message (a private attribute: the message does without it if missing)
        processes = list((getattr(pool, "_processes", None) or {}).values())
        for future in as_completed(futures):
            try:
                start, arrays = future.result()
            except Exception as exc:
                pool.shutdown(wait=True, cancel_futures=True)  # first: an exit code is known once its process is joined
                raise _failure(exc, processes) from exc
            store(start, arrays)
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def available_cores() -> int:
    """Cores this process may run on (affinity-aware where the platform tells)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


# ---------------------------------------------------------------------------------- environment
class PendulumEnvironment:
    """The pendulum as a system to control: the simulator of the data set (Pinocchio, RK4) and its camera, one frame
    per call, for a batch of episodes.

    :meth:`reset` places the chains at given joint angles and velocities and returns the first measurements;
    :meth:`step` holds the torques ``u [B, n_links]`` (N m) for one frame period, as the data's torques are held, and
    returns the next. Measurements are made as the data's: frames rendered and noised (``noise_std``, clipped,
    quantised to 8 bits), float32 ``[B, 1, H, W]`` in [0, 1]; with the data's ``sensors`` the encoders' reading too
    (``angle_noise_std``; NaN between samples every ``angle_every`` periods), packed as a batch's ``y`` is
    (``[B, P]``; the reading alone ``[B, 2 n]``, :func:`angle_reading` of the angles noised). :attr:`state` ``[B, 2 n]`` (angles, then velocities) is the truth, for
    scoring only. The noise of episode ``i`` comes from ``numpy.random.default_rng([seed, 2, i])`` (split id 2:
    neither the training nor the test data's streams).
    """

    def __init__(self, params: dict[str, Any], seed: int = 0):
        self.params = dict(params)
        self.model = pendulum_model(params["n_links"])
        self.data = self.model.createData()
        self.steps = int(round(params["frame_dt"] / params["dt"]))
        self.seed = int(seed)
        self.frame_dt = float(params["frame_dt"])

    def reset(self, q0: np.ndarray, v0: np.ndarray) -> np.ndarray:
        self.q = np.array(q0, dtype=np.float64, ndmin=2)
        self.v = np.array(v0, dtype=np.float64, ndmin=2)
        self.rngs = [np.random.default_rng([self.seed, 2, i]) for i in range(len(self.q))]
        self.period = 0
        return self.measure()

    def measure(self) -> np.ndarray:
        """The measurements now, in the data's layout (see the class doc)."""
        sensors = self.params.get("sensors", ["image"])
        parts = {}
        if "image" in sensors:
            parts["image"] = self.frames()
        if "angle" in sensors:
            noise = np.stack([r.standard_normal(self.q.shape[1]) for r in self.rngs])
            angle = angle_reading(self.q + self.params["angle_noise_std"] * noise)
            if self.period % self.params["angle_every"]:
                angle[:] = np.nan
            parts["angle"] = angle
        if len(parts) == 1:
            return next(iter(parts.values()))
        return np.concatenate([parts[s].reshape(len(self.q), -1) for s in sensors], axis=1)

    @property
    def state(self) -> np.ndarray:
        return np.concatenate([self.q, self.v], axis=-1)

    def frames(self) -> np.ndarray:
        p = self.params
        out = np.empty((len(self.q), 1, p["image_size"], p["image_size"]), np.float32)
        for j, r in enumerate(self.rngs):
            clean = render(self.q[j : j + 1], p["image_size"], p["line_width"], p["rendering"])[0]
            noisy = np.clip(clean + np.float32(p["noise_std"]) * r.standard_normal(clean.shape, dtype=np.float32), 0, 1)
            out[j] = quantize(noisy) / np.float32(255.0)
        return out

    def clean_frames(self) -> np.ndarray:
        """The current frames without noise (for pictures)."""
        p = self.params
        return np.stack(
            [
                quantize(render(q[None], p["image_size"], p["line_width"], p["rendering"])[0]) / np.float32(255)
                for q in self.q
            ]
        )

    def step(self, u: np.ndarray) -> np.ndarray:
        u = np.asarray(u, dtype=np.float64).reshape(len(self.q), 1, -1)
        q, v, _ = simulate(
            self.model, self.data, self.q, self.v, 2, self.steps, self.params["dt"], self.params["damping"], u
        )
        self.q, self.v = q[:, 1], v[:, 1]
        self.period += 1
        return self.measure()


# ---------------------------------------------------------------------------------- recorded episodes
# What a recorded episode's system must share with the data's (the excitation, the starts and the seed may differ)
RECORDED_SYSTEM = (
    "n_links",
    "image_size",
    "rendering",
    "line_width",
    "noise_std",
    "frame_dt",
    "dt",
    "damping",
    "gravity",
)
RECORDED_KEYS = ("y", "y_clean", "state", "u")


def read_recorded(path: str, params: dict[str, Any], n_frames: int) -> dict[str, np.ndarray]:
    """The arrays of a file of recorded episodes (``ClosedLoop(record=...)``), checked against the data's system
    ``params`` and length ``n_frames``: ``ValueError`` with one line naming what differs."""
    import json

    if not os.path.isfile(path):
        raise ValueError(f"recorded: no file {path} (write one with the closed loop's record option, docs/control.md)")
    try:
        with np.load(path) as z:
            missing = [k for k in (*RECORDED_KEYS, "params") if k not in z.files]
            if missing:
                raise ValueError(f"recorded: {path} lacks {missing}: not a file written by the closed loop's record")
            arrays = {k: z[k] for k in RECORDED_KEYS}
            system = json.loads(str(z["params"]))
    except (OSError, EOFError) as exc:
        raise ValueError(f"recorded: {path} is not a readable .npz file ({exc})") from None
    differ = [k for k in RECORDED_SYSTEM if system.get(k) != params.get(k)]
    if system.get("torque_limit", 0) > params.get("torque_limit", 0):
        differ.append("torque_limit")
    if differ:
        shown = ", ".join(f"{k} {system.get(k)} (data: {params.get(k)})" for k in differ)
        raise ValueError(f"recorded: {path} was recorded on another system: {shown}")
    count, size = len(arrays["u"]), params["image_size"]
    expected = {
        "y": (count, n_frames, 1, size, size),
        "y_clean": (count, n_frames, 1, size, size),
        "state": (count, n_frames, 2 * params["n_links"]),
        "u": (count, n_frames, params["n_links"]),
    }
    for key, shape in expected.items():
        if arrays[key].shape != shape:
            raise ValueError(
                f"recorded: {path}'s {key} has shape {list(arrays[key].shape)}, the data need {list(shape)} "
                f"(episodes of duration / frame_dt = {n_frames} frames)"
            )
        if not np.isfinite(arrays[key]).all():
            raise ValueError(f"recorded: {path}'s {key} holds NaN or inf")
    if arrays["y"].dtype != np.uint8 or arrays["y_clean"].dtype != np.uint8:
        raise ValueError(f"recorded: {path}'s frames must be uint8, as the data's")
    return arrays


def file_digest(path: str) -> str:
    """A short hash of a file's bytes (what the cache key records of a recorded file)."""
    import hashlib

    h = hashlib.sha1()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:10]


# ---------------------------------------------------------------------------------- DataModule
class PendulumDataModule(TrajectoryDataModule):
    """Noisy images of an n-link pendulum (defaults: the paper's simple pendulum).

    Batches: ``"y"`` and ``"y_clean"`` float ``[B, 100, 1, H, W]`` in [0, 1] (stored as uint8),
    ``"state"`` float32 ``[B, 100, 2 * n_links]``: joint angles (relative, not wrapped) then joint
    velocities at every frame. The quadruple pendulum of the paper is ``n_links=4, image_size=48,
    n_train=2000, n_test=2000, damping=0.1, max_velocity=0.0``. With ``torque_limit > 0`` the chain is driven:
    batches also hold ``"u"`` float32 ``[B, 100, n_links]``, the joint torques (N m) applied from each frame to
    the next (:func:`excitation`), cached beside the images; a model learns ``x[t+1] = f(x[t], u[t])``.

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
        dt: RK4 integrator step (s); see the module docstring for its accuracy.
        rendering: ``"paper"`` (the paper generator's images) or ``"analytic"`` (round-capped lines, shorter
            chain): see the module doc.
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
        max_energy: an energy bound on the excitation, J above hanging at rest (:func:`chain_energy`; the simple
            pendulum upright at rest has ``2 g = 19.62``): above it, a torque that would add energy is not applied
            that frame (:func:`simulate`), so the data cover the speeds that reach upright without spinning far
            beyond them. ``None`` (the default): no bound.
        closed_loop_share: the share of trajectories identified in closed loop (simple pendulum only; default 0,
            none): a classic controller (:func:`swing_up_balance`) swings them up and holds them upright, with
            ``closed_loop_noise`` times their excitation added for exploration, so the data show the pendulum
            caught and held upright, which random torques within a low limit almost never do. Which trajectories:
            :func:`closed_loop`, by index.
        closed_loop_noise: the share of the excitation added to the controller's torque (default 0.5: a standard
            deviation of ``torque_limit / 4``).
        closed_loop_override: in the closed-loop share, the frames whose excitation exceeds this share of the
            torque limit get the excitation alone, the controller off (default ``None``: never): open-loop pushes at
            the states the controller holds, where its own torque is tied to the state and cannot show what a
            torque does (docs/datasets.md).
        closed_loop_balance: whether the closed-loop share's controller holds the pendulum upright (default true);
            false: it only pumps energy, and within its catch of upright the excitation alone drives the pendulum,
            which falls and is swung up again (no torque near upright depends on the state).
        sensors: what measures the chain, packed per step in this order: ``["image"]`` (the default, the camera),
            ``["angle"]`` (the joint encoders alone) or both. The encoders report :func:`angle_reading` of the
            noised angles, ``[sin q, cos q]`` (``2 n_links`` values per step).
        angle_noise_std: std of the encoders' Gaussian noise on each angle (rad), before the sine and cosine.
        angle_every: the encoders sample every ``angle_every`` frames (NaN between).
        recorded: ``.npz`` files of episodes recorded on this system (the closed loop's ``record``: a learned
            controller's episodes, for identification in closed loop, docs/control.md), appended to the training
            split after the ``n_train`` generated trajectories, in order. Camera data only; each file's system
            (:data:`RECORDED_SYSTEM`) and length must be the data's. The cache key holds each file's hash.
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
        self._validate()

    def _validate(self) -> None:
        def need(ok: bool, message: str) -> None:
            if not ok:
                raise ValueError(message)

        need(self.n_links >= 1, f"n_links must be >= 1, got {self.n_links}")
        need(
            self.n_train >= 1 and self.n_test >= 1,
            f"n_train and n_test must be >= 1, got {self.n_train}, {self.n_test}",
        )
        need(self.line_width > 0, f"line_width must be > 0 pixels, got {self.line_width}")
        need(self.image_size >= 1, f"image_size must be a positive number of pixels, got {self.image_size}")
        if self.rendering == "paper":
            link, smallest = self.image_size / 2 / self.n_links, 2 * self.n_links
        else:
            link = chain_length_pixels(self.image_size, self.line_width) / self.n_links
            smallest = math.ceil(2 * (self.n_links + self.line_width / 2 + 1))
        need(
            link >= 1.0,
            f"image_size {self.image_size} is too small for {self.n_links} links of width {self.line_width} "
            f"({self.rendering} rendering): each link would be {link:.2f} pixels long (needs >= 1); use "
            f"image_size >= {smallest}" + (" or a thinner line_width" if self.rendering == "analytic" else ""),
        )
        need(self.damping >= 0, f"damping must be >= 0 (tau = -damping * velocity), got {self.damping}")
        need(
            self.sensors in (["image"], ["angle"], ["image", "angle"], ["angle", "image"]),
            f"sensors must be [image], [angle] or both (in the order they are packed), got {self.sensors}",
        )
        need(
            self.angle_noise_std > 0 and self.angle_every >= 1,
            f"angle_noise_std must be > 0 (rad) and angle_every >= 1 (frames), got {self.angle_noise_std}, "
            f"{self.angle_every}",
        )
        need(
            self.sensors == ["image"] or not self.normalize,
            "several sensors (or an angle alone) are served unnormalised: set normalize: false",
        )
        need(
            self.torque_limit >= 0 and self.torque_correlation > 0,
            f"torque_limit must be >= 0 (N m; 0: a free chain) and torque_correlation > 0 (s), got "
            f"{self.torque_limit}, {self.torque_correlation}",
        )
        need(
            self.max_energy is None or (self.max_energy > 0 and self.torque_limit > 0),
            f"max_energy bounds the excitation's work: it needs torque_limit > 0 and must be > 0 (J above hanging "
            f"at rest), got max_energy {self.max_energy} with torque_limit {self.torque_limit}",
        )
        need(
            0.0 <= self.closed_loop_share <= 1.0 and self.closed_loop_noise >= 0,
            f"closed_loop_share must be in [0, 1] and closed_loop_noise >= 0, got {self.closed_loop_share}, "
            f"{self.closed_loop_noise}",
        )
        need(
            self.closed_loop_override is None or (self.closed_loop_share and 0 <= self.closed_loop_override < 1),
            f"closed_loop_override hands frames of the closed-loop share to the excitation: it needs "
            f"closed_loop_share > 0 and a share of the torque limit in [0, 1), got {self.closed_loop_override} with "
            f"closed_loop_share {self.closed_loop_share}",
        )
        need(
            self.closed_loop_balance or self.closed_loop_share,
            "closed_loop_balance: false lets the closed-loop share's pendulum fall near upright: it needs "
            "closed_loop_share > 0",
        )
        need(
            not self.closed_loop_share or (self.n_links == 1 and self.torque_limit > 0),
            f"closed_loop_share drives the simple pendulum by a swing-up controller: it needs n_links: 1 and "
            f"torque_limit > 0, got n_links {self.n_links} with torque_limit {self.torque_limit}",
        )
        need(
            self.max_angle >= 0 and self.max_velocity >= 0,
            f"max_angle and max_velocity are half-widths of uniform ranges and must be >= 0, got "
            f"{self.max_angle}, {self.max_velocity}",
        )
        need(self.noise_std >= 0, f"noise_std must be >= 0, got {self.noise_std}")
        need(
            self.dt > 0 and self.frame_dt > 0 and self.duration > 0,
            f"dt, frame_dt and duration must be > 0, got {self.dt}, {self.frame_dt}, {self.duration}",
        )
        steps = self.frame_dt / self.dt
        need(
            abs(steps - round(steps)) < 1e-6 * max(1.0, steps),
            f"frame_dt ({self.frame_dt}) must be a whole multiple of the integrator step dt ({self.dt}): "
            f"use dt = frame_dt / k for an integer k, e.g. {self.frame_dt / max(1, math.ceil(steps))}",
        )
        frames = self.duration / self.frame_dt
        need(
            abs(frames - round(frames)) < 1e-6 * max(1.0, frames) and round(frames) >= 2,
            f"duration ({self.duration}) must be a whole multiple (>= 2) of frame_dt ({self.frame_dt}): "
            f"the trajectory has duration / frame_dt frames",
        )
        need(self.workers >= 1, f"workers must be >= 1 (or null for all available cores), got {self.workers}")
        need(
            not self.recorded or self.sensors == ["image"],
            f"recorded episodes are camera data: they need sensors [image], got {self.sensors}",
        )
        need(self.seed >= 0, f"seed must be >= 0 (it seeds numpy's SeedSequence), got {self.seed}")

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
        """This data set's pendulum as a system to control, frame by frame (:class:`PendulumEnvironment`)."""
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
        tasks = [(params, SPLIT_IDS[split], s, min(s + CHUNK_SIZE, count)) for s in range(0, count, CHUNK_SIZE)]
        workers = min(self.workers, len(tasks))
        bar = tqdm(total=count, desc=f"pendulum {split} ({n} link{'s' * (n > 1)}, {workers} workers)", unit="traj")

        def store(start: int, arrays: dict[str, np.ndarray]) -> None:
            for key, a in arrays.items():
                out[key][start : start + len(a)] = a
            bar.update(len(arrays["y"]))

        try:
            _run_tasks(tasks, workers, store)  # a failure: one DataGenerationError, the pool ended
        finally:
            bar.close()
        if split == "train" and self.recorded:  # the recorded episodes after the generated trajectories
            params = self.system_params()
            files = [read_recorded(path, params, frames) for path in self.recorded]
            out = {key: np.concatenate([a, *(f[key] for f in files)]) for key, a in out.items()}
        return out
