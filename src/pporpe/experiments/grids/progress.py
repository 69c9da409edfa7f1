"""The grid's progress bar and its estimate of the time left, read from the run folders:
the live progress the workers write every few seconds (``progress.json``,
:class:`~pporpe.runs.cadence.LiveProgress`), else the episodes checkpointed so far."""

from __future__ import annotations

import contextlib
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ...limits import MAX_CSV_BYTES
from ...run_files import read_regular_file
from ...runs.cadence import LIVE_SECONDS, RECENT_EPISODES, read_live

__all__ = ["RECENT_EPISODES", "GridProgress", "RunProgress", "run_progress"]


@dataclass(frozen=True)
class RunProgress:
    """How far a run got, as the progress bar reads it."""

    episodes: int
    """Training episodes done, at most the budget (all of it once the run is done)."""
    steps: int
    """Environment steps of those episodes (the last one's ``total_steps``)."""
    steps_left: float | None
    """Guess of the steps still to run: the episodes left times :attr:`length`; 0 once done;
    ``None`` before the run's first episode."""
    length: float | None = None
    """Mean length of the run's last :data:`RECENT_EPISODES` episodes (None: none yet)."""


def _from_csv(run_dir: Path) -> tuple[int, int, float | None]:
    """Rows, steps and the mean recent episode length of ``episodes.csv`` (written at each
    checkpoint). A file without the ``total_steps`` and ``length`` columns, or with values
    that are not numbers, counts every episode as one step. Only the last rows are parsed:
    :func:`pporpe.runs.logger.read_records` costs about 20 us a row (a second per count
    for 30 runs of 2000 episodes)."""
    try:
        raw = read_regular_file(run_dir / "episodes.csv", MAX_CSV_BYTES)
        lines = raw.decode("utf-8", errors="replace").splitlines()
    except ValueError:  # missing, not a file, too large: counted as no episodes
        lines = []
    rows = [ln for ln in lines[1:] if ln]
    if not rows:
        return 0, 0, None
    header = lines[0].split(",")
    steps, length = len(rows), 1.0
    if "total_steps" in header and "length" in header:
        i_steps, i_len = header.index("total_steps"), header.index("length")
        # A file someone edited by hand must not stop the grid: count its rows instead.
        with contextlib.suppress(ValueError, IndexError, OverflowError):
            recent = [float(r.split(",")[i_len]) for r in rows[-RECENT_EPISODES:]]
            steps, length = int(float(rows[-1].split(",")[i_steps])), sum(recent) / len(recent)
    return len(rows), steps, length


def run_progress(run_dir: Path, budget: int, since: float | None = None) -> RunProgress:
    """How far a run got: its live progress if written at or after the wall time ``since``
    (:func:`~pporpe.runs.cadence.read_live`; a worker writes it every few seconds), else
    its ``episodes.csv``.

    Episodes grow longer as a run learns (Ant's and HalfCheetah's from 20 steps to 1000),
    so the time left is estimated in environment steps, not in episodes.
    """
    done = (run_dir / "done.json").exists()
    live = read_live(run_dir, since) if since is not None and not done else None
    if live is not None:
        lengths = live["lengths"]
        n, steps = live["episodes"], live["total_steps"]
        length = sum(lengths) / len(lengths) if lengths else None
    else:
        n, steps, length = _from_csv(run_dir)
    if done:
        return RunProgress(budget, steps, 0.0, length)
    n = min(n, budget)
    return RunProgress(n, steps, None if length is None else (budget - n) * length, length)


def _amount(x: float) -> str:
    """``"950"``, ``"26k"``, ``"1.2M"``: a count of steps, short."""
    if x >= 1e6:
        return f"{x / 1e6:.1f}M"
    return f"{x / 1e3:.0f}k" if x >= 1e4 else f"{x:.0f}"


def _windowed(
    history: list[tuple[float, int]], now: float, gained: int, window: float
) -> list[tuple[float, int]]:
    """``history`` of ``(time, steps gained)`` counts without those older than ``window``
    seconds, with this count ``(now, gained)`` appended."""
    return [*[(t, g) for t, g in history if now - t <= window], (now, gained)]


def _seconds_per_step(history: list[tuple[float, int]]) -> float | None:
    """Seconds per step over ``history`` (:func:`_windowed`), from its last count before
    work began in it (a worker's start-up is no work); None without steps gained since."""
    t_now, g_now = history[-1]
    start = [(t, g) for t, g in history if g == history[0][1]][-1]
    if g_now <= start[1]:
        return None
    return (t_now - start[0]) / (g_now - start[1])


def _minutes(seconds: float) -> str:
    """``"40 s"`` under a minute, ``"12 min"``, ``"3.4 h"`` from an hour on."""
    if seconds < 60:
        return f"{seconds:.0f} s"
    return f"{seconds / 60:.0f} min" if seconds < 3600 else f"{seconds / 3600:.1f} h"


class GridProgress:
    """One overall progress bar: runs done (read from the run folders, so that runs
    finishing inside a population count at once), failed, jobs running, and, for runs with
    an episode budget, the episodes done with the time left at this call's step rate, and
    for runs with a budget in steps (batch PPO) the steps done with theirs (a population
    finishes its runs together, so the run count alone stays at 0 for most of a task)."""

    BAR_FORMAT = "{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} [{elapsed}{postfix}]"
    """tqdm's default bar without its own time left and rate ("<6:32:04, 811.18s/run"):
    they extrapolate the count of finished runs, which in populations finish together, so
    the only estimate shown is the bar's own ``left~``, from the steps still to run."""
    COUNT_EVERY_S = 10.0
    """Seconds between two counts of the runs' episodes on a terminal (three times as long
    into a log file, where every change of the bar is a line)."""
    RATE_WINDOW_S = 300.0
    """The counts of the last five minutes give the rate of the time left."""

    def __init__(
        self,
        total: int,
        done: int,
        runs: list[Path],
        enabled: bool,
        budgets: list[int | None] | None = None,
        file: Any = None,
        clock: Callable[[], float] = time.perf_counter,
        step_budgets: list[int | None] | None = None,
    ) -> None:
        self.bar: Any = None
        self.initial, self.runs = done, runs
        self.failed = 0
        self.episode_runs = [
            (r, b) for r, b in zip(runs, budgets or [None] * len(runs), strict=True) if b
        ]
        self.episodes_total = sum(b for _, b in self.episode_runs)
        self.step_runs = [
            (r, b) for r, b in zip(runs, step_budgets or [None] * len(runs), strict=True) if b
        ]
        """The runs with a budget in steps (batch PPO), counted by :meth:`count_steps`."""
        self.steps_total = sum(b for _, b in self.step_runs)
        self.step_base: dict[Path, int] | None = None
        self.step_history: list[tuple[float, int]] = []
        self.steps_text = ""
        self.clock = clock
        self.since = time.time()
        """Wall time of the bar's start: live progress written before it is an earlier
        call's, ahead of the checkpoints the runs resume from."""
        self.base: dict[Path, int] | None = None
        """Every run's steps at the first count: the steps this call started from."""
        self.history: list[tuple[float, int]] = []
        """``(time, steps done in this call)`` of the counts of the last
        :attr:`RATE_WINDOW_S` seconds."""
        self.t_counted = -math.inf
        self.episodes_text = ""
        self.live_seconds = LIVE_SECONDS if enabled else None
        """How often the jobs write their runs' live progress for this bar (None: never)."""
        self.file = file if file is not None else sys.stderr
        # On a terminal the bar's clock moves, so every poll redraws it; asked once.
        isatty = getattr(self.file, "isatty", None)
        self.redraw_every_poll = isatty is not None and bool(isatty())
        self.count_every = self.COUNT_EVERY_S * (1 if self.redraw_every_poll else 3)
        self.shown: tuple[Any, ...] | None = None
        self.last_poll: tuple[int, list[dict[str, Any]]] = (0, [])
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

    def note(self, line: str) -> None:
        """A line above the bar (nothing without a bar)."""
        if self.bar is not None:
            self.bar.write(line, file=self.file)

    def count_episodes(self) -> str:
        """``"N/M, left~T"``: episodes done and the time left, the steps still to run
        (:func:`run_progress`) at the rate of the steps done in this call
        (:meth:`time_left`). Episodes grow longer as runs learn, so neither the episode
        rate nor an old step rate is a good guess."""
        progress = {r: run_progress(r, b, self.since) for r, b in self.episode_runs}
        n = sum(p.episodes for p in progress.values())
        if self.base is None:
            self.base = {r: p.steps for r, p in progress.items()}
        gained = sum(max(0, p.steps - self.base[r]) for r, p in progress.items())
        self.history = _windowed(self.history, self.clock(), gained, self.RATE_WINDOW_S)
        text = f"{n}/{self.episodes_total}"
        left = self.time_left(progress)
        if left is not None and n < self.episodes_total:
            text += f", left~{_minutes(left)}"
        return text

    def time_left(self, progress: dict[Path, RunProgress]) -> float | None:
        """Seconds left: the steps still to run at the rate of this call's counts of the
        last five minutes, from the last count before work began in them (a worker's
        start-up is no work).
        A run with no episode yet has its whole budget left at the recent episode length
        of the other runs of its task (or of all runs); None without a rate or a length."""
        per_step = _seconds_per_step(self.history)
        if per_step is None:
            return None
        lengths: dict[str, list[float]] = {}
        for run, p in progress.items():
            if p.length is not None:
                lengths.setdefault(run.parent.parent.name, []).append(p.length)
        every = [x for task in lengths.values() for x in task]
        steps_left = 0.0
        for (run, budget), p in zip(self.episode_runs, progress.values(), strict=True):
            if p.steps_left is not None:
                steps_left += p.steps_left
                continue
            guess = lengths.get(run.parent.parent.name) or every
            if not guess:
                return None
            steps_left += budget * sum(guess) / len(guess)
        return steps_left * per_step

    def count_steps(self) -> str:
        """``"X/Y, left~T"`` for the runs with a budget in steps (batch PPO): the steps
        done (live, else those checkpointed; a finished run's whole budget) and the time
        left at the rate of this call's steps of the last :attr:`RATE_WINDOW_S` seconds,
        from when work began."""
        steps = {r: self._run_steps(r, b) for r, b in self.step_runs}
        if self.step_base is None:
            self.step_base = dict(steps)
        gained = sum(max(0, n - self.step_base[r]) for r, n in steps.items())
        self.step_history = _windowed(self.step_history, self.clock(), gained, self.RATE_WINDOW_S)
        done = sum(steps.values())
        text = f"{_amount(done)}/{_amount(self.steps_total)}"
        per_step = _seconds_per_step(self.step_history)
        if per_step is not None and done < self.steps_total:
            text += f", left~{_minutes((self.steps_total - done) * per_step)}"
        return text

    def _run_steps(self, run: Path, budget: int) -> int:
        """A step-budget run's steps so far, at most its budget."""
        if (run / "done.json").exists():
            return budget
        live = read_live(run, self.since)
        return min(budget, live["total_steps"] if live is not None else _from_csv(run)[1])

    def poll(self, jobs_running: int, results: list[dict[str, Any]]) -> None:
        """Count finished runs on disk and failed ones in the jobs' results; show the jobs
        still running and, every :attr:`count_every` seconds, the episodes done. On a
        terminal the bar is
        redrawn at every poll (its clock moves); into a file or a pipe only when what it
        shows changed, so that a log of a long grid holds a line per change, not one every
        two seconds."""
        if self.bar is None:
            return
        self.last_poll = (jobs_running, results)
        done = sum((r / "done.json").exists() for r in self.runs)
        self.failed = sum(res["status"] == "failed" for res in results)
        self.bar.n = self.initial + done + self.failed
        due = self.clock() - self.t_counted >= self.count_every
        if (self.episode_runs or self.step_runs) and due:
            self.episodes_text = self.count_episodes() if self.episode_runs else ""
            self.steps_text = self.count_steps() if self.step_runs else ""
            self.t_counted = self.clock()
        postfix: dict[str, Any] = {"jobs": jobs_running, "failed": self.failed}
        if self.episodes_text:
            postfix["episodes"] = self.episodes_text
        if self.steps_text:
            postfix["steps"] = self.steps_text
        self.bar.set_postfix(postfix, refresh=False)
        shown = (self.bar.n, *postfix.items())
        if self.redraw_every_poll or shown != self.shown:
            self.bar.refresh()
            self.shown = shown

    def close(self) -> None:
        """Count once more, then close the bar (its last state stays on the terminal; a
        short grid showed the episodes of its first count, "episodes=0/6", when done)."""
        if self.bar is not None:
            self.t_counted = -math.inf
            self.poll(*self.last_poll)
            self.bar.close()
