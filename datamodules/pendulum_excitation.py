"""The torques that drive the pendulum's data: a random excitation, a classic swing-up controller, and the
data's torques in feedback (the controller on a share of the trajectories, an energy bound).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from datamodules.pendulum_sim import GRAVITY, chain_energy


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
    """The data's torques in feedback (:func:`~datamodules.pendulum_sim.simulate`'s ``policy``) for trajectories
    ``indices`` of a split, or ``None`` where they are the excitation's as drawn. Two parts, in this order: with
    ``closed_loop_share``, the trajectories :func:`closed_loop` picks get :func:`swing_up_balance` plus
    ``closed_loop_noise`` times their excitation (exploration), clipped to ``+-torque_limit``, except, with
    ``closed_loop_override``, the frames whose excitation exceeds that share of the limit, and, with
    ``closed_loop_balance`` false, those within the controller's catch of upright: those get the excitation alone; with
    ``max_energy``, a chain above the bound gets no torque that would do positive work (``u . v > 0``: that frame's
    torque is 0)."""
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
