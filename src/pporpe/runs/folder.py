"""A run folder on disk: what it holds, and how it is opened, checked and read back.

A run folder holds:

* ``config.json``     ``{"kind": <learner kind>, ...every setting}``, written before any work;
* ``episodes.csv``    one row per training episode (:class:`~pporpe.runs.logger.EpisodeRecord`);
* ``tensorboard/``    the same scalars for TensorBoard;
* ``checkpoint.pt``   the trainer's state, the records and the wall time, written atomically;
* ``evaluation.json`` median / mean / IQR of the test episodes (when requested);
* ``done.json``       written last: the run is complete, with its counters;
* ``progress.json``   while a grid trains the run: its episodes and steps so far, for the
  grid's progress bar (:class:`~pporpe.runs.cadence.LiveProgress`), removed at its end.

Folders written by earlier versions are read (:func:`read_config`) and resumed as the same
run: :mod:`pporpe.runs.migrate` upgrades what they hold.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from ..config import config_from_dict, config_to_dict
from ..io import atomic_path, atomic_write_json
from ..run_files import check_folder_env, read_json
from .cadence import LIVE_FILE
from .checkpoint_data import NotData, Unreadable, check_run_state, load_data, scan_checkpoint
from .kinds import LearnerKind, get_kind
from .links import RUN_WRITES, clear_run_files, refuse_links
from .migrate import upgrade_config

__all__ = [
    "CHECKPOINT",
    "RUN_FILES",
    "check_checkpoint",
    "clear_run_dir",
    "config_json",
    "load_checkpoint",
    "load_run_state",
    "open_run_dir",
    "read_config",
    "same_run_config",
    "save_checkpoint",
]

CHECKPOINT = "checkpoint.pt"


def config_json(kind: LearnerKind, cfg: Any) -> dict[str, Any]:
    """The ``config.json`` content of a run: its kind, then every setting."""
    return {"kind": kind.name, **config_to_dict(cfg)}


def _parsed(data: dict[str, Any]) -> tuple[str, Any] | None:
    """The kind and configuration of ``config.json`` content, or None if it does not parse."""
    data = upgrade_config(data)
    try:
        kind = get_kind(data["kind"])
        body = {k: v for k, v in data.items() if k != "kind"}
        return kind.name, config_from_dict(kind.config_type, body)
    except (KeyError, ValueError):
        return None


def same_run_config(a: dict[str, Any], b: dict[str, Any]) -> bool:
    """Whether two ``config.json`` contents are the same run: equal as parsed settings, so
    a field added by a later pporpe version, at the value the run ran with, is no change."""
    stored = _parsed(a)
    return stored is not None and stored == _parsed(b)


def _read_json(path: Path) -> dict[str, Any]:
    """A run file's JSON object, read as data (:func:`pporpe.run_files.read_json`: bounded
    size and nesting), or a ValueError that names the file and what to do."""
    data = read_json(path, "restore it, or use another --out folder")
    if not isinstance(data, dict):
        raise ValueError(f"{path} does not hold a JSON object; restore it, or use another --out")
    return data


def _differences(a: dict[str, Any], b: dict[str, Any], prefix: str = "") -> list[str]:
    """Dotted names of the settings that differ between two config dictionaries."""
    out = []
    for key in sorted(set(a) | set(b)):
        x, y = a.get(key), b.get(key)
        if isinstance(x, dict) and isinstance(y, dict):
            out += _differences(x, y, f"{prefix}{key}.")
        elif x != y:
            out.append(f"{prefix}{key}")
    return out


def read_config(run_dir: str | Path) -> tuple[LearnerKind, Any]:
    """The learner kind and run configuration saved in ``run_dir/config.json``, read as
    data: every setting checked by the run config (types, ranges and the bounds of
    :mod:`pporpe.limits`) and the task resolved among the registered ones, never imported
    (:func:`pporpe.run_files.check_folder_env`). ``ValueError`` naming the file otherwise."""
    path = Path(run_dir) / "config.json"
    if not path.is_file():
        raise ValueError(f"{Path(run_dir)} is not a run folder (it has no config.json)")
    data = upgrade_config(_read_json(path))
    try:
        kind = get_kind(data.pop("kind"))
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
    cfg: Any = config_from_dict(kind.config_type, data, str(path))
    check_folder_env(cfg.env, str(path))
    return kind, cfg


def open_run_dir(run_dir: str | Path, config: dict[str, Any]) -> tuple[Path, bool]:
    """Create a run folder and write ``config.json`` first, or check that it matches.

    Returns the folder and whether the run is complete (``done.json`` exists). A folder
    that holds a run with a different config is refused, so results are never mixed, and
    so is one where a name the run writes is a symbolic link
    (:func:`~pporpe.runs.links.refuse_links`), before anything is written.
    Configs are compared as parsed settings: a field added by a later pporpe version, at
    its default, is the same run as the folder's.
    """
    run = Path(run_dir)
    if run.exists() and not run.is_dir():
        raise ValueError(f"the run folder {run} is an existing file; choose another --out")
    try:
        run.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"cannot create the run folder {run}: {exc.strerror}") from None
    refuse_links(run, RUN_WRITES)
    path = run / "config.json"
    if not path.exists():
        atomic_write_json(path, config)
    else:
        saved = _read_json(path)
        if not same_run_config(saved, config):
            _refuse_another_kind(run, upgrade_config(saved).get("kind"), config.get("kind"))
            differ = _differences(upgrade_config(saved), upgrade_config(config))
            raise ValueError(
                f"{run} holds a run with a different config (differing: "
                f"{', '.join(differ) or 'unreadable settings'}); use another --out folder, "
                "or --force to start over in it"
            )
    return run, (run / "done.json").exists()


def _refuse_another_kind(run: Path, saved: Any, wanted: Any) -> None:
    """A folder of another learner kind is refused saying so (not as differing fields)."""
    from .kinds import kinds

    if saved != wanted and saved in kinds() and wanted in kinds():
        article = "an" if saved[0] in "aeiou" else "a"
        raise ValueError(
            f"{run}: this folder holds {article} {saved} run, not the {wanted} run of this "
            "command (--learner); use another --out folder, or --force to start over in it"
        )


RUN_FILES = ("config.json", CHECKPOINT, "episodes.csv", "updates.csv", "evaluation.json",
             "done.json", "error.txt", "tensorboard", LIVE_FILE)  # fmt: skip
"""What a run writes into its folder (``--force`` removes these, and nothing else)."""


def clear_run_dir(run_dir: str | Path) -> None:
    """Remove a run's files from its folder, so that a new run can start there: first
    checked, then removed (:func:`~pporpe.runs.links.clear_run_files`); a symbolic link
    among them, or a file that cannot be removed, is ``ValueError`` naming it and nothing
    is removed."""
    run = Path(run_dir)
    if run.is_dir():
        clear_run_files(run, RUN_FILES)


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    """Write a checkpoint atomically (to a temporary file, then rename). The state is
    serialised in memory first, so a full disk raises ``OSError`` (torch.save would turn it
    into an unspecific RuntimeError) and the previous checkpoint stays."""
    import io

    buf = io.BytesIO()
    torch.save(state, buf)
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.getbuffer())


def _unsafe(path: Path, what: str) -> ValueError:
    return ValueError(
        f"{path} is not a safe checkpoint: {what}, and a pporpe checkpoint holds only data; "
        "nothing in it ran. Delete it if you did not write it (the run then starts over "
        "without it)"
    )


def _cannot_read(path: Path, reason: str) -> ValueError:
    return ValueError(
        f"{path} cannot be read ({reason}); it was not changed. Restore it from a copy, or "
        "use --force to start the run over"
    )


def check_checkpoint(path: str | Path) -> None:
    """Refuse, without reading its pickle, a checkpoint that is not a regular torch zip
    file of stored entries or whose pickle names anything besides tensors, plain values
    and numpy's number arrays (:func:`pporpe.runs.checkpoint_data.scan_checkpoint`).

    Raises ``ValueError`` naming the file, and what it would call."""
    path = Path(path)
    try:
        scan_checkpoint(path, lambda what: _unsafe(path, what))
    except Unreadable as exc:
        raise _cannot_read(path, str(exc)) from None


def load_checkpoint(run_dir: str | Path) -> dict[str, Any]:
    """The checkpoint of a run folder (or of a population's home folder), read as data
    (:mod:`pporpe.runs.checkpoint_data`): tensors, plain values and numpy arrays and scalars
    of number types, never code, never an object array.

    ``ValueError`` naming the file if it has none, if it is corrupt, if it would run code
    or holds anything else, or if it is no pporpe checkpoint; the file is left as it is."""
    path = Path(run_dir) / CHECKPOINT
    if not path.is_file():
        raise ValueError(f"{Path(run_dir)} is not a run folder with a checkpoint ({CHECKPOINT})")
    check_checkpoint(path)
    try:
        state = load_data(path)
    except NotData as exc:
        raise _unsafe(path, str(exc)) from None
    except Exception as exc:  # a torn or foreign file: zip or EOF errors, memory
        raise _unreadable(path, exc) from None
    if not isinstance(state, dict) or not ("records" in state or "members" in state):
        raise ValueError(f"{path} is not a pporpe checkpoint; restore it or use --force")
    return state


_TORCH_BOILERPLATE = ("Weights only load failed", "Please file an issue", "Check the documentation")
"""The lines of torch's refusals that are about torch, not about the file."""


def load_run_state(run_dir: str | Path, kind: str) -> dict[str, Any]:
    """The checkpoint of a run folder (:func:`load_checkpoint`) checked to be a run state
    of learner kind ``kind`` (:func:`pporpe.runs.checkpoint_data.check_run_state`): its
    records, counters and learner, of that kind; ``ValueError`` naming the file otherwise."""
    state = load_checkpoint(run_dir)
    check_run_state(state, Path(run_dir) / CHECKPOINT, kind)
    return state


def _unreadable(path: Path, exc: BaseException) -> ValueError:
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    reason = [ln for ln in lines if not ln.startswith(_TORCH_BOILERPLATE)] or lines or [""]
    return _cannot_read(path, f"{type(exc).__name__}: {reason[0][:200]}")
