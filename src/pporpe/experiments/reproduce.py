"""Run a grid of independent training runs on a local process pool or a Ray cluster.

Each run trains and evaluates into ``OUT/<env>/<method>/seed<k>`` through
:func:`pporpe.runs.train`, which checkpoints at episode boundaries and resumes. So
running :func:`reproduce` again with the same arguments after a crash (even SIGKILL)
skips finished runs and resumes unfinished ones from their last checkpoint.

Safety against two processes on one run: local workers die with their parent
(``PR_SET_PDEATHSIG`` on Linux), and every run holds an exclusive lock on
``<run>/.lock`` while it trains.

A failed run leaves ``error.txt`` (its traceback) in its folder; the others go on.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import signal
import sys
import time
import traceback
from collections.abc import Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path
from typing import Any

from ..config import config_from_dict
from ..io import atomic_write_json, atomic_write_text
from ..runs.folder import config_json
from ..runs.kinds import get_kind, kind_of
from .grid import GridSpec, RunSpec, spec_summary

__all__ = ["GridOutcome", "reproduce", "run_one"]

BACKENDS = ("local", "ray")


@dataclass(frozen=True)
class GridOutcome:
    """Status of every run after :func:`reproduce`."""

    done: list[str]
    """Keys of finished runs (including those skipped because already done)."""
    failed: dict[str, str]
    """Keys of failed runs, with the last line of their error."""
    skipped: list[str]
    """Keys that were already finished when this call started."""
    wall_time: float
    """Seconds this call took."""

    @property
    def ok(self) -> bool:
        """Whether every run finished."""
        return not self.failed


@contextlib.contextmanager
def _run_lock(run_dir: Path) -> Iterator[None]:
    run_dir.mkdir(parents=True, exist_ok=True)
    with open(run_dir / ".lock", "w") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def run_one(run_dir: str, cfg_dict: dict[str, Any]) -> dict[str, Any]:
    """Train and evaluate one run (in a worker); never raises, reports the status.

    ``cfg_dict`` is the run's ``config.json`` content: its learner kind and settings.
    """
    path = Path(run_dir)
    try:
        data = dict(cfg_dict)
        kind = get_kind(data.pop("kind"))
        cfg: Any = config_from_dict(kind.config_type, data)
        with _run_lock(path):
            (path / "error.txt").unlink(missing_ok=True)
            from ..runs.loop import train

            result = train(cfg, path, progress=False)
        score = result.evaluation.median if result.evaluation is not None else None
        return {"run_dir": run_dir, "status": "done", "score": score}
    except Exception as exc:
        tb = traceback.format_exc()
        with contextlib.suppress(OSError):
            atomic_write_text(path / "error.txt", tb)
        return {
            "run_dir": run_dir,
            "status": "failed",
            "error": f"{type(exc).__name__}: {exc}".splitlines()[0],
        }


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


class _Progress:
    """One overall progress bar: runs done, running, failed, time left."""

    def __init__(self, total: int, done: int, enabled: bool) -> None:
        self.bar: Any = None
        self.failed = 0
        if enabled:
            from tqdm import tqdm

            self.bar = tqdm(total=total, initial=done, unit="run", desc="grid", dynamic_ncols=True)

    def update(self, running: int, finished: int = 0, failed: int = 0) -> None:
        self.failed += failed
        if self.bar is not None:
            self.bar.update(finished + failed)
            self.bar.set_postfix(running=running, failed=self.failed)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _run_local(
    jobs: list[tuple[str, dict[str, Any]]], workers: int, progress: _Progress
) -> list[dict[str, Any]]:
    results: list[dict[str, Any]] = []
    ctx = get_context("spawn")
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_worker_init) as pool:
        pending: set[Future[dict[str, Any]]] = {pool.submit(run_one, d, c) for d, c in jobs}
        progress.update(running=min(workers, len(pending)))
        while pending:
            finished, pending = wait(pending, return_when=FIRST_COMPLETED)
            for fut in finished:
                res = fut.result()
                results.append(res)
                ok = res["status"] == "done"
                progress.update(
                    running=min(workers, len(pending)), finished=int(ok), failed=int(not ok)
                )
    return results


def _run_ray(
    jobs: list[tuple[str, dict[str, Any]]], address: str | None, progress: _Progress
) -> list[dict[str, Any]]:
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
        remote = ray.remote(num_cpus=1, max_retries=0)(run_one)
        refs = [remote.remote(d, c) for d, c in jobs]
        results: list[dict[str, Any]] = []
        total_cpus = max(int(ray.cluster_resources().get("CPU", 1)), 1)
        while refs:
            ready, refs = ray.wait(refs, num_returns=1)
            res = ray.get(ready[0])
            results.append(res)
            ok = res["status"] == "done"
            progress.update(
                running=min(total_cpus, len(refs)), finished=int(ok), failed=int(not ok)
            )
        return results
    finally:
        if started_here:
            ray.shutdown()


def reproduce(
    spec: GridSpec,
    out: str | Path,
    backend: str = "local",
    workers: int | None = None,
    address: str | None = None,
    progress: bool = True,
) -> GridOutcome:
    """Run every run of ``spec`` into ``out`` (skipping finished ones); return the outcome."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {list(BACKENDS)}; got {backend!r}")
    if workers is not None and not (isinstance(workers, int) and workers >= 1):
        raise ValueError(f"workers must be an int >= 1; got {workers!r}")
    if address is not None and backend != "ray":
        raise ValueError("--address is only for --backend ray")
    out_dir = Path(out).resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out_dir / "grid.json", spec_summary(spec))

    t0 = time.perf_counter()
    skipped: list[str] = []
    jobs: list[tuple[str, dict[str, Any]]] = []
    by_dir: dict[str, RunSpec] = {}
    for run in spec.runs:
        run_dir = out_dir / run.key
        by_dir[str(run_dir)] = run
        if (run_dir / "done.json").exists():
            skipped.append(run.key)
        else:
            jobs.append((str(run_dir), config_json(kind_of(run.config), run.config)))

    bar = _Progress(len(spec.runs), len(skipped), progress)
    try:
        if not jobs:
            results: list[dict[str, Any]] = []
        elif backend == "local":
            n = workers or os.cpu_count() or 1
            results = _run_local(jobs, min(n, len(jobs)), bar)
        else:
            results = _run_ray(jobs, address, bar)
    finally:
        bar.close()

    done = list(skipped)
    failed: dict[str, str] = {}
    for res in results:
        key = by_dir[res["run_dir"]].key
        if res["status"] == "done":
            done.append(key)
        else:
            failed[key] = res["error"]
    outcome = GridOutcome(
        done=done, failed=failed, skipped=skipped, wall_time=time.perf_counter() - t0
    )
    atomic_write_json(
        out_dir / "status.json",
        {
            "done": sorted(done),
            "failed": failed,
            "skipped": sorted(skipped),
            "wall_time_s": outcome.wall_time,
            "backend": backend,
        },
    )
    return outcome
