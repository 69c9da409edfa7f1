"""``pporpe reproduce``: a grid of training runs on a local process pool or a Ray cluster.

Each run trains and evaluates into ``OUT/<env>/<method>/seed<k>`` through the one run
loop (:func:`pporpe.runs.loop.run_queue`); online runs of one task, and batch runs of one
task and shape, share a population (:func:`~.planning.plan_jobs`). Runs checkpoint and
resume, so running :func:`reproduce` again with the same arguments after a crash (even
SIGKILL) skips finished runs and resumes unfinished ones from their last checkpoint, with
the same packing.

Safety against two processes on one run: local workers die with their parent
(``PR_SET_PDEATHSIG`` on Linux), and every run holds an exclusive lock on
``<run>/.lock`` while it trains (:mod:`.backends`).

A failed run leaves ``error.txt`` (its traceback) in its folder; the others go on.
This module checks the arguments and ties the parts together: planning
(:mod:`.planning`), the backends (:mod:`.backends`), the progress bar (:mod:`.progress`)
and ``grid.json`` (:mod:`.merge`).
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ...envs import make_env
from ...runs.cadence import CHECKPOINT_WITHIN_S
from ...runs.folder import CHECKPOINT, check_checkpoint
from ...runs.links import RUN_WRITES, refuse_linked_path, refuse_links
from ...runs.population_checkpoint import (
    POPULATION_FILE,
    adopt_orphaned_states,
    discard_finished,
)
from ...text import count
from .backends import BACKENDS, run_job, run_local, run_ray
from .merge import merged_grid_summary, write_grid_summary, write_status
from .planning import POPULATIONS, Job, plan_jobs
from .progress import GridProgress
from .spec import GridSpec

__all__ = ["GridOutcome", "Job", "merged_grid_summary", "plan_jobs", "reproduce", "run_job"]

DEFAULT_POPULATION = 4
"""Runs trained at once by one worker: the best K of benchmarks/throughput.py
(benchmarks/results/throughput.json), where the fused engine's member-step is cheapest
(at K = 4 its members' state stays in cache; from K = 8 it does not). The torch engine
gains from larger populations instead (its cost per member-step falls about 4x from
K = 1 to 30): pass ``--population 30`` for a grid it trains. Batch runs
(:class:`pporpe.batch.BatchPopulation`) gain up to K = 30 as well
(benchmarks/results/batch_population.json)."""

DEFAULT_CHECKPOINT_SECONDS = 60.0
"""At most one population checkpoint a minute asked for by the runs' ``checkpoint_every``:
a population's state is megabytes. (By time, whatever the count, every run is checkpointed
30 s into a call, a minute later, then every 2 minutes: :mod:`pporpe.runs.cadence`.)"""


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
    interrupted: list[str] = field(default_factory=list)
    """Keys of the runs stopped by ``stop`` (Ctrl-C), each at its last checkpoint."""

    @property
    def ok(self) -> bool:
        """Whether every run finished."""
        return not self.failed and not self.interrupted


def _is_count(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool) and x >= 1


def _check_arguments(
    backend: str, workers: int | None, address: str | None, population: int, every: float,
    within: float,
) -> None:  # fmt: skip
    """Refuse bad arguments before any work, naming the parameter and what it allows."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {list(BACKENDS)}; got {backend!r}")
    if workers is not None and not _is_count(workers):
        raise ValueError(f"workers must be an int >= 1; got {workers!r}")
    if address is not None and backend != "ray":
        raise ValueError("--address is only for --backend ray")
    if not _is_count(population):
        raise ValueError(f"population must be an int >= 1; got population={population!r}")
    if not (
        isinstance(every, int | float) and not isinstance(every, bool) and 0 <= every < float("inf")
    ):
        raise ValueError(
            f"checkpoint_seconds must be a number >= 0; got checkpoint_seconds={every!r}"
        )
    if isinstance(within, bool) or not isinstance(within, int | float) or not within >= 0:
        raise ValueError(
            f"checkpoint_within must be a number >= 0; got checkpoint_within={within!r}"
        )


def _split_finished(spec: GridSpec, out_dir: Path) -> tuple[list[str], list[tuple[Path, Any]]]:
    """The keys of the runs already done, and ``(run_dir, config)`` of the others."""
    skipped: list[str] = []
    todo: list[tuple[Path, Any]] = []
    for run in spec.runs:
        run_dir = out_dir / run.key
        if (run_dir / "done.json").exists():
            skipped.append(run.key)
        else:
            todo.append((run_dir, run.config))
    return skipped, todo


def _check_tasks(source: str, cfgs: list[Any]) -> None:
    """Build the task of every run still to train, once each, so that a task the learners
    cannot use (discrete actions, a missing package) is refused before any folder is
    written, naming the spec."""
    for env in dict.fromkeys(cfg.env for cfg in cfgs):
        try:
            make_env(env).close()
        except (ValueError, ImportError) as exc:  # ImportError: e.g. Hopper-v3, moved away
            error = ImportError if isinstance(exc, ImportError) else ValueError
            raise error(f"{source}: task {env!r}: {exc}") from None


def _check_checkpoints(jobs: list[Job]) -> None:
    """Refuse, before any work, a checkpoint of the jobs (a run's own or a population's)
    that would run code when read (:func:`~pporpe.runs.folder.check_checkpoint`)."""
    for job in jobs:
        for folder in dict.fromkeys([job.home, *(d for d, _ in job.runs)]):
            if (path := Path(folder) / CHECKPOINT).is_file():
                check_checkpoint(path)


def _check_links(out_dir: Path, todo: list[tuple[Path, Any]], jobs: list[Job]) -> None:
    """Refuse, before any work, a symbolic link where the grid will write: its own files,
    the folders on the way to each run still to train and what the run writes there, the
    populations' homes (:mod:`pporpe.runs.links`)."""
    refuse_links(out_dir, ("grid.json", "status.json", POPULATIONS))
    for run_dir, _ in todo:
        refuse_linked_path(out_dir, run_dir.relative_to(out_dir))
        refuse_links(run_dir, RUN_WRITES)
    for job in jobs:
        home = Path(job.home)
        if home.is_relative_to(out_dir):
            refuse_linked_path(out_dir, home.relative_to(out_dir))
        refuse_links(home, (CHECKPOINT, POPULATION_FILE))


def _discard_finished_populations(populations: Path, progress: bool) -> None:
    """Delete the checkpoints of the populations whose runs have all finished
    (:func:`~pporpe.runs.population_checkpoint.discard_finished`): a population discards its
    own when its last run finishes, so these are left by a grid packed differently before
    (its runs went on in other populations); they hold nothing a run needs."""
    finished = discard_finished(populations)
    if finished and progress:
        print(
            f"removed the checkpoints of {count(len(finished), 'population')} packed before "
            f"(under {populations}): all their runs are done",
            file=sys.stderr,
        )


def _plan(
    spec: GridSpec, out_dir: Path, population: int, workers: int, progress: bool
) -> tuple[list[str], list[tuple[Path, Any]], list[Job]]:
    """The runs already done, the runs still to train and their jobs: every task and every
    checkpoint the jobs will read checked first, and the states of runs in flight in
    populations no longer planned handed to the runs
    (:func:`~pporpe.runs.population_checkpoint.adopt_orphaned_states`)."""
    skipped, todo = _split_finished(spec, out_dir)
    _check_tasks(spec.source, [cfg for _, cfg in todo])
    jobs = plan_jobs(todo, out_dir, population, workers) if todo else []
    _check_links(out_dir, todo, jobs)
    _check_checkpoints(jobs)
    adopted = adopt_orphaned_states(
        out_dir / POPULATIONS, [j.home for j in jobs], [d for j in jobs for d, _ in j.runs]
    )
    if adopted and progress:
        print(
            f"{count(len(adopted), 'run')} in flight in populations packed before "
            f"(under {out_dir / POPULATIONS}) go on from their checkpoints",
            file=sys.stderr,
        )
    return skipped, todo, jobs


def _progress_bar(
    spec: GridSpec, skipped: list[str], todo: list[tuple[Path, Any]], progress: bool
) -> GridProgress:
    """The grid's progress bar over its runs still to train, with their budgets: episodes,
    or steps for a run budgeted in steps."""
    budgets = [getattr(cfg, "episodes", None) for _, cfg in todo]
    step_budgets = [None if b else getattr(cfg, "total_steps", None) for b, (_, cfg) in
                    zip(budgets, todo, strict=True)]  # fmt: skip
    return GridProgress(len(spec.runs), len(skipped), [d for d, _ in todo], progress, budgets,
                        step_budgets=step_budgets)  # fmt: skip


def _run_jobs(
    jobs: list[Job], backend: str, workers: int, address: str | None,
    bar: GridProgress, seconds: tuple[float, float], stop: Callable[[], bool] | None,
) -> list[dict[str, Any]]:  # fmt: skip
    """Every job's run statuses, from the chosen backend (``seconds``: checkpoint_seconds and
    checkpoint_within); the bar is closed after."""
    least, within = seconds
    try:
        if not jobs:
            return []
        if backend == "local":
            return run_local(jobs, min(workers, len(jobs)), bar, least, stop, within)
        return run_ray(jobs, address, bar, least, stop, within)
    finally:
        bar.close()


def _outcome(
    spec: GridSpec, out_dir: Path, skipped: list[str], results: list[dict[str, Any]], t0: float
) -> GridOutcome:
    """The grid's outcome from the jobs' run statuses (``run_dir`` back to the run key)."""
    key_of = {str(out_dir / run.key): run.key for run in spec.runs}
    done = list(skipped)
    failed: dict[str, str] = {}
    interrupted: list[str] = []
    for res in results:
        key = key_of[res["run_dir"]]
        if res["status"] == "done":
            done.append(key)
        elif res["status"] == "interrupted":
            interrupted.append(key)
        else:
            failed[key] = res["error"]
    return GridOutcome(done, failed, skipped, time.perf_counter() - t0, interrupted)


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
    stop: Callable[[], bool] | None = None,
    checkpoint_within: float = CHECKPOINT_WITHIN_S,
) -> GridOutcome:
    """Run every run of ``spec`` into ``out`` (skipping finished ones); return the outcome.

    ``whole``: the grid ``spec`` is a chunk of (:func:`~.grid.select_runs`); ``grid.json``
    then lists all of its runs, so that the report counts what is still missing.

    Online runs of one task (batch runs of one task and shape) are trained ``population``
    at a time by one worker (:func:`~.planning.plan_jobs`); a run in flight in a population
    that this call no longer plans (some runs finished since, or the filter or the worker
    count changed) resumes from that population's checkpoint
    (:func:`~pporpe.runs.population_checkpoint.adopt_orphaned_states`), and at the end the
    checkpoints of populations whose runs have all finished are deleted; the checkpoints
    their ``checkpoint_every`` asks for are written at most every ``checkpoint_seconds``. Whatever
    the count, every run is also checkpointed by time: after a quarter of
    ``checkpoint_within`` seconds, half of it later, then every ``checkpoint_within``
    seconds (:mod:`pporpe.runs.cadence`). ``status.json`` in ``out`` counts the runs of the
    whole grid (:mod:`.merge`); a call that trains nothing leaves it and ``grid.json`` as
    they are.

    ``stop`` is asked every few seconds while jobs run; when it turns True (``pporpe
    reproduce`` passes Ctrl-C's request), every running run is checkpointed at its next
    step and the call returns with those runs, and the ones not started, ``interrupted``.
    """
    seconds = (checkpoint_seconds, checkpoint_within)
    _check_arguments(backend, workers, address, population, *seconds)
    out_dir = Path(out).resolve()
    if out_dir.exists() and not out_dir.is_dir():
        raise ValueError(f"the results folder {out} is an existing file; choose another --out")
    t0 = time.perf_counter()
    n_workers = workers or os.cpu_count() or 1
    skipped, todo, jobs = _plan(spec, out_dir, population, n_workers, progress)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"cannot create the results folder {out}: {exc.strerror}") from None
    listed = spec if whole is None else whole  # a chunk lists the whole grid
    listing_changed = write_grid_summary(out_dir, listed)
    bar = _progress_bar(spec, skipped, todo, progress)
    results = _run_jobs(jobs, backend, n_workers, address, bar, seconds, stop)
    _discard_finished_populations(out_dir / POPULATIONS, progress)

    outcome = _outcome(spec, out_dir, skipped, results, t0)
    wall = outcome.wall_time if jobs else 0.0
    write_status(out_dir, outcome.failed, wall, backend, bool(jobs) or listing_changed)
    return outcome
