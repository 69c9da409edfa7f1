"""The layout of the package (``src/pporpe``): rooms that import one way.

Every file says what it owns in its first line and stays under 600 lines, every function
under 60; no file imports one that imports it back (TYPE_CHECKING and function-level
imports included), anywhere in the package; the rooms' arrows point one way (the
environments' families never import the face, the grids and the reports never import each
other, the online and the batch report never import each other nor does a sweep's report
import the online one); the old module paths of
the environments re-export the same objects with a DeprecationWarning. For the online
learner: both engines answer the population's interface, the fused kernel's disk cache is
keyed on all of its files, and the warm-up compiles every signature a population then
calls.
"""

from __future__ import annotations

import ast
import importlib
import inspect
import sys
from pathlib import Path

import numpy as np
import pytest
from tiny import ACT, HIGH, LOW, OBS
from tiny import small_config as cfg

import pporpe
from pporpe.online.engine import Engine
from pporpe.online.population import PopulationLearner

PACKAGE = Path(pporpe.__file__).resolve().parent
SRC = PACKAGE.parent
MAX_LINES = 600
MAX_FUNCTION_LINES = 60


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


FILES = {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


@pytest.mark.parametrize("name", sorted(FILES))
def test_every_file_says_what_it_owns_and_is_short(name: str) -> None:
    text = FILES[name].read_text()
    doc = ast.get_docstring(ast.parse(text))
    assert doc and doc.splitlines()[0].strip(), f"{name} has no module docstring"
    assert len(text.splitlines()) <= MAX_LINES, name


@pytest.mark.parametrize("name", sorted(FILES))
def test_every_function_is_short(name: str) -> None:
    """From ``def`` to its last line, docstring included (decorators not counted)."""
    tree = ast.parse(FILES[name].read_text())
    long = [
        f"{node.name} ({node.end_lineno - node.lineno + 1} lines)"
        for node in ast.walk(tree)
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
        and node.end_lineno is not None
        and node.end_lineno - node.lineno + 1 > MAX_FUNCTION_LINES
    ]
    assert not long, f"{name}: {', '.join(long)}"


def _imports(name: str, path: Path) -> set[str]:
    """The modules of ``src/pporpe`` that ``name`` imports, anywhere in the file."""
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            module = ".".join(base + ([node.module] if node.module else []))
            for alias in node.names:
                sub = f"{module}.{alias.name}"
                found.add(sub if sub in FILES else module)
        elif isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
    return {m for m in found if m in FILES and m != name}


GRAPH = {name: _imports(name, path) for name, path in FILES.items()}


def test_the_import_graph_sees_every_kind_of_import() -> None:
    """Module-level, function-level and TYPE_CHECKING imports, relative and absolute, are
    all edges (a cycle through any of them would go unseen otherwise)."""
    assert "pporpe.envs" in GRAPH["pporpe.batch.vecenv"]  # module level, relative
    assert "pporpe.runs.loop" in GRAPH["pporpe.experiments.grids.backends"]  # in a function
    assert "pporpe.envs.registration" in GRAPH["pporpe.envs"]  # a submodule by name


def test_no_file_imports_one_that_imports_it_back() -> None:
    done: set[str] = set()

    def visit(name: str, path: list[str]) -> None:
        if name in path:
            raise AssertionError(" -> ".join([*path[path.index(name) :], name]))
        if name not in done:
            for other in sorted(GRAPH[name]):
                visit(other, [*path, name])
            done.add(name)

    for name in sorted(GRAPH):
        visit(name, [])


def _reach(name: str) -> set[str]:
    """Every module ``name`` imports, directly or through others."""
    seen: set[str] = set()
    todo = [name]
    while todo:
        for other in GRAPH[todo.pop()] - seen:
            seen.add(other)
            todo.append(other)
    return seen


def _room(prefix: str) -> list[str]:
    return [n for n in FILES if n == prefix or n.startswith(prefix + ".")]


ARROWS = [
    # (a room, what none of its modules reaches, whether that module alone or its room)
    ("pporpe.online.torch_engine", "pporpe.online.population", "alone"),
    ("pporpe.online.fused_engine", "pporpe.online.population", "alone"),
    ("pporpe.envs.bullet", "pporpe.envs", "alone"),  # a family never imports the face
    ("pporpe.envs.mujoco", "pporpe.envs", "alone"),
    ("pporpe.envs.registration", "pporpe", "room"),  # imports nothing of pporpe
    ("pporpe.experiments.grids", "pporpe.experiments.reports", "room"),
    ("pporpe.experiments.reports", "pporpe.experiments.grids", "room"),
    ("pporpe.experiments.reports.online", "pporpe.experiments.reports.batch", "room"),
    ("pporpe.experiments.reports.batch", "pporpe.experiments.reports.online", "room"),
    # a sweep's report reads runs as the batch report does, never the online report's code
    ("pporpe.experiments.reports.sweep", "pporpe.experiments.reports.online", "room"),
    ("pporpe.experiments.reports.online", "pporpe.experiments.reports.sweep", "room"),
    ("pporpe.experiments.reports.batch", "pporpe.experiments.reports.sweep", "room"),
    # what both rooms know of a sweep imports neither room
    ("pporpe.experiments.sweep_terms", "pporpe.experiments.grids", "room"),
    ("pporpe.experiments.sweep_terms", "pporpe.experiments.reports", "room"),
]


@pytest.mark.parametrize(("room", "never", "scope"), ARROWS)
def test_the_rooms_arrows_point_one_way(room: str, never: str, scope: str) -> None:
    """No module of ``room`` imports ``never`` (``alone``: that module; ``room``: it or any
    of its submodules), directly or through others."""
    for name in _room(room):
        inside = [never] if scope == "alone" else _room(never)
        reached = _reach(name) & set(inside)
        assert not reached, f"{name} -> {sorted(reached)}"


def test_what_the_reports_share_imports_neither_report() -> None:
    """The shared reporting modules reach neither the online, the batch nor a sweep's
    report; only the face of ``pporpe report`` (``reports.report``) sends a grid to one of
    them."""
    reports = "pporpe.experiments.reports"
    either = set(_room(f"{reports}.online") + _room(f"{reports}.batch") + _room(f"{reports}.sweep"))
    shared = [n for n in _room(reports) if n not in either and n != f"{reports}.report"]
    assert f"{reports}.stats" in shared and f"{reports}.verdicts" in shared
    for name in shared:
        reached = _reach(name) & either
        assert not reached, f"{name} -> {sorted(reached)}"


def test_every_learner_kind_of_the_package_is_found_by_name() -> None:
    """A module that registers a learner kind when imported is in ``runs.kinds._BUILTIN``,
    so that ``get_kind`` finds its kind before anything imported it (a run folder's
    ``config.json`` read in a fresh process)."""
    from pporpe.runs.kinds import _BUILTIN

    registering = set()
    for name, path in FILES.items():
        for node in ast.parse(path.read_text()).body:
            calls = [n for n in ast.walk(node) if isinstance(n, ast.Call)]
            if any(getattr(c.func, "id", None) == "register_kind" for c in calls):
                registering.add(name)
    assert {"pporpe.online.kind", "pporpe.batch.kind"} <= registering  # the scan sees them
    assert registering == set(_BUILTIN.values())


def test_both_engines_answer_the_populations_interface() -> None:
    from pporpe.online.fused_engine import FusedEngine
    from pporpe.online.torch_engine.engine import TorchEngine

    calls = [n for n, f in vars(Engine).items() if inspect.isfunction(f) and n[0] != "_"]
    assert sorted(calls) == ["begin", "outputs", "set_member", "step"]
    for engine in (TorchEngine, FusedEngine):
        for call in calls:
            theirs = inspect.signature(getattr(engine, call)).parameters
            assert list(theirs) == list(inspect.signature(getattr(Engine, call)).parameters)


ENV_OLD_PATHS = {
    "pporpe.bullet_step": ("pporpe.envs.bullet", "pporpe.envs.side_by_side"),
    "pporpe.mujoco_step": ("pporpe.envs.mujoco",),
}


@pytest.mark.parametrize("old", sorted(ENV_OLD_PATHS))
def test_the_environments_old_paths_warn_and_re_export_the_same_objects(old: str) -> None:
    if old == "pporpe.mujoco_step":
        pytest.importorskip("mujoco")
    homes = [importlib.import_module(h) for h in ENV_OLD_PATHS[old]]
    sys.modules.pop(old, None)
    with pytest.warns(DeprecationWarning, match=old.replace(".", r"\.")):
        module = importlib.import_module(old)
    for home in homes:
        for name in home.__all__:
            assert getattr(module, name) is getattr(home, name), (old, name)
    assert set(module.__all__) == set().union(*(h.__all__ for h in homes))


@pytest.mark.parametrize("old", ["fused", "optim", "traces", "tsoft", "update"])
def test_the_online_learners_old_module_paths_are_gone(old: str) -> None:
    """Deprecated for one release (CHANGELOG), then removed."""
    assert f"pporpe.online.{old}" not in FILES
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module(f"pporpe.online.{old}")


def test_the_fused_engines_old_names_are_there() -> None:
    from pporpe.online import fused_engine

    for name in ("FusedEngine", "compile_kernels", "segment_ranges", "warm_up"):
        assert callable(getattr(fused_engine, name))


def test_the_kernel_cache_is_keyed_on_every_kernel_file(tmp_path: Path) -> None:
    from pporpe.online.fused_engine.kernels import jit, step

    for name in ("a.py", "b.py"):
        (tmp_path / name).write_text("x = 1\n")
    before = jit.kernels_source_stamp(tmp_path)
    (tmp_path / "b.py").write_text("x = 2\n")
    assert jit.kernels_source_stamp(tmp_path) != before
    stamp = jit.kernels_source_stamp()
    dispatchers = [f for f in vars(step).values() if hasattr(f, "_cache")]
    assert len(dispatchers) >= 10  # the step's own and those it imports
    for kernel in dispatchers:
        assert kernel._cache._cache_file._source_stamp == stamp, kernel.__name__


def test_the_warm_up_compiles_every_signature_a_population_calls() -> None:
    """A population after the warm-up adds no signature to the kernels: every process
    that trains loads them, none compiles (tests/test_fused.py, compiled_or_loaded)."""
    import torch

    from pporpe.online.fused_engine import _KERNELS, warm_up

    warm_up()
    before = [list(k.signatures) for k in _KERNELS]
    pop = PopulationLearner(OBS, LOW, HIGH, [cfg(), cfg(method="ppo")], [0, 1], engine="fused")
    no = np.zeros(2, dtype=bool)
    pop.begin_episode([0, 1], np.zeros((2, OBS)))
    pop.step(np.ones(2), np.ones((2, OBS)), no, no, active=np.array([True, False]))
    forced = torch.zeros(2, ACT)
    pop.step(np.ones(2), np.ones((2, OBS)), no, np.ones(2, dtype=bool), forced_u=forced)
    pop.begin_episode([1], np.zeros((1, OBS)), forced_u=forced[:1])
    pop.act_deterministic(np.zeros((2, OBS)))
    pop.value(np.zeros((2, OBS)))
    assert [list(k.signatures) for k in _KERNELS] == before
