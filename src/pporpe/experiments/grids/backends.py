"""Where jobs run: a local process pool or a Ray cluster, one worker per job.

Each job goes through :func:`run_job`, which locks its run folders while it trains them.

Ctrl-C or SIGTERM: the local workers ignore both (a terminal or a scheduler sends them to
every process of the group); the parent, asked to stop (its ``stop``), sets an event that
every worker's run loop reads after each unit of work, so each job checkpoints its runs at
that step and reports them ``"interrupted"``; jobs not started yet are cancelled. Ray tasks are
cancelled (their runs keep their last checkpoints).
"""

from __future__ import annotations

import contextlib
import fcntl
import multiprocessing
import os
import signal
import sys
import traceback
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from multiprocessing import get_context
from pathlib import Path
from typing import Any

from ...config import config_from_dict
from ...io import atomic_write_text
from ...runs.cadence import CHECKPOINT_WITHIN_S
from ...runs.kinds import get_kind
from ...runs.stopping import Interrupted
from ...text import count
from .planning import Job
from .progress import GridProgress

__all__ = ["BACKENDS", "run_job", "run_local", "run_ray"]

BACKENDS = ("local", "ray")

RAY_RETRIES = 3
"""How many times Ray runs a job again whose worker died (not for an error in the job:
a failed run is recorded in its folder, and the job returns)."""

_STOP: Any = None
"""In a local worker: the pool's stop event (a ``multiprocessing.Event``), set by the parent
on Ctrl-C; None elsewhere."""


@contextlib.contextmanager
def _run_lock(run_dir: Path) -> Iterator[None]:
    run_dir.mkdir(parents=True, exist_ok=True)
    flags = os.O_WRONLY | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0)  # never through a link
    with os.fdopen(os.open(run_dir / ".lock", flags, 0o666), "w") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def _failure(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}".splitlines()[0]


def _done_or(path: Path, status: dict[str, Any]) -> dict[str, Any]:
    """A run's status after its job stopped: done if it finished, else ``status``."""
    if (path / "done.json").exists():
        return {"run_dir": str(path), "status": "done", "score": None}
    return {"run_dir": str(path), **status}


def run_job(
    home: str,
    runs: list[tuple[str, dict[str, Any]]],
    population: int = 1,
    checkpoint_seconds: float = 0.0,
    checkpoint_within: float = CHECKPOINT_WITHIN_S,
    live_seconds: float | None = None,
) -> list[dict[str, Any]]:
    """Train a queue of runs of one task through one trainer of up to ``population`` slots
    (in a worker); never raises, reports the status of every run. ``checkpoint_seconds``
    (for a population), ``checkpoint_within`` and ``live_seconds`` go to
    :func:`~pporpe.runs.loop.run_queue`.

    ``runs`` holds ``(run_dir, config.json content)`` pairs; ``home`` keeps the queue's
    ``population.json``. Every run folder is locked while the job holds it. A run that
    fails alone leaves its message in ``error.txt``; if the whole job fails, every
    unfinished run of it gets the traceback. Stopped by the pool's stop event (Ctrl-C),
    the job checkpoints its runs and reports the unfinished ones ``"interrupted"``.
    """
    paths = [Path(d) for d, _ in runs]
    try:
        cfgs: list[Any] = []
        for _, cfg_dict in runs:
            data = dict(cfg_dict)
            kind = get_kind(data.pop("kind"))
            cfgs.append(config_from_dict(kind.config_type, data))
        with contextlib.ExitStack() as locks:
            for path in paths:
                locks.enter_context(_run_lock(path))
            from ...runs.loop import run_queue

            results = run_queue(
                list(zip(cfgs, paths, strict=True)),
                capacity=population,
                home=home,
                checkpoint_seconds=checkpoint_seconds if population > 1 else 0.0,
                stop=_STOP.is_set if _STOP is not None else None,
                checkpoint_within=checkpoint_within,
                live_seconds=live_seconds,
            )
        out: list[dict[str, Any]] = []
        for d, res in zip((d for d, _ in runs), results, strict=True):
            if res.error is not None:
                out.append({"run_dir": d, "status": "failed", "error": res.error})
            else:
                score = res.evaluation.median if res.evaluation is not None else None
                out.append({"run_dir": d, "status": "done", "score": score})
        return out
    except Interrupted:
        return [_done_or(path, {"status": "interrupted"}) for path in paths]
    except Exception as exc:
        tb = traceback.format_exc()
        for path in paths:
            if not (path / "done.json").exists():
                with contextlib.suppress(OSError):
                    atomic_write_text(path / "error.txt", tb)
        return [_done_or(path, {"status": "failed", "error": _failure(exc)}) for path in paths]


def _worker_init(stop: Any, environ: dict[str, str]) -> None:
    """Pool initializer: take the grid process's environment, die with the pool, leave
    Ctrl-C to the parent, and keep C-level chatter off the terminal.

    ``environ`` is the grid process's environment when it started the pool (a worker forked
    from the pool's server would otherwise have the server's, from when the server
    started); torch gets the thread count a process started with it would have. The worker
    gets SIGKILL when its parent (the pool's server, which ends with the grid process) dies
    (Linux). It ignores SIGINT and SIGTERM (a terminal or a scheduler sends them to every
    process of the job): the parent asks it to stop through ``stop`` (kept in
    :data:`_STOP`), at a safe point. Its standard output goes to /dev/null at the
    descriptor level (PyBullet prints from C on every connection); tracebacks of failed
    runs are still written to their ``error.txt``.
    """
    global _STOP
    _STOP = stop
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    if sys.platform.startswith("linux"):
        import ctypes

        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    os.environ.clear()
    os.environ.update(environ)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    if "torch" in sys.modules:  # imported by the server: its threads as OMP_NUM_THREADS says
        with contextlib.suppress(ValueError, RuntimeError):
            sys.modules["torch"].set_num_threads(int(os.environ["OMP_NUM_THREADS"]))
    with contextlib.suppress(OSError):
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 1)
        os.close(devnull)


POOL_PRELOAD = ["pporpe.experiments.grids.pool_preload"]
"""What the pool's server imports before it forks a worker (:mod:`.pool_preload`)."""


def _pool_context() -> Any:
    """The local pool's start method: workers forked from one server process that imported
    :data:`POOL_PRELOAD` (``forkserver``: one process pays for the imports, not every
    worker), or started fresh (``spawn``) where there is no forkserver (Windows, macOS
    builds without it). The server is one per grid process, started at its first pool."""
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return get_context("spawn")
    ctx = get_context("forkserver")
    ctx.set_forkserver_preload(POOL_PRELOAD)
    return ctx


def _interrupted(job: Job) -> list[dict[str, Any]]:
    """The statuses of a job that was cancelled before it started."""
    return [_done_or(Path(d), {"status": "interrupted"}) for d, _ in job.runs]


def run_local(
    jobs: list[Job],
    workers: int,
    progress: GridProgress,
    checkpoint_seconds: float,
    stop: Callable[[], bool] | None = None,
    checkpoint_within: float = CHECKPOINT_WITHIN_S,
) -> list[dict[str, Any]]:
    """Run ``jobs`` on a pool of ``workers`` processes (:func:`_pool_context`); every job's
    run statuses.
    When ``stop()`` turns True (Ctrl-C), the running jobs stop at a safe point with their
    checkpoints and the others are cancelled: their runs are ``"interrupted"``. The jobs
    write their runs' live progress when the bar reads it (:attr:`GridProgress.live_seconds`)."""
    results: list[dict[str, Any]] = []
    ctx = _pool_context()
    event = ctx.Event()
    pool = ProcessPoolExecutor(
        workers, ctx, initializer=_worker_init, initargs=(event, dict(os.environ))
    )
    try:
        cadence = (checkpoint_seconds, checkpoint_within, progress.live_seconds)
        futures = {pool.submit(run_job, j.home, j.runs, j.population, *cadence): j for j in jobs}
        pending = set(futures)
        progress.poll(min(workers, len(pending)), results)
        while pending:
            finished, pending = wait(pending, timeout=2.0, return_when=FIRST_COMPLETED)
            for fut in finished:
                results.extend(_interrupted(futures[fut]) if fut.cancelled() else fut.result())
            if stop is not None and stop() and not event.is_set():
                event.set()  # every worker's run loop stops at its next step
                for fut in pending:
                    fut.cancel()  # those not started yet
            progress.poll(min(workers, len(pending)), results)
    except BaseException:  # a second Ctrl-C: no waiting for the jobs' statuses
        event.set()
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown()
    return results


def run_ray(
    jobs: list[Job],
    address: str | None,
    progress: GridProgress,
    checkpoint_seconds: float,
    stop: Callable[[], bool] | None = None,
    checkpoint_within: float = CHECKPOINT_WITHIN_S,
) -> list[dict[str, Any]]:
    """Run ``jobs`` as Ray tasks of one CPU each (on the cluster at ``address``, or a local
    one started for the call); every job's run statuses. When ``stop()`` turns True
    (Ctrl-C), the tasks left are cancelled: their runs keep their last checkpoints and are
    ``"interrupted"``. Ray's own log lines stay off the terminal (:func:`_start_ray`)."""
    try:
        import ray
    except ImportError:
        raise ValueError(
            '--backend ray needs Ray: pip install -c constraints.txt "pporpe[ray]"'
        ) from None
    started_here = not ray.is_initialized()
    if started_here:
        _start_ray(ray, address, progress)
    try:
        # a worker that dies (killed, out of memory, its node lost) is retried: the task
        # resumes its runs from their checkpoints, with the same records
        remote = ray.remote(num_cpus=1, max_retries=RAY_RETRIES)(run_job)
        cadence = (checkpoint_seconds, checkpoint_within, progress.live_seconds)
        job_of = {remote.remote(j.home, j.runs, j.population, *cadence): j for j in jobs}
        refs = list(job_of)
        results: list[dict[str, Any]] = []
        total_cpus = max(int(ray.cluster_resources().get("CPU", 1)), 1)
        progress.poll(min(total_cpus, len(refs)), results)
        while refs:
            ready, refs = ray.wait(refs, num_returns=1, timeout=2.0)
            for ref in ready:
                results.extend(ray.get(ref))
            if stop is not None and stop():
                for ref in refs:
                    ray.cancel(ref)
                    results.extend(_interrupted(job_of[ref]))
                refs = []
            progress.poll(min(total_cpus, len(refs)), results)
        return results
    finally:
        if started_here:
            ray.shutdown()


def _start_ray(ray: Any, address: str | None, progress: GridProgress) -> None:
    """Connect to the Ray cluster at ``address`` (or start a local one) without Ray's log
    lines on the terminal, where they would break the grid's bar (its token warning, "Started
    a local Ray instance"; errors still show); one line above the bar says where the jobs run
    instead. The workers' output stays on the cluster (``log_to_driver=False``)."""
    import logging

    context = ray.init(
        address=address, include_dashboard=False, log_to_driver=False,
        logging_level=logging.ERROR,
    )  # fmt: skip
    cpus = int(ray.cluster_resources().get("CPU", 0))
    where = getattr(context, "address_info", {}).get("gcs_address") or address or "local"
    progress.note(f"ray: {count(cpus, 'CPU')} at {where}")
