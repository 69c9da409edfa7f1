"""Run a grid of independent training runs on a local process pool or a Ray cluster.

Each run trains and evaluates into ``OUT/<env>/<method>/seed<k>`` through the one run
loop (:func:`pporpe.runs.loop.run_queue`); online runs of one task share a population
(:func:`plan_jobs`). Runs checkpoint and resume, so running :func:`reproduce` again with
the same arguments after a crash (even SIGKILL) skips finished runs and resumes
unfinished ones from their last checkpoint, with the same packing.

Safety against two processes on one run: local workers die with their parent
(``PR_SET_PDEATHSIG`` on Linux), and every run holds an exclusive lock on
``<run>/.lock`` while it trains.

A failed run leaves ``error.txt`` (its traceback) in its folder; the others go on.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import math
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

__all__ = ["GridOutcome", "Job", "plan_jobs", "reproduce", "run_job"]

BACKENDS = ("local", "ray")

DEFAULT_POPULATION = 30
"""Online runs trained at once by one worker: benchmarks/throughput.py measured the cost
per member-step falling 3.2x from K = 1 to 15 and 4.1-4.7x to K = 30 (0.62-0.69 ms), with
little more to gain at K = 60; 30 is also the paper's runs per task."""

DEFAULT_CHECKPOINT_SECONDS = 60.0
"""At most one population checkpoint a minute: a population's state is megabytes."""


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


@dataclass(frozen=True)
class Job:
    """Runs of one task and network shape that one worker trains through one trainer."""

    home: str
    """Folder of the job's ``population.json``."""
    runs: list[tuple[str, dict[str, Any]]]
    """``(run_dir, config.json content)`` in queue order."""
    population: int
    """Slots of the trainer: runs trained at once."""


def plan_jobs(
    runs: list[tuple[Path, Any]], out_dir: Path, population: int, workers: int
) -> list[Job]:
    """Pack runs into jobs: runs that can share a trainer (same kind, task and network
    shape: :meth:`~pporpe.runs.kinds.LearnerKind.pack_key`) form a queue; a queue is split
    into as many jobs as it takes to keep ``workers`` busy (at most one per run), and each
    job trains up to ``population`` runs at once, refilling a slot when a run finishes.
    The packing depends only on the spec, ``population``, ``workers`` and which runs are
    unfinished."""
    groups: dict[Any, list[tuple[Path, Any]]] = {}
    for run_dir, cfg in runs:
        kind = kind_of(cfg)
        groups.setdefault((kind.name, kind.pack_key(cfg)), []).append((run_dir, cfg))
    total = sum(len(g) for g in groups.values())
    jobs: list[Job] = []
    for members in groups.values():
        kind = kind_of(members[0][1])
        cap = population if kind.name == "online" else 1
        n_jobs = max(1, round(workers * len(members) / total)) if total else 1
        if cap == 1:
            n_jobs = len(members)
        n_jobs = min(n_jobs, len(members))
        size = -(-len(members) // n_jobs)
        for j in range(0, len(members), size):
            chunk = members[j : j + size]
            home = chunk[0][0] if len(chunk) == 1 else out_dir / "populations" / _job_name(chunk)
            jobs.append(
                Job(
                    str(home),
                    [(str(d), config_json(kind, c)) for d, c in chunk],
                    min(cap, len(chunk)),
                )
            )
    return jobs


def _job_name(chunk: list[tuple[Path, Any]]) -> str:
    first, last = chunk[0][0], chunk[-1][0]
    return f"{first.parent.parent.name}-{len(chunk)}runs-{first.parent.name}-{first.name}-" + (
        f"{last.parent.name}-{last.name}"
    )


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


@dataclass(frozen=True)
class RunProgress:
    """What a run has on disk, as the progress bar reads it."""

    episodes: int
    """Training episodes logged, at most the budget (all of it once the run is done)."""
    steps: int
    """Environment steps of the logged episodes (the last row's ``total_steps``)."""
    steps_left: float | None
    """Guess of the steps still to run: the episodes left times the mean length of the last
    :data:`RECENT_EPISODES` logged; 0 once done; ``None`` before the first checkpoint."""


RECENT_EPISODES = 10
"""Logged episodes whose mean length stands for the length of the episodes to come."""


def run_progress(run_dir: Path, budget: int) -> RunProgress:
    """Read a run's ``episodes.csv`` (written at each checkpoint) for the progress bar.

    Episodes grow longer as a run learns (Ant's and HalfCheetah's from 20 steps to 1000),
    so the time left is estimated in environment steps, not in episodes. A file without
    the ``total_steps`` and ``length`` columns, or with values that are not numbers, counts
    every episode as one step. Only the last rows are parsed: this runs every half minute
    over every run of a grid, and :func:`pporpe.runs.logger.read_records` costs about 20 us
    a row (a second per count for 30 runs of 2000 episodes).
    """
    done = (run_dir / "done.json").exists()
    try:
        with open(run_dir / "episodes.csv", encoding="utf-8", errors="replace") as f:
            lines = f.read().splitlines()
    except OSError:
        lines = []
    rows = [ln for ln in lines[1:] if ln]
    if not rows:
        return RunProgress(budget, 0, 0.0) if done else RunProgress(0, 0, None)
    header, n = lines[0].split(","), min(len(rows), budget)
    steps, length = len(rows), 1.0
    if "total_steps" in header and "length" in header:
        i_steps, i_len = header.index("total_steps"), header.index("length")
        # A file someone edited by hand must not stop the grid: count its rows instead.
        with contextlib.suppress(ValueError, IndexError):
            recent = [float(r.split(",")[i_len]) for r in rows[-RECENT_EPISODES:]]
            steps, length = int(float(rows[-1].split(",")[i_steps])), sum(recent) / len(recent)
    if done:
        return RunProgress(budget, steps, 0.0)
    return RunProgress(n, steps, (budget - n) * length)


class _Progress:
    """One overall progress bar: runs done (read from the run folders, so that runs
    finishing inside a population count at once), failed, jobs running, and, for runs with
    an episode budget, the episodes on disk with the time left at their rate (a population
    finishes its runs together, so the run count alone stays at 0 for most of a task)."""

    BAR_FORMAT = "{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} [{elapsed}{postfix}]"
    """tqdm's default bar without its own time left and rate ("<6:32:04, 811.18s/run"):
    they extrapolate the count of finished runs, which in populations finish together, so
    the only estimate shown is the bar's own ``left~``, from the steps still to run."""
    COUNT_EVERY_S = 30.0
    """Seconds between two counts of the runs' episodes (each reads every episodes.csv)."""
    RATE_COUNTS = 10
    """Counts (the last five minutes) whose rate gives the time left."""

    def __init__(
        self,
        total: int,
        done: int,
        runs: list[Path],
        enabled: bool,
        budgets: list[int | None] | None = None,
        file: Any = None,
    ) -> None:
        self.bar: Any = None
        self.initial, self.runs = done, runs
        self.failed = 0
        self.episode_runs = [
            (r, b) for r, b in zip(runs, budgets or [None] * len(runs), strict=True) if b
        ]
        self.episodes_total = sum(b for _, b in self.episode_runs)
        self.history: list[tuple[float, int]] = []
        self.t_counted = -math.inf
        self.episodes_text = ""
        self.file = file if file is not None else sys.stderr
        # On a terminal the bar's clock moves, so every poll redraws it; asked once.
        isatty = getattr(self.file, "isatty", None)
        self.redraw_every_poll = isatty is not None and bool(isatty())
        self.shown: tuple[Any, ...] | None = None
        if enabled:
            from tqdm import tqdm

            self.bar = tqdm(
                total=total,
                initial=done,
                unit="run",
                desc="grid",
                dynamic_ncols=True,
                file=self.file,
                bar_format=self.BAR_FORMAT,
            )

    def count_episodes(self) -> str:
        """``"N/M, left~T min"``: episodes on disk and the time left, the steps still to run
        (:func:`run_progress`) at the step rate of the last few counts. Episodes grow longer
        as runs learn, so neither the episode rate nor an old step rate is a good guess."""
        progress = [run_progress(r, b) for r, b in self.episode_runs]
        n = sum(p.episodes for p in progress)
        steps = sum(p.steps for p in progress)
        now = time.perf_counter()
        self.history = [*self.history[-(self.RATE_COUNTS - 1) :], (now, steps)]
        text = f"{n}/{self.episodes_total}"
        t0, steps0 = self.history[0]
        gained = steps - steps0
        known = [p.steps_left for p in progress if p.steps_left is not None]
        if gained > 0 and n < self.episodes_total and known:
            # A run without a checkpoint yet is guessed at the mean of the others.
            steps_left = sum(known) * len(progress) / len(known)
            left = steps_left * (now - t0) / gained
            text += f", left~{left / 60:.0f} min"
        return text

    def poll(self, jobs_running: int, results: list[dict[str, Any]]) -> None:
        """Count finished runs on disk and failed ones in the jobs' results; show the jobs
        still running and, every half minute, the episodes on disk. On a terminal the bar is
        redrawn at every poll (its clock moves); into a file or a pipe only when what it
        shows changed, so that a log of a long grid holds a line per change, not one every
        two seconds."""
        if self.bar is None:
            return
        done = sum((r / "done.json").exists() for r in self.runs)
        self.failed = sum(res["status"] != "done" for res in results)
        self.bar.n = self.initial + done + self.failed
        if self.episode_runs and time.perf_counter() - self.t_counted >= self.COUNT_EVERY_S:
            self.episodes_text = self.count_episodes()
            self.t_counted = time.perf_counter()
        postfix: dict[str, Any] = {"jobs": jobs_running, "failed": self.failed}
        if self.episodes_text:
            postfix["episodes"] = self.episodes_text
        self.bar.set_postfix(postfix, refresh=False)
        shown = (self.bar.n, *postfix.items())
        if self.redraw_every_poll or shown != self.shown:
            self.bar.refresh()
            self.shown = shown

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _run_local(
    jobs: list[Job], workers: int, progress: _Progress, checkpoint_seconds: float
) -> list[dict[str, Any]]:
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


def _run_ray(
    jobs: list[Job], address: str | None, progress: _Progress, checkpoint_seconds: float
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
        remote = ray.remote(num_cpus=1, max_retries=0)(run_job)
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


def merged_grid_summary(path: Path, spec: GridSpec) -> dict[str, Any]:
    """``spec``'s summary, keeping the runs of an earlier ``grid.json`` at ``path``.

    Grids run in chunks (one task, or a block of seeds, at a time) into one folder then
    report together: a run of an earlier spec stays listed, in its place, and a run of
    this spec replaces its entry (a changed configuration of the same run is refused by
    the run folder itself).
    """
    summary = spec_summary(spec)
    if not path.exists():
        return summary
    try:
        old = json.loads(path.read_text())
        old_runs = {r["key"]: r for r in old["runs"]}
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: not a grid summary written by pporpe ({exc})") from None
    old_runs.update({r["key"]: r for r in summary["runs"]})
    return {**summary, "runs": list(old_runs.values())}


def reproduce(
    spec: GridSpec,
    out: str | Path,
    backend: str = "local",
    workers: int | None = None,
    address: str | None = None,
    progress: bool = True,
    population: int = DEFAULT_POPULATION,
    checkpoint_seconds: float = DEFAULT_CHECKPOINT_SECONDS,
    whole: GridSpec | None = None,
) -> GridOutcome:
    """Run every run of ``spec`` into ``out`` (skipping finished ones); return the outcome.

    ``whole``: the grid ``spec`` is a chunk of (:func:`~.grid.select_runs`); ``grid.json``
    then lists all of its runs, so that the report counts what is still missing.

    Online runs of one task are trained ``population`` at a time by one worker
    (:func:`plan_jobs`); their checkpoints are written at most every
    ``checkpoint_seconds``.
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {list(BACKENDS)}; got {backend!r}")
    if workers is not None and not (
        isinstance(workers, int) and not isinstance(workers, bool) and workers >= 1
    ):
        raise ValueError(f"workers must be an int >= 1; got {workers!r}")
    if address is not None and backend != "ray":
        raise ValueError("--address is only for --backend ray")
    if not (isinstance(population, int) and not isinstance(population, bool) and population >= 1):
        raise ValueError(f"population must be an int >= 1; got population={population!r}")
    if not (
        isinstance(checkpoint_seconds, int | float)
        and not isinstance(checkpoint_seconds, bool)
        and 0 <= checkpoint_seconds < float("inf")
    ):
        raise ValueError(
            "checkpoint_seconds must be a number >= 0; "
            f"got checkpoint_seconds={checkpoint_seconds!r}"
        )
    out_dir = Path(out).resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    listed = spec if whole is None else whole  # a chunk lists the whole grid
    atomic_write_json(out_dir / "grid.json", merged_grid_summary(out_dir / "grid.json", listed))

    t0 = time.perf_counter()
    skipped: list[str] = []
    todo: list[tuple[Path, Any]] = []
    by_dir: dict[str, RunSpec] = {}
    for run in spec.runs:
        run_dir = out_dir / run.key
        by_dir[str(run_dir)] = run
        if (run_dir / "done.json").exists():
            skipped.append(run.key)
        else:
            todo.append((run_dir, run.config))
    n_workers = workers or os.cpu_count() or 1
    jobs = plan_jobs(todo, out_dir, population, n_workers) if todo else []

    budgets = [getattr(cfg, "episodes", None) for _, cfg in todo]
    bar = _Progress(len(spec.runs), len(skipped), [d for d, _ in todo], progress, budgets)
    try:
        if not jobs:
            results: list[dict[str, Any]] = []
        elif backend == "local":
            results = _run_local(jobs, min(n_workers, len(jobs)), bar, checkpoint_seconds)
        else:
            results = _run_ray(jobs, address, bar, checkpoint_seconds)
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
