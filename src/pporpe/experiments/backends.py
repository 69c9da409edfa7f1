"""Where jobs run: a local process pool or a Ray cluster, one worker per job.

Each job goes through :func:`run_job`, which locks its run folders while it trains them.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import signal
import sys
import traceback
from collections.abc import Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from multiprocessing import get_context
from pathlib import Path
from typing import Any

from ..config import config_from_dict
from ..io import atomic_write_text
from ..runs.kinds import get_kind
from .planning import Job
from .progress import GridProgress

__all__ = ["BACKENDS", "run_job", "run_local", "run_ray"]

BACKENDS = ("local", "ray")

RAY_RETRIES = 3
"""How many times Ray runs a job again whose worker died (not for an error in the job:
a failed run is recorded in its folder, and the job returns)."""


@contextlib.contextmanager
def _run_lock(run_dir: Path) -> Iterator[None]:
    run_dir.mkdir(parents=True, exist_ok=True)
    with open(run_dir / ".lock", "w") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def _failure(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}".splitlines()[0]


def run_job(
    home: str,
    runs: list[tuple[str, dict[str, Any]]],
    population: int = 1,
    checkpoint_seconds: float = 0.0,
) -> list[dict[str, Any]]:
    """Train a queue of runs of one task through one trainer of up to ``population`` slots
    (in a worker); never raises, reports the status of every run.

    ``runs`` holds ``(run_dir, config.json content)`` pairs; ``home`` keeps the queue's
    ``population.json``. Every run folder is locked while the job holds it. A run that
    fails alone leaves its message in ``error.txt``; if the whole job fails, every
    unfinished run of it gets the traceback.
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
            from ..runs.loop import run_queue

            results = run_queue(
                list(zip(cfgs, paths, strict=True)),
                capacity=population,
                home=home,
                checkpoint_seconds=checkpoint_seconds if population > 1 else 0.0,
            )
        out: list[dict[str, Any]] = []
        for d, res in zip((d for d, _ in runs), results, strict=True):
            if res.error is not None:
                out.append({"run_dir": d, "status": "failed", "error": res.error})
            else:
                score = res.evaluation.median if res.evaluation is not None else None
                out.append({"run_dir": d, "status": "done", "score": score})
        return out
    except Exception as exc:
        tb = traceback.format_exc()
        failed: list[dict[str, Any]] = []
        for path in paths:
            if (path / "done.json").exists():
                failed.append({"run_dir": str(path), "status": "done", "score": None})
                continue
            with contextlib.suppress(OSError):
                atomic_write_text(path / "error.txt", tb)
            failed.append({"run_dir": str(path), "status": "failed", "error": _failure(exc)})
        return failed


def _worker_init() -> None:
    """Pool initializer: die with the parent, and keep C-level chatter off the terminal.

    The worker gets SIGKILL when the parent process dies (Linux). Its standard output
    goes to /dev/null at the descriptor level (PyBullet prints from C on every
    connection); tracebacks of failed runs are still written to their ``error.txt``.
    """
    if sys.platform.startswith("linux"):
        import ctypes

        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    with contextlib.suppress(OSError):
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 1)
        os.close(devnull)


def run_local(
    jobs: list[Job], workers: int, progress: GridProgress, checkpoint_seconds: float
) -> list[dict[str, Any]]:
    """Run ``jobs`` on a pool of ``workers`` spawned processes; every job's run statuses."""
    results: list[dict[str, Any]] = []
    ctx = get_context("spawn")
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_worker_init) as pool:
        pending: set[Future[list[dict[str, Any]]]] = {
            pool.submit(run_job, j.home, j.runs, j.population, checkpoint_seconds) for j in jobs
        }
        progress.poll(min(workers, len(pending)), results)
        while pending:
            finished, pending = wait(pending, timeout=2.0, return_when=FIRST_COMPLETED)
            for fut in finished:
                results.extend(fut.result())
            progress.poll(min(workers, len(pending)), results)
    return results


def run_ray(
    jobs: list[Job], address: str | None, progress: GridProgress, checkpoint_seconds: float
) -> list[dict[str, Any]]:
    """Run ``jobs`` as Ray tasks of one CPU each (on the cluster at ``address``, or a local
    one started for the call); every job's run statuses."""
    try:
        import ray
    except ImportError:
        raise ValueError(
            '--backend ray needs Ray: pip install -c constraints.txt "pporpe[ray]"'
        ) from None
    started_here = not ray.is_initialized()
    if started_here:
        ray.init(address=address, include_dashboard=False, log_to_driver=False)
    try:
        # a worker that dies (killed, out of memory, its node lost) is retried: the task
        # resumes its runs from their checkpoints, with the same records
        remote = ray.remote(num_cpus=1, max_retries=RAY_RETRIES)(run_job)
        refs = [remote.remote(j.home, j.runs, j.population, checkpoint_seconds) for j in jobs]
        results: list[dict[str, Any]] = []
        total_cpus = max(int(ray.cluster_resources().get("CPU", 1)), 1)
        progress.poll(min(total_cpus, len(refs)), results)
        while refs:
            ready, refs = ray.wait(refs, num_returns=1, timeout=2.0)
            for ref in ready:
                results.extend(ray.get(ref))
            progress.poll(min(total_cpus, len(refs)), results)
        return results
    finally:
        if started_here:
            ray.shutdown()
