"""The pendulum's trajectories generated: simulated, rendered and noised in chunks, in a pool of worker processes
(or in this process), with one error naming the cause of any failure.

Generation is deterministic given ``seed``: trajectory ``i`` of split ``s`` draws its initial state
and its noise from ``np.random.default_rng([seed, s, i])`` (``s = 0`` train, ``1`` test), and the
simulation of a trajectory involves only element-wise arithmetic and its own ``pin.aba`` calls,
so the arrays do not depend on ``workers`` or on how trajectories are grouped. On another installation
(numpy build, CPU) the noise may differ: numpy guarantees its streams only within one build and
machine (docs/datasets.md has a measured case).
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from typing import Any

import numpy as np

from datamodules.pendulum_excitation import data_policy, torques_of
from datamodules.pendulum_render import angle_reading, quantize, render
from datamodules.pendulum_sim import pendulum_model, simulate

CHUNK_SIZE = 32  # trajectories per worker task (simulated together to amortise Python overhead)
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


def chunk_tasks(params: dict[str, Any], split_id: int, count: int) -> list[tuple[dict[str, Any], int, int, int]]:
    """The worker tasks of a split's ``count`` trajectories, :data:`CHUNK_SIZE` per task (:func:`run_tasks`'s)."""
    return [(params, split_id, s, min(s + CHUNK_SIZE, count)) for s in range(0, count, CHUNK_SIZE)]


def generate_chunk(params: dict[str, Any], split_id: int, start: int, stop: int) -> dict[str, np.ndarray]:
    """Trajectories ``start..stop-1`` of a split: ``{"y", "y_clean", "state"}`` (see the module doc).

    ``params`` is :meth:`datamodules.pendulum.PendulumDataModule.generator_params`. Runs in a pool worker (or in the
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


def run_tasks(tasks: list, workers: int, store: Callable[[int, dict[str, np.ndarray]], None]) -> None:
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
