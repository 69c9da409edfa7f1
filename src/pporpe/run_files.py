"""The JSON files of a run or grid folder, read as data: bounded in size and nesting, and
parsed against their schemas before anything is built from them.

A run folder may come from someone else (``results/`` holds hundreds, and sharing them is
what a reproduction invites), so every file pporpe reads from one is data to check, never
something to trust:

* :func:`read_json`: a regular file of at most :data:`~pporpe.limits.MAX_JSON_BYTES`,
  UTF-8 JSON nested at most :data:`~pporpe.limits.MAX_JSON_DEPTH` deep, or one
  ``ValueError`` naming the file (never a ``RecursionError``, never a read that blocks);
* :func:`parse_done`, :func:`parse_evaluation`, :func:`parse_grid`: the schemas of
  ``done.json``, ``evaluation.json`` and ``grid.json`` (known fields, their types and
  ranges); ``config.json`` is parsed by the run configs themselves
  (:func:`pporpe.runs.folder.read_config`);
* :func:`check_folder_env`: a task read from a folder is one of pporpe's tasks or a
  registered Gymnasium id; the ``module:Id`` form, which imports a module, is refused
  (it stays allowed where the user types it: a command line, their own grid spec);
* :func:`check_run_key`: a run's key in ``grid.json`` is a path inside the grid folder.
"""

from __future__ import annotations

import json
import math
import os
import stat
from pathlib import Path
from typing import Any

from .limits import (
    MAX_EPISODES,
    MAX_GRID_RUNS,
    MAX_JSON_BYTES,
    MAX_JSON_DEPTH,
    MAX_SEED,
    MAX_STEPS,
    short_repr,
)

__all__ = [
    "DONE_FIELDS",
    "EVALUATION_FIELDS",
    "check_folder_env",
    "check_run_key",
    "json_depth",
    "parse_done",
    "parse_evaluation",
    "parse_grid",
    "read_done",
    "read_evaluation",
    "read_grid",
    "read_json",
    "read_regular_file",
]

_COUNT = "count"
_SECONDS = "seconds"
_NUMBER = "number"

DONE_FIELDS: dict[str, str] = {
    "episodes": _COUNT,
    "total_steps": _COUNT,
    "chunks": _COUNT,
    "updates": _COUNT,
    "cpu_time_since": _COUNT,
    "train_time": _SECONDS,
    "cpu_time": _SECONDS,
    "eval_cpu_time": _SECONDS,
}
"""The fields ``done.json`` may hold: counters (ints in [0, 10**9]) and seconds (finite
numbers >= 0). Every pporpe version's runs wrote a subset."""

EVALUATION_FIELDS: dict[str, str] = {
    "episodes": _COUNT,
    "median": _NUMBER,
    "mean": _NUMBER,
    "q25": _NUMBER,
    "q75": _NUMBER,
    "iqr": _NUMBER,
    "returns": "returns",
    "seed": "seed",
}
"""The fields ``evaluation.json`` may hold: ``returns`` (a list of numbers, one per test
episode), ``episodes`` (their count), their summary (numbers) and, written by
``pporpe evaluate``, the environment ``seed``."""


def _first_line(text: str) -> str:
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    return lines[0][:200] if lines else ""


def read_regular_file(path: str | Path, max_bytes: int, remedy: str = "") -> bytes:
    """The bytes of ``path``, a regular file (a link to one is read) of at most ``max_bytes``;
    else ``ValueError`` naming it, with ``remedy`` appended. A named pipe or a device is never
    opened for reading in a way that could block."""
    path = Path(path)
    tail = f"; {remedy}" if remedy else ""
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except OSError as exc:
        raise ValueError(f"{path} cannot be read ({exc.strerror or exc}){tail}") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise ValueError(f"{path} is not a regular file{tail}")
        if info.st_size > max_bytes:
            raise ValueError(f"{path} is larger than pporpe reads ({max_bytes:,} bytes){tail}")
        with os.fdopen(fd, "rb", closefd=False) as fh:
            data = fh.read(info.st_size + 1)  # a buffer of the file's size, not of the bound
    except OSError as exc:
        raise ValueError(f"{path} cannot be read ({exc.strerror or exc}){tail}") from None
    finally:
        os.close(fd)
    if len(data) > max_bytes:
        raise ValueError(f"{path} is larger than pporpe reads ({max_bytes:,} bytes){tail}")
    return data


def json_depth(value: Any) -> int:
    """How deeply lists and objects nest in a parsed JSON value (0 for a number or a
    string), without recursion."""
    deepest, stack = 0, [(value, 0)]
    while stack:
        item, depth = stack.pop()
        if isinstance(item, dict):
            item = list(item.values())
        if isinstance(item, list):
            depth += 1
            deepest = max(deepest, depth)
            stack.extend((x, depth) for x in item if isinstance(x, dict | list))
    return deepest


def read_json(path: str | Path, remedy: str = "", max_bytes: int = MAX_JSON_BYTES) -> Any:
    """The JSON value of ``path``: a regular file of at most ``max_bytes``, UTF-8, nested at
    most :data:`~pporpe.limits.MAX_JSON_DEPTH` deep; else one ``ValueError`` naming the file
    (``remedy`` appended: what to do about it)."""
    raw = read_regular_file(path, max_bytes, remedy)
    tail = f"; {remedy}" if remedy else ""
    deep = ValueError(
        f"{path} nests lists or objects more than {MAX_JSON_DEPTH} deep, which no pporpe "
        f"file does{tail}"
    )
    try:
        data = json.loads(raw.decode("utf-8"))
    except RecursionError:
        raise deep from None
    except (UnicodeDecodeError, ValueError) as exc:  # JSONDecodeError, an int of 4300 digits
        raise ValueError(f"{path} cannot be read ({_first_line(str(exc))}){tail}") from None
    if json_depth(data) > MAX_JSON_DEPTH:
        raise deep
    return data


def _is_count(value: Any, most: int = MAX_STEPS) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and 0 <= value <= most


def _is_number(value: Any) -> bool:
    """An int or a float, not a bool; NaN and infinities included (a summary of returns may
    hold them), an int too large for a float not."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return False
    return isinstance(value, float) or value.bit_length() <= 1023


def _is_seconds(value: Any) -> bool:
    return _is_number(value) and math.isfinite(value) and value >= 0


_CHECKS = {
    _COUNT: (_is_count, "an int in [0, 10**9]"),
    _SECONDS: (_is_seconds, "a finite number >= 0"),
    _NUMBER: (_is_number, "a number"),
    "returns": (
        lambda v: isinstance(v, list)
        and 1 <= len(v) <= MAX_EPISODES
        and all(_is_number(x) and not math.isnan(x) for x in v),
        f"a list of 1 to {MAX_EPISODES:,} numbers (not NaN)",
    ),
    "seed": (lambda v: isinstance(v, int) and not isinstance(v, bool) and 0 <= v < 2**64,
             "an int in [0, 2**64)"),
}  # fmt: skip


def _parse_fields(data: Any, fields: dict[str, str], path: Path, remedy: str) -> dict[str, Any]:
    """``data`` checked against ``fields`` (name -> kind of value): an object with known
    fields only, each of its kind; else ``ValueError`` naming the file and the field."""
    tail = f"; {remedy}" if remedy else ""
    if not isinstance(data, dict):
        raise ValueError(f"{path} does not hold a JSON object{tail}")
    unknown = sorted(set(data) - set(fields))
    if unknown:
        names = short_repr(unknown, 80)
        raise ValueError(f"{path}: unknown field(s) {names}; pporpe writes only "
                         f"{sorted(fields)}{tail}")  # fmt: skip
    for name, value in data.items():
        check, allowed = _CHECKS[fields[name]]
        if not check(value):
            raise ValueError(f"{path}: {name} must be {allowed}; got {short_repr(value)}{tail}")
    return dict(data)


def parse_done(data: Any, path: str | Path) -> dict[str, Any]:
    """The content of a ``done.json`` checked against :data:`DONE_FIELDS`."""
    return _parse_fields(data, DONE_FIELDS, Path(path), "restore it, or delete it to "
                         "finish the run again from its checkpoint")  # fmt: skip


def read_done(run_dir: str | Path) -> dict[str, Any]:
    """``run_dir/done.json``, read and checked (:func:`parse_done`)."""
    path = Path(run_dir) / "done.json"
    return parse_done(read_json(path), path)


def parse_evaluation(data: Any, path: str | Path) -> dict[str, Any]:
    """The content of an ``evaluation.json`` checked against :data:`EVALUATION_FIELDS`: the
    ``returns`` or at least their ``median`` (what a report reads), ``episodes`` (when given
    with the returns) their count."""
    remedy = "restore it, or run pporpe evaluate on the folder again"
    parsed = _parse_fields(data, EVALUATION_FIELDS, Path(path), remedy)
    if "returns" not in parsed:
        if "median" not in parsed:
            raise ValueError(f"{path}: it holds neither returns nor their median; {remedy}")
        return parsed
    if parsed.get("episodes", len(parsed["returns"])) != len(parsed["returns"]):
        raise ValueError(
            f"{path}: episodes={parsed['episodes']} but {len(parsed['returns'])} returns; {remedy}"
        )
    return parsed


def read_evaluation(run_dir: str | Path) -> dict[str, Any]:
    """``run_dir/evaluation.json``, read and checked (:func:`parse_evaluation`)."""
    path = Path(run_dir) / "evaluation.json"
    return parse_evaluation(read_json(path), path)


def check_run_key(key: Any, where: str) -> str:
    """A run's key as ``grid.json`` lists it: a relative path of 1 to 8 names (no ``.``,
    ``..``, backslash or NUL), so that the run's folder is inside the grid folder."""
    parts = key.split("/") if isinstance(key, str) else []
    ok = 1 <= len(parts) <= 8 and len(key) <= 400
    ok = ok and all(p not in ("", ".", "..") and "\\" not in p and "\0" not in p for p in parts)
    if not ok:
        raise ValueError(
            f"{where}: a run's key must be a relative path inside the grid folder (names "
            f"joined by '/', no '..'); got {short_repr(key)}"
        )
    return str(key)


_GRID_RUN_FIELDS = {
    "key": lambda v: isinstance(v, str),
    "env": lambda v: isinstance(v, str) and 1 <= len(v) <= 200,
    "method": lambda v: isinstance(v, str) and 1 <= len(v) <= 200,
    "seed": lambda v: _is_count(v, MAX_SEED),
    "config": lambda v: isinstance(v, dict),
}


def parse_grid(data: Any, path: str | Path) -> dict[str, Any]:
    """The content of a ``grid.json`` checked: an object whose ``runs`` is a list of at most
    :data:`~pporpe.limits.MAX_GRID_RUNS` runs, each with a ``key`` inside the folder
    (:func:`check_run_key`), an ``env`` and a ``method`` (strings), a ``seed`` (an int in
    [0, 2**32 - 1]) and a ``config`` (an object; its settings are checked where they are
    compared); ``name`` and ``source`` strings when given. Other fields are kept as they
    are and never read."""
    where = str(path)
    remedy = "restore it, or run pporpe reproduce with its spec again to rewrite it"
    if not isinstance(data, dict) or not isinstance(data.get("runs"), list):
        raise ValueError(f"{where}: not a grid summary (an object with a list of runs); {remedy}")
    if len(data["runs"]) > MAX_GRID_RUNS:
        raise ValueError(f"{where}: more than {MAX_GRID_RUNS:,} runs; {remedy}")
    for name in ("name", "source"):
        if name in data and not isinstance(data[name], str):
            raise ValueError(f"{where}: {name} must be a string; {remedy}")
    for i, run in enumerate(data["runs"]):
        if not isinstance(run, dict):
            raise ValueError(f"{where}: run {i} is not an object; {remedy}")
        for name, check in _GRID_RUN_FIELDS.items():
            if not check(run.get(name)):
                raise ValueError(
                    f"{where}: run {i} has no valid {name!r} (got {short_repr(run.get(name))})"
                    f"; {remedy}"
                )
        check_run_key(run["key"], f"{where}: run {i}")
    return data


def read_grid(root: str | Path) -> dict[str, Any]:
    """``root/grid.json``, read and checked (:func:`parse_grid`)."""
    path = Path(root) / "grid.json"
    return parse_grid(read_json(path), path)


def check_folder_env(env: Any, where: str) -> str:
    """The registered Gymnasium id of a task read from a run folder (``where`` names the
    file): one of pporpe's tasks or a registered id. The ``module:Id`` form is refused
    before anything is imported: importing a module runs its code, which a folder received
    from someone else must never do (a user who trusts such a task passes it themselves,
    on the command line or in their own grid spec)."""
    if not isinstance(env, str) or not env:
        raise ValueError(f"{where}: env must be a task name; got {short_repr(env)}")
    if ":" in env:
        raise ValueError(
            f"{where}: env={short_repr(env)} names a module to import (module:Id), which "
            "pporpe never does for a task read from a run folder (nothing was imported); "
            "a folder's task must be one of pporpe's tasks or a registered Gymnasium id"
        )
    from .envs import resolve_env_id

    try:
        return resolve_env_id(env)
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None
