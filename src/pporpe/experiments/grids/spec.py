"""Experiment grids as data: methods x tasks x seeds, read from a TOML spec.

A spec (see ``experiments/paper.toml``)::

    name = "paper"
    methods = ["ppo", "rb", "rpe"]
    seeds = 10                 # 0..9, or an explicit list [0, 1, 2]
    eval_episodes = 50
    checkpoint_every = 10      # optional

    kind = "online"            # optional: the learner kind ("online" or "batch")

    [learner]                  # optional: any field of the kind's learner settings
    eps = 0.1                  # (OnlineConfig for "online", BatchConfig for "batch")

    [[tasks]]
    env = "pendulum"
    episodes = 200             # or steps = N (batch runs: steps)
    seeds = 25                 # optional: this task's own seeds (a count or a list)
    [tasks.learner]            # optional: overrides for this task only
    lr = 1e-4

    [sweep.rpe]                # optional: settings to sweep, per method (:mod:`.sweep`)
    eps = [0.1, 0.2]

Every run is independent; its folder is ``OUT/<env>/<method>/seed<k>`` (a sweep's:
``OUT/<env>/<method>-eps0.1/seed<k>``). A malformed spec is rejected before any run starts,
naming the file, the field and what is allowed.
"""

from __future__ import annotations

import dataclasses
import functools
import tomllib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ...config import is_int
from ...envs import resolve_env_id
from ...runs.kinds import get_kind
from ...surrogates import METHODS
from .sweep import Setting, SweepSpec, cell_name, parse_sweep, settings_of

__all__ = ["GridSpec", "RunSpec", "load_spec", "parse_spec", "select_runs"]

_TOP_FIELDS = {
    "name",
    "kind",
    "methods",
    "seeds",
    "eval_episodes",
    "checkpoint_every",
    "learner",
    "tasks",
    "sweep",
}
_TASK_FIELDS = {"env", "episodes", "steps", "seeds", "learner"}


@dataclass(frozen=True)
class RunSpec:
    """One (method, task, seed) run of a grid."""

    method: str
    """Surrogate name."""
    env: str
    """Task alias or Gymnasium id."""
    seed: int
    """Seed."""
    config: Any
    """Full run configuration (the kind's config type, e.g. TrainConfig)."""
    setting: Setting = ()
    """The run's swept settings (a sweep's cell), ``(field, value)`` pairs; () without."""

    @property
    def key(self) -> str:
        """Relative folder of the run: ``<env>/<method>/seed<k>``; in a sweep,
        ``<env>/<method>-<field><value>.../seed<k>`` (:func:`.sweep.cell_name`)."""
        return f"{self.env}/{cell_name(self.method, self.setting)}/seed{self.seed}"


@dataclass(frozen=True)
class GridSpec:
    """A parsed, validated grid."""

    name: str
    """Name of the grid."""
    runs: tuple[RunSpec, ...]
    """Every run, ordered task by task, then seed, then method."""
    source: str
    """The file it was read from."""
    sweep: SweepSpec | None = None
    """The spec's sweep (:mod:`.sweep`); None for a grid without one."""

    @property
    def methods(self) -> list[str]:
        """Methods in the grid, in spec order."""
        return list(dict.fromkeys(r.method for r in self.runs))

    @property
    def envs(self) -> list[str]:
        """Tasks in the grid, in spec order."""
        return list(dict.fromkeys(r.env for r in self.runs))


def select_runs(
    spec: GridSpec,
    tasks: Sequence[str] | None = None,
    methods: Sequence[str] | None = None,
    seeds: Sequence[int] | None = None,
) -> GridSpec:
    """The part of ``spec`` with these tasks, methods and seeds (None: all): one chunk of a
    grid, or one cell to re-run. Each value must be in the spec (ValueError naming the
    option and what the spec has)."""
    asked: dict[str, Sequence[Any] | None] = {"tasks": tasks, "methods": methods, "seeds": seeds}
    have: dict[str, list[Any]] = {
        "tasks": spec.envs,
        "methods": spec.methods,
        "seeds": list(dict.fromkeys(r.seed for r in spec.runs)),
    }
    chosen: dict[str, set[Any] | None] = {}
    for option, values in asked.items():
        if values is None:
            chosen[option] = None
            continue
        unknown = [v for v in values if v not in have[option]]
        if unknown or not values:
            raise ValueError(
                f"--{option} {' '.join(str(v) for v in (unknown or values))}: not in the spec "
                f"{spec.source!r}, which has {', '.join(str(v) for v in have[option])}"
            )
        chosen[option] = set(values)

    def keep(r: RunSpec) -> bool:
        return all(
            chosen[o] is None or v in chosen[o]  # type: ignore[operator]
            for o, v in (("tasks", r.env), ("methods", r.method), ("seeds", r.seed))
        )

    return dataclasses.replace(spec, runs=tuple(r for r in spec.runs if keep(r)))


def _fail(where: str, field: str, value: Any, allowed: str) -> ValueError:
    return ValueError(f"{where}: field '{field}' must be {allowed}; got {value!r}")


def _parse_header(data: dict[str, Any], where: str) -> tuple[str, Any]:
    """The spec's fields are known and the required ones there; its name and learner kind."""
    unknown = sorted(set(data) - _TOP_FIELDS)
    if unknown:
        raise ValueError(f"{where}: unknown field(s) {unknown}; allowed: {sorted(_TOP_FIELDS)}")
    for required in ("methods", "seeds", "tasks"):
        if required not in data:
            raise ValueError(f"{where}: missing field '{required}'")
    name = data.get("name", Path(where).stem)
    if not isinstance(name, str):
        raise _fail(where, "name", name, "a string")
    try:
        kind = get_kind(data.get("kind", "online"))
    except ValueError as exc:
        raise ValueError(f"{where}: field 'kind': {exc}") from None
    return name, kind


def _parse_methods(methods: Any, where: str) -> list[str]:
    """``methods``: a non-empty list of distinct names from :data:`METHODS`."""
    if not (isinstance(methods, list) and methods and all(m in METHODS for m in methods)):
        raise _fail(where, "methods", methods, f"a non-empty list drawn from {list(METHODS)}")
    if len(set(methods)) != len(methods):
        raise _fail(where, "methods", methods, "a list without repeats")
    return list(methods)


def _parse_seeds(seeds: Any, where: str) -> list[int]:
    """``seeds``: a count n (seeds 0..n-1) or a non-empty list of distinct ints >= 0."""
    if is_int(seeds):
        if seeds < 1:
            raise _fail(where, "seeds", seeds, "a positive count or a list of ints >= 0")
        return list(range(seeds))
    if (
        isinstance(seeds, list)
        and seeds
        and all(is_int(s) and s >= 0 for s in seeds)
        and len(set(seeds)) == len(seeds)
    ):
        return list(seeds)
    raise _fail(where, "seeds", seeds, "a positive count or a non-empty list of distinct ints >= 0")


def _parse_common(data: dict[str, Any], where: str) -> tuple[dict[str, Any], dict[str, Any]]:
    """The settings of every run: ``eval_episodes`` and ``checkpoint_every``, and the
    ``learner`` table (which must not set the method)."""
    eval_episodes = data.get("eval_episodes", 50)
    if not (is_int(eval_episodes) and eval_episodes >= 0):
        raise _fail(where, "eval_episodes", eval_episodes, "an int >= 0")
    checkpoint_every = data.get("checkpoint_every", 10)
    if not (is_int(checkpoint_every) and checkpoint_every >= 1):
        raise _fail(where, "checkpoint_every", checkpoint_every, "an int >= 1")
    learner = data.get("learner", {})
    if not isinstance(learner, dict):
        raise _fail(where, "learner", learner, "a table of learner settings")
    if "method" in learner:
        raise ValueError(f"{where}: field 'learner.method' is set by 'methods', not by learner")
    return {"eval_episodes": eval_episodes, "checkpoint_every": checkpoint_every}, learner


def _parse_task(
    task: dict[str, Any], at: str, seen_envs: set[str]
) -> tuple[str, dict[str, Any], dict[str, Any]]:
    """One ``[[tasks]]`` table: its environment (added to ``seen_envs``, which must not
    hold it yet), its budget (episodes or steps) and its learner settings."""
    unknown = sorted(set(task) - _TASK_FIELDS)
    if unknown:
        raise ValueError(f"{at}: unknown field(s) {unknown}; allowed: {sorted(_TASK_FIELDS)}")
    env = task.get("env")
    if not isinstance(env, str):
        raise ValueError(f"{at}: field 'env' must be a task alias or Gymnasium id; got {env!r}")
    try:
        resolve_env_id(env)
    except ValueError as exc:
        raise ValueError(f"{at}: field 'env': {exc}") from None
    if env in seen_envs:
        raise ValueError(f"{at}: field 'env' repeats {env!r}")
    seen_envs.add(env)
    episodes, steps = task.get("episodes"), task.get("steps")
    if (episodes is None) == (steps is None):
        raise ValueError(f"{at}: exactly one of the fields 'episodes' and 'steps' must be set")
    for fname, value in (("episodes", episodes), ("steps", steps)):
        if value is not None and not (is_int(value) and value >= 1):
            raise ValueError(f"{at}: field '{fname}' must be an int >= 1; got {value!r}")
    learner = task.get("learner", {})
    if not isinstance(learner, dict) or "method" in learner:
        raise ValueError(
            f"{at}: field 'learner' must be a table of learner settings other than method"
        )
    budget = {"episodes": episodes} if episodes is not None else {"steps": steps}
    return env, budget, learner


def parse_spec(data: dict[str, Any], where: str = "spec") -> GridSpec:
    """Validate a spec dictionary and expand it into runs (no run is started): every task,
    then every seed, then every method."""
    name, kind = _parse_header(data, where)
    methods = _parse_methods(data["methods"], where)
    seeds = _parse_seeds(data["seeds"], where)
    common, base_learner = _parse_common(data, where)
    tasks = data["tasks"]
    if not (isinstance(tasks, list) and tasks and all(isinstance(t, dict) for t in tasks)):
        raise _fail(where, "tasks", tasks, "a non-empty array of tables ([[tasks]])")
    runs: list[RunSpec] = []
    seen_envs: set[str] = set()
    parsed = []
    for i, task in enumerate(tasks):
        at = f"{where}: tasks[{i}]"
        env, budget, task_learner = _parse_task(task, at, seen_envs)
        task_seeds = _parse_seeds(task["seeds"], at) if "seeds" in task else seeds
        parsed.append((at, env, budget, task_learner, task_seeds))
    all_seeds = list(dict.fromkeys(s for *_, task_seeds in parsed for s in task_seeds))
    sweep = parse_sweep(data, where, methods, all_seeds) if "sweep" in data else None
    for at, env, budget, task_learner, task_seeds in parsed:
        for seed in task_seeds:
            for method in methods:
                build = functools.partial(kind.grid_config, env, method, seed, budget, common)
                for setting in settings_of(sweep, method):
                    cfg = _swept_config(build, base_learner, task_learner, setting,
                                        (where, at, method))  # fmt: skip
                    runs.append(RunSpec(method, env, seed, cfg, setting))
    return GridSpec(name=name, runs=tuple(runs), source=where, sweep=sweep)


def _swept_config(
    build: Callable[[dict[str, Any], str], Any],
    base: dict[str, Any],
    own: dict[str, Any],
    setting: Setting,
    places: tuple[str, str, str],
) -> Any:
    """One run's configuration with its swept ``setting`` over the spec's and the task's
    learner tables (:func:`_run_config`); ``places`` holds the spec, the task's place and
    the method. A bad swept value is named by its section, ``sweep.<method>.<field>``: the
    first field refused alone, or every field when only their combination is."""
    spec, at, method = places
    if not setting:
        return _run_config(build, base, own, spec, at)
    for name, _ in setting:
        if name in own:
            raise ValueError(f"{at}.learner: field '{name}' is swept by sweep.{method}; "
                             "a task's table cannot set it")  # fmt: skip
    prefix = f"{spec}: sweep.{method}"
    try:
        return build({**base, **own, **dict(setting)}, prefix)
    except ValueError as exc:
        _run_config(build, base, own, spec, at)  # raises if the fault is not the sweep's
        reason = str(exc).removeprefix(f"{prefix}: ")
    culprits = [n for n, v in setting if _fails(build, {**base, **own, n: v}, at)]
    names = culprits[:1] or [n for n, _ in setting]
    raise ValueError(f"{prefix}.{' and '.join(names)}: {reason}")


def _run_config(
    build: Callable[[dict[str, Any], str], Any],
    base: dict[str, Any],
    own: dict[str, Any],
    spec: str,
    at: str,
) -> Any:
    """One run's configuration, ``build(learner settings, where)``, from the spec's
    ``[learner]`` table ``base`` and its task's ``own``. An error names the table that holds
    the bad setting: the task's (``tasks[i].learner``), or the spec's (``learner``) when the
    run fails with the spec's table alone and not without it."""
    try:
        return build({**base, **own}, f"{at}.learner")
    except ValueError:
        if base and not _fails(build, {}, at):
            build(base, f"{spec}: learner")  # raises, naming the spec's table: the fault
        raise


def _fails(build: Callable[[dict[str, Any], str], Any], learner: dict[str, Any], at: str) -> bool:
    try:
        build(learner, at)
    except ValueError:
        return True
    return False


def load_spec(path: str | Path) -> GridSpec:
    """Read and validate a TOML grid spec."""
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"grid spec {p} does not exist")
    try:
        data = tomllib.loads(p.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{p}: not valid TOML: {exc}") from None
    return parse_spec(data, str(p))


def spec_summary(spec: GridSpec) -> dict[str, Any]:
    """A JSON-ready description of the grid (saved beside its results); a sweep's also
    records the sweep (``"sweep"``) and each run's swept settings (``"setting"``)."""
    summary: dict[str, Any] = {
        "name": spec.name,
        "source": spec.source,
        "runs": [
            {
                "key": r.key,
                "method": r.method,
                "env": r.env,
                "seed": r.seed,
                **({"setting": dict(r.setting)} if spec.sweep is not None else {}),
                "config": dataclasses.asdict(r.config),
            }
            for r in spec.runs
        ],
    }
    if spec.sweep is not None:
        summary["sweep"] = spec.sweep.summary()
    return summary
