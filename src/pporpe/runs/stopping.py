"""Stopping the run loop at a safe point: Ctrl-C (SIGINT) or a scheduler's SIGTERM asks,
the loop checkpoints, then stops.

A ``KeyboardInterrupt`` raised in the middle of a step (inside an update, or the fused
engine's kernel) leaves the trainer's state half-written, so it cannot be checkpointed.
:func:`stop_on_signals` turns the first SIGINT or SIGTERM (what ``kill``, SLURM and most
job schedulers send before they kill) into a request instead: the run loop
(:func:`pporpe.runs.loop.run_queue`, its ``stop`` argument) checks it after every unit
of work, writes every busy run's checkpoint at that step and raises :class:`Interrupted`,
which says how far each run got. A second signal raises ``KeyboardInterrupt`` at once
(the work since the last checkpoint is lost, as after a kill).
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import FrameType

__all__ = ["STOP_SIGNALS", "Interrupted", "StopRequest", "stop_on_sigint", "stop_on_signals"]

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
"""The signals :func:`stop_on_signals` turns into a stop request."""


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
        self.signum: int | None = None
        """The signal that asked (None when :meth:`set` was called directly)."""

    def __call__(self) -> bool:
        return self.requested

    def set(self) -> None:
        """Ask the run loop to stop at its next safe point."""
        self.requested = True


@contextmanager
def stop_on_signals() -> Iterator[StopRequest]:
    """Inside, the first SIGINT or SIGTERM sets the yielded :class:`StopRequest` (pass it as
    the run loop's ``stop``); a second raises ``KeyboardInterrupt`` at once. The previous
    handlers are restored on exit. Outside the main thread no handler is set and the
    request is never made; a signal that is ignored (SIGINT in a process started in the
    background) stays ignored."""
    stop = StopRequest()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def request(signum: int, frame: FrameType | None) -> None:
        if stop.requested:
            raise KeyboardInterrupt
        stop.signum = signum
        stop.set()

    previous = {sig: signal.getsignal(sig) for sig in STOP_SIGNALS}
    for sig, handler in previous.items():
        if handler is not signal.SIG_IGN:
            signal.signal(sig, request)
    try:
        yield stop
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


stop_on_sigint = stop_on_signals
"""The name of :func:`stop_on_signals` before it also handled SIGTERM (pporpe 0.5.0);
kept for one release."""
