"""The n-link planar pendulum of the paper: its Pinocchio model, RK4 integration and mechanical energy.

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
states drawn like the paper's). Cost: ~7 ms (1 link) and ~16 ms (4 links) of dynamics per trajectory, ~1 ms
rendering, 1-2 ms noise, on one core.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

GRAVITY = 9.81


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
            :func:`~datamodules.pendulum_excitation.data_policy`). ``None``: the torques as given. Torques past the
            last frame are left as given.

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
