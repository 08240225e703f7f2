"""Failures in data-generation workers end the generation at once with one message, and never hang.

Each case runs in a forked child of the test process (its own process group, its stderr in a file) with a time
limit: a generation that hangs (what a ``multiprocessing.Pool`` does when its initializer raises or a worker dies)
fails the test after ``LIMIT`` seconds, and the child and its workers are killed. The child reports what
``generate`` raised, how long it took, the worker processes still alive and the one-line message ``cli.py`` would
print. Patches are made in the child, so forked pool workers inherit them and the test process keeps none.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from datamodules import pendulum_generation as gen
from datamodules.pendulum import PendulumDataModule

pytestmark = pytest.mark.skipif("fork" not in mp.get_all_start_methods(), reason="the cases run in forked children")

LIMIT = 60  # seconds: the generations below take well under a second when nothing hangs
MISSING = "No module named 'pinocchio'"


def _child(scenario, conn, err_path: str) -> None:
    os.setpgid(0, 0)  # one group with its workers: the parent kills them all on a hang
    err = open(err_path, "w", buffering=1)
    os.dup2(err.fileno(), 2)  # the workers' stderr too
    sys.stderr = err
    try:
        conn.send(("returned", scenario()))
    except BaseException as exc:  # noqa: BLE001  (everything is reported to the parent)
        conn.send(("raised", type(exc).__name__, str(exc)))


def run_isolated(scenario, tmp_path: Path):
    """``(outcome, stderr)``: what ``scenario()`` returned or raised in a forked child, and what it printed."""
    ctx = mp.get_context("fork")
    reader, writer = ctx.Pipe(duplex=False)
    err = tmp_path / "stderr.txt"
    proc = ctx.Process(target=_child, args=(scenario, writer, str(err)))
    proc.start()
    writer.close()
    try:
        if not reader.poll(LIMIT):
            pytest.fail(
                f"no answer after {LIMIT} s: the generation hangs; its stderr ends with:\n{err.read_text()[-3000:]}"
            )
        outcome = reader.recv()
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)  # whatever is left of the child's group
        except ProcessLookupError:
            pass
        proc.join()
    return outcome, err.read_text()


def tiny_module(tmp_path: Path, workers: int) -> PendulumDataModule:
    return PendulumDataModule(
        n_train=6, n_test=2, duration=0.5, image_size=8, workers=workers, data_dir=str(tmp_path / "data")
    )


def generate_and_report(dm: PendulumDataModule) -> dict:
    """Generate the training split; report its error, its time, the workers left and the CLI's line."""
    from ssm_ms.cli import user_error

    gen.CHUNK_SIZE = 1  # one task per trajectory: several tasks per worker
    gen._WORKER.clear()  # no model inherited from the test process: every process builds its own
    start = time.perf_counter()
    try:
        dm.generate("train")
    except Exception as exc:  # noqa: BLE001
        return {
            "type": type(exc).__name__,
            "message": str(exc),
            "seconds": time.perf_counter() - start,
            "children": [p.pid for p in mp.active_children()],  # joins the finished ones
            "cli": user_error(exc),
        }
    raise AssertionError("generate did not raise")


def check_failure(outcome, stderr: str, cause: str) -> dict:
    assert outcome[0] == "returned", outcome
    report = outcome[1]
    assert report["type"] == "DataGenerationError"
    assert report["message"] == f"pendulum data generation failed: {cause}"
    assert report["cli"] == (report["message"], 1)  # cli.py prints it as one `error:` line, status 1
    assert report["children"] == []  # the pool is ended: no worker left behind
    assert report["seconds"] < 20
    assert "Traceback" not in stderr and "Exception in initializer" not in stderr  # no worker printed its own
    return report


def _missing_pinocchio(n_links: int) -> None:
    raise ModuleNotFoundError(MISSING, name="pinocchio")


# ------------------------------------------------------------------------------------------------- the pendulum
@pytest.mark.parametrize("workers", [2, 1], ids=["pool", "single-process"])
def test_worker_setup_failure_stops_with_one_message(tmp_path, workers):
    """A process that cannot build its model (pinocchio missing): before, a Pool respawned workers forever."""

    def scenario():
        gen._init_worker = _missing_pinocchio
        return generate_and_report(tiny_module(tmp_path, workers))

    outcome, stderr = run_isolated(scenario, tmp_path)
    check_failure(outcome, stderr, f"ModuleNotFoundError: {MISSING} ({gen.PINOCCHIO_HINT})")
    assert "pip install 'pin" in gen.PINOCCHIO_HINT


@pytest.mark.parametrize("workers", [2, 1], ids=["pool", "single-process"])
def test_task_failure_stops_at_once_with_one_message(tmp_path, workers):
    """A task raising in a worker: the same message as in one process, and the tasks not started are dropped."""
    ran = tmp_path / "ran"
    ran.mkdir()
    original = gen.generate_chunk

    def failing_chunk(params, split_id, start, stop):
        (ran / str(start)).touch()
        if start == 0:
            raise FloatingPointError("the integrator diverged")
        time.sleep(0.2)
        return original(params, split_id, start, stop)

    def scenario():
        gen.generate_chunk = failing_chunk
        dm = tiny_module(tmp_path, workers)
        dm.n_train = 40
        return generate_and_report(dm)

    outcome, stderr = run_isolated(scenario, tmp_path)
    check_failure(outcome, stderr, "FloatingPointError: the integrator diverged")
    assert len(list(ran.iterdir())) <= 8  # of 40 tasks: the generation stopped, not ran to the end


def test_worker_death_stops_with_one_message(tmp_path):
    """A worker killed (the out-of-memory killer) or crashed: before, a Pool lost its task and waited forever."""
    original = gen.generate_chunk

    def dying_chunk(params, split_id, start, stop):
        if start == 2:
            os.kill(os.getpid(), signal.SIGKILL)
        return original(params, split_id, start, stop)

    def scenario():
        gen.generate_chunk = dying_chunk
        return generate_and_report(tiny_module(tmp_path, 2))

    outcome, stderr = run_isolated(scenario, tmp_path)
    check_failure(
        outcome,
        stderr,
        f"a worker process died (exit code {-signal.SIGKILL}): killed (e.g. by the "
        "out-of-memory killer: try fewer `workers`) or crashed",
    )


def test_pool_still_generates_the_single_process_arrays(tmp_path):
    """The pool's arrays do not depend on the number of workers (the determinism the pool must keep)."""

    def scenario():
        gen.CHUNK_SIZE = 2
        return [tiny_module(tmp_path, w).generate("train") for w in (1, 2)]

    outcome, stderr = run_isolated(scenario, tmp_path)
    assert outcome[0] == "returned", outcome
    one, two = outcome[1]
    for key in ("y", "y_clean", "state"):
        np.testing.assert_array_equal(one[key], two[key])


# --------------------------------------------------------------------------------- the DDP benchmark's workers
def _exit_at_once(code: int) -> None:
    os._exit(code)


def _wait_forever() -> None:  # rank 0 blocked in a collective with a dead peer
    while True:
        time.sleep(1)


def test_ddp_benchmark_does_not_wait_for_a_dead_worker(tmp_path):
    """``bench_ddp_nodes.py``: a rank that fails (e.g. its port taken) ends the run instead of ``queue.get()``
    waiting forever for rank 0's results."""
    from benchmarks.bench_ddp_nodes import gather_results

    def scenario():
        ctx = mp.get_context("fork")
        queue = ctx.Queue()
        procs = [ctx.Process(target=_wait_forever), ctx.Process(target=_exit_at_once, args=(3,))]
        for p in procs:
            p.start()
        start = time.perf_counter()
        try:
            gather_results(procs, queue, poll=0.2)
        except RuntimeError as exc:
            return str(exc), time.perf_counter() - start, [p.exitcode for p in procs], mp.active_children()
        raise AssertionError("gather_results did not raise")

    outcome, _ = run_isolated(scenario, tmp_path)
    assert outcome[0] == "returned", outcome
    message, seconds, codes, left = outcome[1]
    assert "rank 1 exited with code 3" in message and seconds < 10
    assert codes[1] == 3 and codes[0] is not None and left == []  # the waiting rank was ended too
