"""The grid's progress bar and its estimate of the time left, read from the run folders."""

from __future__ import annotations

import contextlib
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["RECENT_EPISODES", "GridProgress", "RunProgress", "run_progress"]


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


class GridProgress:
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
        self.failed = sum(res["status"] == "failed" for res in results)
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
        """Close the bar (its last state stays on the terminal)."""
        if self.bar is not None:
            self.bar.close()
