"""Sweeps as a grid dimension: the ``[sweep]`` table of a grid spec.

A sweep names, per method, learner settings to sweep; every combination of a method's
values is a cell of the grid with its own run folders (``<env>/<method>-<field><value>.../seed<k>``,
e.g. ``Hopper-v4/rpe-eps0.2-lr0.0003/seed100``)::

    [sweep]
    select = "iqm:mean_return"   # the rule that picks each method's setting (stage 1)
    evaluation_seeds = 20        # stage 2's seeds: a count (the smallest seeds >= 0 that are
                                 # not tuning seeds) or a list disjoint from the spec's seeds
    equal_budget = true          # false: methods may have different numbers of settings

    [sweep.rpe]
    eps = [0.1, 0.2]
    lr = [3e-4, 1e-3]

A spec with a sweep is *stage 1* (tuning): ``pporpe report`` on its folder draws each
method's sensitivity and writes ``selected.toml``, the *stage-2* spec (evaluation): each
method at its chosen setting (one value per field), the evaluation seeds, and
``stage1 = "."`` in its ``[sweep]`` table, the stage-1 folder, relative to the spec's
folder. A stage-2 spec is refused while that folder is missing or unfinished, or when its
seeds overlap the tuning seeds.

Every refusal comes before any folder is written, in one line naming the spec, the section
(``sweep.<method>.<field>``) and what is allowed. A grid without a sweep is unchanged: its
folders, ``grid.json`` and reports are what they were.
"""

from __future__ import annotations

import itertools
import json
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ...config import is_int
from ...surrogates import METHODS
from ..sweep_terms import DEFAULT_RULE, Setting, cell_name, check_rule, sweep_of, value_text

__all__ = [
    "SWEEP_OPTIONS",
    "Setting",
    "SweepSpec",
    "cell_name",
    "parse_sweep",
    "settings_of",
    "stage1_problem",
    "sweep_of",
    "value_text",
]

SWEEP_OPTIONS = ("select", "evaluation_seeds", "equal_budget", "stage1")
"""The ``[sweep]`` table's own fields; its other keys are methods."""

NOT_SWEPT = (
    "method", "seed", "env", "episodes", "steps", "total_steps", "eval_episodes",
    "checkpoint_every",
)  # fmt: skip
"""Names a sweep cannot sweep: they name a run or its budget (``methods``, ``seeds``,
``tasks``, ``eval_episodes`` and ``checkpoint_every`` set them)."""

_TEXT = re.compile(r"^[A-Za-z0-9_.+]+$")
"""A string value that may stand in a folder's name."""


@dataclass(frozen=True)
class SweepSpec:
    """A parsed sweep: each method's combinations and how stage 1 selects among them."""

    settings: Mapping[str, tuple[Setting, ...]]
    """Per method (spec order), its combinations (the product of its lists, in spec order);
    ``((),)`` for a method the sweep does not name."""
    equal_budget: bool
    """Whether every method must have the same number of combinations."""
    rule: str
    """The selection rule (:func:`..sweep_terms.check_rule`), declared before any run."""
    evaluation_seeds: tuple[int, ...]
    """Stage 2's seeds (stage 1); empty in a stage-2 spec."""
    stage1: str | None = None
    """A stage-2 spec: the name of its stage-1 folder (the spec's ``stage1``, a path
    relative to the spec's folder, names it)."""
    tuning_seeds: tuple[int, ...] = ()
    """A stage-2 spec: the seeds its stage-1 folder ran."""
    raw: Mapping[str, Any] = field(default_factory=dict)
    """The spec as read (stage 1): what ``selected.toml`` is written from."""

    @property
    def stage(self) -> int:
        """1 for a tuning sweep, 2 for an evaluation spec."""
        return 1 if self.stage1 is None else 2

    def summary(self) -> dict[str, Any]:
        """What ``grid.json`` records of the sweep (``"sweep"``)."""
        out: dict[str, Any] = {
            "stage": self.stage,
            "select": self.rule,
            "equal_budget": self.equal_budget,
            "settings": {m: [dict(s) for s in combos] for m, combos in self.settings.items()},
        }
        if self.stage == 1:
            out["evaluation_seeds"] = list(self.evaluation_seeds)
            out["spec"] = json.loads(json.dumps(self.raw, default=str))
        else:
            out["stage1"] = self.stage1
            out["tuning_seeds"] = list(self.tuning_seeds)
        return out


def settings_of(sweep: SweepSpec | None, method: str) -> tuple[Setting, ...]:
    """The combinations of ``method`` (``((),)``: one, without swept settings)."""
    return ((),) if sweep is None else sweep.settings[method]


def _refuse(where: str, section: str, message: str) -> ValueError:
    return ValueError(f"{where}: {section}: {message}")


def _values(where: str, method: str, name: str, values: Any) -> list[Any]:
    """One swept field's list: non-empty, distinct scalars, a field a run can vary."""
    section = f"sweep.{method}.{name}"
    if name in NOT_SWEPT:
        raise _refuse(where, section, "not a learner setting (the spec's methods, seeds and "
                      "tasks set it)")  # fmt: skip
    if not (isinstance(values, list) and values):
        raise _refuse(where, section, f"must be a non-empty list of values; got {values!r}")
    for v in values:
        ok = isinstance(v, bool | int | float) or (isinstance(v, str) and _TEXT.match(v))
        if not ok:
            raise _refuse(where, section, "values must be numbers, booleans or strings of "
                          f"letters, digits and _.+; got {v!r}")  # fmt: skip
    if len({(type(v), v) for v in values}) != len(values):
        raise _refuse(where, section, f"a list without repeats; got {values!r}")
    return list(values)


def _combinations(where: str, method: str, table: Any) -> tuple[Setting, ...]:
    """The product of a method's swept lists, in spec order."""
    if not isinstance(table, dict):
        raise _refuse(where, f"sweep.{method}", f"must be a table of lists; got {table!r}")
    if not table:
        return ((),)
    names = list(table)
    lists = [_values(where, method, n, table[n]) for n in names]
    return tuple(tuple(zip(names, combo, strict=True)) for combo in itertools.product(*lists))


def _method_tables(where: str, sweep: dict[str, Any], methods: Sequence[str]) -> dict[str, Any]:
    """The ``[sweep.<method>]`` tables: each a known method of the spec."""
    tables = {k: v for k, v in sweep.items() if k not in SWEEP_OPTIONS}
    for name, table in tables.items():
        if name not in METHODS:
            what = "unknown method" if isinstance(table, dict) else "unknown field"
            allowed = f"the sweep's fields are {list(SWEEP_OPTIONS)}, its tables methods of"
            raise _refuse(where, f"sweep.{name}", f"{what}; {allowed} {list(METHODS)}")
        if name not in methods:
            raise _refuse(where, f"sweep.{name}", f"the method is not in the spec's methods "
                          f"{list(methods)}")  # fmt: skip
    return tables


def _check_budget(where: str, settings: Mapping[str, tuple[Setting, ...]]) -> None:
    """Every method has as many combinations as the first one."""
    counts = {m: len(c) for m, c in settings.items()}
    first = next(iter(counts))
    for method, n in counts.items():
        if n != counts[first]:
            raise _refuse(where, f"sweep.{method}", f"{n} setting(s), but {first} has "
                          f"{counts[first]}: every method gets the same number (the same "
                          "tuning budget) unless the sweep says equal_budget = false")  # fmt: skip


def _evaluation_seeds(where: str, value: Any, tuning: Sequence[int]) -> tuple[int, ...]:
    """Stage 2's seeds: a count (the smallest seeds >= 0 that are not tuning seeds) or a
    list of distinct ints >= 0 disjoint from the tuning seeds."""
    section = "sweep.evaluation_seeds"
    if is_int(value) and value >= 1:
        fresh = (s for s in itertools.count() if s not in set(tuning))
        return tuple(itertools.islice(fresh, value))
    if not (isinstance(value, list) and value and all(is_int(s) and s >= 0 for s in value)
            and len(set(value)) == len(value)):  # fmt: skip
        raise _refuse(where, section, "must be a positive count or a non-empty list of "
                      f"distinct ints >= 0; got {value!r}")  # fmt: skip
    overlap = sorted(set(value) & set(tuning))
    if overlap:
        raise _refuse(where, section, f"seeds {overlap} are tuning seeds (the spec's seeds): "
                      "evaluation seeds must be fresh")  # fmt: skip
    return tuple(value)


def parse_sweep(
    data: dict[str, Any], where: str, methods: Sequence[str], tuning: Sequence[int]
) -> SweepSpec:
    """The spec's ``[sweep]`` table (``data["sweep"]``) checked against its ``methods`` and
    its seeds ``tuning`` (every seed of every task); the values themselves are checked
    when each run is built (:func:`.spec.parse_spec`)."""
    sweep = data["sweep"]
    if not isinstance(sweep, dict):
        raise _refuse(where, "sweep", f"must be a table; got {sweep!r}")
    tables = _method_tables(where, sweep, methods)
    settings = {m: _combinations(where, m, tables.get(m, {})) for m in methods}
    equal = sweep.get("equal_budget", True)
    if not isinstance(equal, bool):
        raise _refuse(where, "sweep.equal_budget", f"must be true or false; got {equal!r}")
    if equal:
        _check_budget(where, settings)
    rule = sweep.get("select", DEFAULT_RULE)
    try:
        check_rule(rule)
    except ValueError as exc:
        raise _refuse(where, "sweep.select", str(exc)) from None
    stage1 = sweep.get("stage1")
    if stage1 is None:
        seeds = _evaluation_seeds(where, sweep.get("evaluation_seeds", 10), tuning)
        return SweepSpec(settings, equal, rule, seeds, raw=data)
    return _stage2(where, sweep, settings, equal, stage1, tuning)


def _stage2(
    where: str, sweep: dict[str, Any], settings: dict[str, tuple[Setting, ...]], equal: bool,
    stage1: Any, seeds: Sequence[int],
) -> SweepSpec:  # fmt: skip
    """A stage-2 spec: one setting per method, its stage-1 folder finished, its seeds fresh."""
    if not isinstance(stage1, str) or not stage1:
        raise _refuse(where, "sweep.stage1", f"must be the stage-1 folder (a path); got {stage1!r}")
    for option in ("select", "evaluation_seeds"):
        if option in sweep:
            raise _refuse(where, f"sweep.{option}", "belongs to stage 1: a stage-2 spec runs "
                          "its own seeds (the field 'seeds') and selects nothing")  # fmt: skip
    for method, combos in settings.items():
        if len(combos) != 1:
            raise _refuse(where, f"sweep.{method}", f"a stage-2 spec gives each method one "
                          f"setting (one value per field); got {len(combos)}")  # fmt: skip
    folder = Path(where).parent / stage1
    grid, problem = stage1_problem(folder)
    if problem:
        raise _refuse(where, "sweep.stage1", f"{folder}: {problem}")
    tuning = sorted({int(r["seed"]) for r in grid["runs"]})
    overlap = sorted(set(seeds) & set(tuning))
    if overlap:
        raise _refuse(where, "seeds", f"seeds {overlap} are tuning seeds of the stage-1 folder "
                      f"{folder}: evaluation seeds must be fresh")  # fmt: skip
    rule = (sweep_of(grid) or {}).get("select", DEFAULT_RULE)
    return SweepSpec(settings, equal, rule, (), folder.resolve().name, tuple(tuning))


def stage1_problem(folder: Path) -> tuple[dict[str, Any], str | None]:
    """A stage-1 folder's ``grid.json`` and what keeps it from stage 2 (None: nothing): no
    grid, a grid that is not a stage-1 sweep, runs without ``done.json``."""
    path = folder / "grid.json"
    if not path.is_file():
        return {}, "holds no grid (no grid.json): run stage 1 into it first"
    try:
        grid = json.loads(path.read_text())
        runs = [(str(r["key"]), r["seed"]) for r in grid["runs"]]
    except (ValueError, KeyError, TypeError) as exc:
        return {}, f"grid.json is not a grid summary written by pporpe ({exc})"
    sweep = sweep_of(grid)
    if sweep is None or sweep.get("stage") != 1:
        return grid, "not a stage-1 sweep (its spec has no [sweep] table, or is a stage-2 spec)"
    lacking = sum(not (folder / key / "done.json").exists() for key, _ in runs)
    if lacking:
        return grid, (f"stage 1 is unfinished: {lacking} of {len(runs)} runs not done "
                      "(finish it, then `pporpe report` it and use its selected.toml)")  # fmt: skip
    return grid, None
