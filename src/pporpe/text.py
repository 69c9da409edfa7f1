"""Numbers and counts as the commands print them: ``1 episode``, ``0.00`` (never ``-0.00``)."""

from __future__ import annotations

__all__ = ["count", "fixed"]


def count(n: int, word: str, plural: str | None = None) -> str:
    """``"1 episode"``, ``"2 episodes"``, ``"0 episodes"`` (``plural`` where it is not
    ``word + "s"``)."""
    return f"{n} {word if n == 1 else plural or word + 's'}"


def fixed(x: float, digits: int = 2) -> str:
    """``x`` with ``digits`` decimals, without the sign of a value that rounds to zero
    (``-0.001`` is ``"0.00"``, not ``"-0.00"``)."""
    text = f"{x:.{digits}f}"
    if text.startswith("-") and float(text) == 0.0:
        return text[1:]
    return text
