"""The equation map of docs/online-learner.md ("Where each equation is computed") against
the code: every function it names exists and its docstring names the row's equation or
rule, each engine has a function for every row of the step, every equation of the paper
is in the map, and every function of the engines whose docstring cites an equation is in
the map."""

from __future__ import annotations

import importlib
import inspect
import re
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

DOC = Path(__file__).resolve().parent.parent / "docs" / "online-learner.md"
SECTION = "## Where each equation is computed"
PREFIXES = {
    "torch engine": "pporpe.online.torch_engine.",
    "fused engine": "pporpe.online.fused_engine.kernels.",
    "both engines": "",
}
"""The package a column's names are under, unless they start with ``pporpe.``."""
ENGINE_MODULES = (
    "pporpe.online.torch_engine.engine",
    "pporpe.online.torch_engine.update",
    "pporpe.online.fused_engine.kernels.head",
    "pporpe.online.fused_engine.kernels.network",
    "pporpe.online.fused_engine.kernels.optimiser",
    "pporpe.online.fused_engine.kernels.step",
    "pporpe.online.fused_engine.kernels.surrogates",
)
"""The modules whose functions that cite an equation must be in the map."""


def _cells(line: str) -> list[str]:
    """The cells of a Markdown table row (``\\|`` is a pipe inside a cell)."""
    inner = line.strip().strip("|")
    return [c.strip().replace("\\|", "|") for c in re.split(r"(?<!\\)\|", inner)]


def _rows() -> list[dict[str, Any]]:
    """Every row of the section's tables: its key, and the functions of each column."""
    text = DOC.read_text()
    start = text.index(SECTION) + len(SECTION)
    end = text.find("\n## ", start)
    rows: list[dict[str, Any]] = []
    header: list[str] = []
    for line in text[start : end if end >= 0 else None].splitlines():
        if not line.startswith("|"):
            header = []
            continue
        cells = _cells(line)
        if not header:
            header = cells
        elif not set(cells[0]) <= {"-", " "}:
            key = re.fullmatch(r"`(.+)`", cells[0])
            assert key, f"the first cell of a row names the key in backticks: {line}"
            names = {
                column: [PREFIXES[column] + n if not n.startswith("pporpe.") else n
                         for n in re.findall(r"`([A-Za-z_][\w.]*\.[\w.]+)`", cell)]
                for column, cell in zip(header, cells, strict=True) if column in PREFIXES
            }  # fmt: skip
            rows.append({"key": key.group(1), "names": names})
    return rows


def _resolve(dotted: str) -> Any:
    """The object a dotted path names: the longest importable module, then attributes."""
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj: Any = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for attr in parts[i:]:
            obj = getattr(obj, attr)
        return obj
    raise ImportError(dotted)


ROWS = _rows()


def test_the_map_is_found() -> None:
    assert len(ROWS) >= 30
    assert all(row["names"] for row in ROWS)


@pytest.mark.parametrize("row", ROWS, ids=[r["key"] for r in ROWS])
def test_every_function_exists_and_its_docstring_names_the_row(row: dict[str, Any]) -> None:
    for column, names in row["names"].items():
        assert names, f"no function in the {column} column"
        for name in names:
            obj = _resolve(name)
            assert callable(obj), name
            doc = " ".join((inspect.getdoc(obj) or "").split()).lower()  # lines unwrapped
            assert row["key"].lower() in doc, f"{name}'s docstring lacks {row['key']!r}"


def test_every_equation_of_the_paper_and_algorithm_1_are_mapped() -> None:
    keys = {row["key"] for row in ROWS}
    missing = [f"eq. ({n})" for n in range(2, 17) if f"eq. ({n})" not in keys]
    assert not missing, missing  # eq. (1), the goal, is named in the text
    assert "Algorithm 1" in keys
    assert "eq. (1)" in DOC.read_text().split(SECTION)[1]


def _citing_functions(module: ModuleType) -> set[str]:
    """Functions and methods defined in ``module`` whose docstrings cite an equation."""
    out = set()
    for name, obj in vars(module).items():
        members = [(name, obj)]
        if inspect.isclass(obj) and obj.__module__ == module.__name__:
            members += [(f"{name}.{m}", f) for m, f in vars(obj).items() if callable(f)]
        for qualname, f in members:
            if getattr(f, "__module__", None) == module.__name__ and "eq. (" in (
                inspect.getdoc(f) or ""
            ):
                out.add(f"{module.__name__}.{qualname}")
    return out


def test_every_engine_function_citing_an_equation_is_in_the_map() -> None:
    mapped = {n for row in ROWS for names in row["names"].values() for n in names}
    citing = set().union(*(_citing_functions(importlib.import_module(m)) for m in ENGINE_MODULES))
    assert citing, "the engines cite no equation"
    assert citing <= mapped, sorted(citing - mapped)
