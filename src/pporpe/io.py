"""Atomic file writes: every result file is written to a temporary file, then renamed.

A reader (or a run resumed after SIGKILL) therefore sees either the old file or the
complete new one, never a torn write.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

__all__ = ["atomic_path", "atomic_savefig", "atomic_write_json", "atomic_write_text"]


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success fsync it and rename it onto ``path``.

    On an exception the temporary file is removed and ``path`` is left untouched. A ``path``
    that is a symbolic link is refused (``ValueError``) before anything is written: a file
    pporpe writes never replaces a link, which may be someone's on purpose.
    """
    target = Path(path)
    if target.is_symlink():
        raise ValueError(
            f"{target} is a symbolic link; pporpe does not write over links: remove it, or "
            "write elsewhere"
        )
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.", suffix=".tmp")
    os.close(fd)
    tmp = Path(tmp_name)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the file normal permissions
    try:
        yield tmp
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _atomic_write(path: str | Path, mode: str, write: Callable[[IO[Any]], object]) -> Path:
    with atomic_path(path) as tmp, open(tmp, mode) as fh:
        write(fh)
    return Path(path)


def atomic_write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically."""
    return _atomic_write(path, "w", lambda fh: fh.write(text))


def atomic_write_json(path: str | Path, obj: Any) -> Path:
    """Write ``obj`` as indented JSON to ``path`` atomically."""
    return atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=False) + "\n")


def atomic_savefig(fig: Any, path: str | Path, **kwargs: Any) -> Path:
    """Save a matplotlib figure atomically, in the format given by the path's suffix.

    A PDF gets no creation date (unless ``metadata`` says otherwise; PNG has none), so the
    same figure gives the same bytes: a regenerated report changes in git only where its
    data did.
    """
    target = Path(path)
    fmt = target.suffix.lstrip(".")
    if fmt == "pdf":
        kwargs.setdefault("metadata", {"CreationDate": None})
    with atomic_path(target) as tmp:
        fig.savefig(tmp, format=fmt, dpi=kwargs.pop("dpi", 150), bbox_inches="tight", **kwargs)
    return target
