"""The layout of the online learner (``src/pporpe/online``): one learner, two engines.

Every file says what it owns in its first line and stays under 600 lines; no file
imports one that imports it back (TYPE_CHECKING and function-level imports included);
both engines answer the population's interface; the old module paths re-export the same
objects; the fused kernel's disk cache is keyed on all of its files; and the warm-up
compiles every signature a population then calls.
"""

from __future__ import annotations

import ast
import importlib
import inspect
from pathlib import Path

import numpy as np
import pytest
from tiny import ACT, HIGH, LOW, OBS
from tiny import small_config as cfg

import pporpe
from pporpe.online.engine import Engine
from pporpe.online.population import PopulationLearner

ONLINE = Path(pporpe.__file__).resolve().parent / "online"
SRC = ONLINE.parent.parent
MAX_LINES = 600


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


FILES = {_module_name(p): p for p in sorted(ONLINE.rglob("*.py"))}


@pytest.mark.parametrize("name", sorted(FILES))
def test_every_file_says_what_it_owns_and_is_short(name: str) -> None:
    text = FILES[name].read_text()
    doc = ast.get_docstring(ast.parse(text))
    assert doc and doc.splitlines()[0].strip(), f"{name} has no module docstring"
    assert len(text.splitlines()) <= MAX_LINES, name


def _imports(name: str, path: Path) -> set[str]:
    """The modules of ``src/pporpe/online`` that ``name`` imports, anywhere in the file."""
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


def test_no_file_imports_one_that_imports_it_back() -> None:
    graph = {name: _imports(name, path) for name, path in FILES.items()}
    done: set[str] = set()

    def visit(name: str, path: list[str]) -> None:
        if name in path:
            raise AssertionError(" -> ".join([*path[path.index(name) :], name]))
        if name not in done:
            for other in sorted(graph[name]):
                visit(other, [*path, name])
            done.add(name)

    for name in sorted(graph):
        visit(name, [])
    assert "pporpe.online.population" not in set().union(
        *(graph[n] for n in graph if n.startswith(("pporpe.online.torch_engine",
                                                   "pporpe.online.fused_engine")))
    )  # fmt: skip


def test_both_engines_answer_the_populations_interface() -> None:
    from pporpe.online.fused_engine import FusedEngine
    from pporpe.online.torch_engine.engine import TorchEngine

    calls = [n for n, f in vars(Engine).items() if inspect.isfunction(f) and n[0] != "_"]
    assert sorted(calls) == ["begin", "outputs", "set_member", "step"]
    for engine in (TorchEngine, FusedEngine):
        for call in calls:
            theirs = inspect.signature(getattr(engine, call)).parameters
            assert list(theirs) == list(inspect.signature(getattr(Engine, call)).parameters)


OLD_PATHS = {
    "pporpe.online.fused": "pporpe.online.fused_engine.kernels",
    "pporpe.online.update": "pporpe.online.torch_engine.update",
    "pporpe.online.optim": "pporpe.online.torch_engine.optim",
    "pporpe.online.traces": "pporpe.online.torch_engine.traces",
    "pporpe.online.tsoft": "pporpe.online.torch_engine.tsoft",
}


@pytest.mark.parametrize("old", sorted(OLD_PATHS))
def test_the_old_module_paths_re_export_the_same_objects(old: str) -> None:
    module = importlib.import_module(old)
    assert module.__all__
    for name in module.__all__:
        obj = getattr(module, name)
        home = importlib.import_module(getattr(obj, "__module__", None) or OLD_PATHS[old])
        assert home.__name__.startswith(OLD_PATHS[old]), (old, name)
        if hasattr(obj, "__module__"):
            assert getattr(home, obj.__name__) is obj, (old, name)


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
