"""Stopping a run mid-way in a test, the way a kill would: a callback that raises."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any


class Interrupted(RuntimeError):
    """Raised by :func:`at_episode`'s callback; nothing in pporpe catches it."""


def at_episode(episode: int) -> Callable[[Any], None]:
    """An ``on_episode`` callback that raises :class:`Interrupted` when the record of
    ``episode`` (0-based) arrives, after the checkpoints written before it."""

    def callback(rec: Any) -> None:
        if rec.episode == episode:
            raise Interrupted

    return callback
