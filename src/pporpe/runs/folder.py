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

import json
import pickle
from pathlib import Path
from typing import Any

import torch

from ..config import config_from_dict, config_to_dict
from ..io import atomic_path, atomic_write_json
from .cadence import LIVE_FILE
from .kinds import LearnerKind, get_kind
from .migrate import upgrade_config

__all__ = [
    "CHECKPOINT",
    "RUN_FILES",
    "check_checkpoint",
    "clear_run_dir",
    "config_json",
    "load_checkpoint",
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
    """A run file's JSON object, or a ValueError that names the file and what to do."""
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(
            f"{path} cannot be read ({exc}); restore it, or use another --out folder"
        ) from None
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
    """The learner kind and run configuration saved in ``run_dir/config.json``."""
    path = Path(run_dir) / "config.json"
    if not path.is_file():
        raise ValueError(f"{Path(run_dir)} is not a run folder (it has no config.json)")
    data = upgrade_config(_read_json(path))
    kind = get_kind(data.pop("kind"))
    return kind, config_from_dict(kind.config_type, data, str(path))


def open_run_dir(run_dir: str | Path, config: dict[str, Any]) -> tuple[Path, bool]:
    """Create a run folder and write ``config.json`` first, or check that it matches.

    Returns the folder and whether the run is complete (``done.json`` exists). A folder
    that holds a run with a different config is refused, so results are never mixed.
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


RUN_FILES = ("config.json", CHECKPOINT, "episodes.csv", "evaluation.json", "done.json",
             "error.txt", "tensorboard", LIVE_FILE)  # fmt: skip
"""What a run writes into its folder (``--force`` removes these, and nothing else)."""


def clear_run_dir(run_dir: str | Path) -> None:
    """Remove a run's files from its folder, so that a new run can start there."""
    import shutil

    run = Path(run_dir)
    if not run.is_dir():
        return
    for name in RUN_FILES:
        target = run / name
        if target.is_dir():
            shutil.rmtree(target)
        else:
            target.unlink(missing_ok=True)


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    """Write a checkpoint atomically (to a temporary file, then rename). The state is
    serialised in memory first, so a full disk raises ``OSError`` (torch.save would turn it
    into an unspecific RuntimeError) and the previous checkpoint stays."""
    import io

    buf = io.BytesIO()
    torch.save(state, buf)
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.getbuffer())


def _allowed_globals() -> list[Any]:
    """What a pporpe checkpoint holds besides tensors and plain values (dicts, lists,
    numbers, strings, None), for ``torch.load(weights_only=True)``: numpy arrays and scalars
    of numbers and their dtypes (a batch run's observation statistics, an online run's last
    action and episode replay record). Not numpy's object arrays, nor anything that runs
    code. Checkpoints written under numpy 1.x spell numpy's functions ``numpy.core``."""
    import numpy as np

    reconstruct = np.zeros(1).__reduce__()[0]  # numpy._core.multiarray._reconstruct
    scalar = np.float64(0.0).__reduce__()[0]  # numpy._core.multiarray.scalar
    dtypes = dict.fromkeys(type(np.dtype(code)) for code in "?bBhHiIlLqQefdgFDG")
    return [
        bytes,  # an empty array's data: protocol 2 pickles b"" as bytes()
        np.ndarray, np.dtype, reconstruct, scalar, *dtypes,
        (reconstruct, "numpy.core.multiarray._reconstruct"),
        (scalar, "numpy.core.multiarray.scalar"),
    ]  # fmt: skip


_TORCH_BOILERPLATE = ("Weights only load failed", "Please file an issue", "Check the documentation")
"""The lines of torch's refusal of a global that are about torch, not about the file."""
_CODE_REFUSALS = ("GLOBAL", "Can only build", "Can only create new object")
"""What ``torch.load(weights_only=True)`` says when a file would import or build more than
data (other refusals are of a torn or foreign file)."""


def _first_line(exc: BaseException) -> str:
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    reason = [ln for ln in lines if not ln.startswith(_TORCH_BOILERPLATE)] or lines or [""]
    return f"{type(exc).__name__}: {reason[0][:200]}"


def _unsafe(path: Path, what: str) -> ValueError:
    return ValueError(
        f"{path} is not a safe checkpoint: {what}, and a pporpe checkpoint holds only data; "
        "it was not opened (nothing in it ran). Delete it if you did not write it (the run "
        "then starts over without it)"
    )


def check_checkpoint(path: str | Path) -> None:
    """Refuse a checkpoint that would import or call anything besides tensors, plain values
    and numpy arrays (:func:`_allowed_globals`), reading its pickle without running it.

    Raises ``ValueError`` naming the file and what it would call (a checkpoint that is not
    a readable torch file at all is left to :func:`load_checkpoint`)."""
    path = Path(path)
    try:
        with torch.serialization.safe_globals(_allowed_globals()):
            foreign = torch.serialization.get_unsafe_globals_in_checkpoint(path)
    except Exception:  # not a zip checkpoint: torch.load(weights_only=True) refuses code
        return
    if foreign:
        raise _unsafe(path, f"it would call {', '.join(sorted(foreign))}")


def load_checkpoint(run_dir: str | Path) -> dict[str, Any]:
    """The checkpoint of a run folder, read with ``torch.load(weights_only=True)``: tensors,
    plain values and numpy arrays only, never code (:func:`check_checkpoint`).

    ``ValueError`` if it has none, if it is corrupt, or if it would run code; the file is
    left as it is."""
    path = Path(run_dir) / CHECKPOINT
    if not path.is_file():
        raise ValueError(f"{Path(run_dir)} is not a run folder with a checkpoint ({CHECKPOINT})")
    check_checkpoint(path)
    try:
        with torch.serialization.safe_globals(_allowed_globals()):
            state = torch.load(path, weights_only=True)
    except pickle.UnpicklingError as exc:
        if any(word in str(exc) for word in _CODE_REFUSALS):  # code, in a pre-zip file
            raise _unsafe(path, f"torch refused it ({_first_line(exc)})") from None
        raise _unreadable(path, exc) from None
    except Exception as exc:  # a torn or foreign file: zip or EOF errors
        raise _unreadable(path, exc) from None
    if not isinstance(state, dict) or not ("records" in state or "members" in state):
        raise ValueError(f"{path} is not a pporpe checkpoint; restore it or use --force")
    return state


def _unreadable(path: Path, exc: BaseException) -> ValueError:
    return ValueError(
        f"{path} cannot be read ({_first_line(exc)}); "
        "it was not changed. Restore it from a copy, or use --force to start the run over"
    )
