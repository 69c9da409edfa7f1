"""Stopping the run loop at a safe point: Ctrl-C (SIGINT) asks, the loop checkpoints, then stops.

A ``KeyboardInterrupt`` raised in the middle of a step (inside an update, or the fused
engine's kernel) leaves the trainer's state half-written, so it cannot be checkpointed.
:func:`stop_on_sigint` turns the first SIGINT into a request instead: the run loop
(:func:`pporpe.runs.loop.run_queue`, its ``stop`` argument) checks it after every unit
of work, writes every busy run's checkpoint at that step and raises :class:`Interrupted`,
which says how far each run got. A second SIGINT raises ``KeyboardInterrupt`` at once (the
work since the last checkpoint is lost, as after a kill).
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import FrameType

__all__ = ["Interrupted", "StopRequest", "stop_on_sigint"]


class Interrupted(KeyboardInterrupt):
    """The run loop stopped at a safe point on request, every busy run checkpointed there."""

    def __init__(self, episodes: dict[Path, int]) -> None:
        super().__init__(f"interrupted with {len(episodes)} runs unfinished")
        self.episodes = episodes
        """Every unfinished run's folder and the episodes it has logged (and checkpointed)."""


class StopRequest:
    """A flag the run loop reads after every unit of work: ``stop()`` is whether to stop."""

    def __init__(self) -> None:
        self.requested = False

    def __call__(self) -> bool:
        return self.requested

    def set(self) -> None:
        """Ask the run loop to stop at its next safe point."""
        self.requested = True


@contextmanager
def stop_on_sigint() -> Iterator[StopRequest]:
    """Inside, the first SIGINT sets the yielded :class:`StopRequest` (pass it as the run
    loop's ``stop``); a second raises ``KeyboardInterrupt`` at once. The previous handler
    is restored on exit. Outside the main thread, or where SIGINT is ignored (a process
    started in the background), no handler is set and the request is never made."""
    stop = StopRequest()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return
    previous = signal.getsignal(signal.SIGINT)
    if previous is signal.SIG_IGN:
        yield stop
        return

    def request(signum: int, frame: FrameType | None) -> None:
        if stop.requested:
            raise KeyboardInterrupt
        stop.set()

    signal.signal(signal.SIGINT, request)
    try:
        yield stop
    finally:
        signal.signal(signal.SIGINT, previous)
