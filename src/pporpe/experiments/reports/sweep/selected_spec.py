"""``selected.toml``: the stage-2 spec a tuning sweep's report writes (:mod:`...grids.sweep`).

It is the stage-1 spec as read (``grid.json`` keeps it) with each method's swept fields at
the value selected (one-item lists), the evaluation seeds as its seeds (a task's own tuning
seeds dropped), ``-eval`` after its name, and ``stage1 = "."``: the folder it is written
into, the stage-1 folder, which ``pporpe reproduce`` checks is finished before any run.
"""

from __future__ import annotations

import copy
import json
import math
import re
import textwrap
from typing import Any

from .selection import Selection
from .sensitivity import setting_text

__all__ = ["selected_spec", "selected_toml", "toml_text"]

_BARE_KEY = re.compile(r"^[A-Za-z0-9_-]+$")


def _key(name: str) -> str:
    return name if _BARE_KEY.match(name) else json.dumps(name)


def _value(v: Any) -> str:
    """A TOML value: a boolean, an integer, a float (``repr``: read back exactly), a string
    or an array of them."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return ("inf" if v > 0 else "-inf") if math.isinf(v) else "nan" if v != v else repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # a TOML basic string: the same escapes
    if isinstance(v, list):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    raise ValueError(f"cannot write {v!r} ({type(v).__name__}) as a TOML value")


def _is_table_array(v: Any) -> bool:
    return isinstance(v, list) and bool(v) and all(isinstance(x, dict) for x in v)


def _table(lines: list[str], path: list[str], table: dict[str, Any]) -> None:
    """``table``'s values, then its sub-tables and arrays of tables, under ``path``."""
    for name, v in table.items():
        if not isinstance(v, dict) and not _is_table_array(v):
            lines.append(f"{_key(name)} = {_value(v)}")
    for name, v in table.items():
        dotted = ".".join(_key(p) for p in [*path, name])
        if isinstance(v, dict):
            lines += ["", f"[{dotted}]"]
            _table(lines, [*path, name], v)
        elif _is_table_array(v):
            for item in v:
                lines += ["", f"[[{dotted}]]"]
                _table(lines, [*path, name], item)


def toml_text(data: dict[str, Any]) -> str:
    """``data`` (tables, arrays of tables, values) as TOML that ``tomllib`` reads back equal."""
    lines: list[str] = []
    _table(lines, [], data)
    return "\n".join(lines).lstrip("\n") + "\n"


def selected_spec(grid: dict[str, Any], selections: dict[str, Selection]) -> dict[str, Any]:
    """The stage-2 spec of the sweep ``grid`` (its ``grid.json``) at ``selections``."""
    sweep = grid["sweep"]
    spec = copy.deepcopy(sweep["spec"])
    spec["name"] = f"{grid['name']}-eval"
    spec["seeds"] = list(sweep["evaluation_seeds"])
    for task in spec.get("tasks", []):
        task.pop("seeds", None)
    chosen: dict[str, Any] = {"stage1": "."}
    for method, sel in selections.items():
        if sel.best.setting:
            chosen[method] = {name: [value] for name, value in sel.best.setting}
    spec["sweep"] = chosen
    return spec


def _seed_text(seeds: list[int]) -> str:
    if seeds == list(range(seeds[0], seeds[0] + len(seeds))) and len(seeds) > 2:
        return f"{seeds[0]}-{seeds[-1]}"
    return ", ".join(map(str, seeds))


def selected_toml(
    grid: dict[str, Any], selections: dict[str, Selection], rule: str, folder: str
) -> str:
    """``selected.toml``: a header saying where it comes from and how to run it, then
    :func:`selected_spec` (``folder``: the stage-1 folder's name, for the commands)."""
    sweep = grid["sweep"]
    tuning = sorted({int(r["seed"]) for r in grid["runs"]})
    head = [
        f"# Stage 2 (evaluation) of the sweep {grid['name']!r}, written by `pporpe report "
        f"{folder}`:",
        "# each method at the setting stage 1 selected by the rule declared before any run,",
        *textwrap.wrap(rule, 88, initial_indent="#   ", subsequent_indent="#   "),
    ]
    for method, sel in selections.items():
        runner = ("" if sel.runner_up is None else
                  f"; runner-up {setting_text(sel.runner_up.setting)} "
                  f"({sel.runner_up.value:.3f})")  # fmt: skip
        head.append(f"#   {method}: {setting_text(sel.best.setting)} "
                    f"({sel.best.value:.3f}){runner}")  # fmt: skip
    head += [
        f"# on the evaluation seeds {_seed_text(list(sweep['evaluation_seeds']))}, disjoint from "
        f"the tuning seeds {_seed_text(tuning)};",
        '# stage1 = ".": the stage-1 folder is this file\'s folder. Run it with',
        f"#   pporpe reproduce {folder}/selected.toml --out {grid['name']}-eval",
        f"#   pporpe report {grid['name']}-eval",
        "",
    ]
    return "\n".join(head) + toml_text(selected_spec(grid, selections))
