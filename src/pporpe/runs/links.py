"""Symbolic links inside a run or grid folder: refused before anything is deleted or written.

A folder from someone else may hold a link where pporpe writes (``tensorboard/`` pointing
at a folder of the user's, ``.lock`` at one of their files). pporpe never deletes or writes
through one: every command that writes into a folder checks the names it will write
first (:func:`refuse_links`, :func:`refuse_linked_path`), and ``--force`` checks that it
can remove every file it removes before it removes any (:func:`clear_run_files`). The
folder given on the command line may itself be a link: that is the user's own choice.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterable
from pathlib import Path

__all__ = ["RUN_WRITES", "clear_run_files", "refuse_linked_path", "refuse_links"]

RUN_WRITES = ("config.json", "checkpoint.pt", "episodes.csv", "updates.csv", "evaluation.json",
              "done.json", "error.txt", "tensorboard", "progress.json", ".lock")  # fmt: skip
"""Every name a run writes in its folder."""


def _link_error(path: Path) -> ValueError:
    return ValueError(
        f"{path} is a symbolic link; pporpe never deletes or writes through a link inside a "
        "run folder (it may point outside it): replace it with a plain file or folder, or "
        "remove it, and run again"
    )


def _links_under(folder: Path) -> Path | None:
    """The first symbolic link found below ``folder`` (not followed), or None."""
    for root, dirs, files in os.walk(folder, followlinks=False):
        for name in sorted(dirs + files):
            if (Path(root) / name).is_symlink():
                return Path(root) / name
    return None


def refuse_links(folder: str | Path, names: Iterable[str]) -> None:
    """``ValueError`` naming the first of ``folder/<name>`` that is a symbolic link, or that
    is a folder holding one (``tensorboard/``)."""
    folder = Path(folder)
    for name in names:
        path = folder / name
        if path.is_symlink():
            raise _link_error(path)
        if path.is_dir() and (inner := _links_under(path)) is not None:
            raise _link_error(inner)


def refuse_linked_path(root: str | Path, relative: str | Path) -> None:
    """``ValueError`` naming the first folder on the way from ``root`` to ``root/relative``
    (``root`` excluded, ``root/relative`` included) that is a symbolic link: a grid's run
    folder ``pendulum/ppo/seed0`` is written inside the grid folder, never elsewhere."""
    path = Path(root)
    for part in Path(relative).parts:
        path = path / part
        if path.is_symlink():
            raise _link_error(path)


def _not_removable(path: Path) -> str | None:
    """Why the entries of folder ``path`` cannot be removed (None when they can)."""
    if not os.access(path, os.W_OK | os.X_OK):
        return f"{path} is not writable"
    return None


def clear_run_files(run: Path, names: Iterable[str]) -> None:
    """Remove ``run/<name>`` for each of ``names`` (a file, or a folder with what it holds),
    after checking that every one of them can be: no symbolic link among them or inside
    them, and every folder they are removed from writable. Nothing is removed when one
    cannot be (``ValueError`` naming it)."""
    targets = [run / name for name in names if os.path.lexists(run / name)]
    refuse_links(run, [t.name for t in targets])
    folders = [run] if targets else []
    for target in targets:
        if target.is_dir():
            folders += [Path(root) for root, _, _ in os.walk(target)]
    for folder in folders:
        if (reason := _not_removable(folder)) is not None:
            raise ValueError(f"cannot start over in {run}: {reason}; nothing was removed")
    for target in targets:
        if target.is_dir():
            shutil.rmtree(target)
        else:
            target.unlink(missing_ok=True)
