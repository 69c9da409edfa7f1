"""The repository's scripts (docs/generate.py, experiments/collect.py) loaded as modules for
their tests: they are scripts, not part of the package."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]


def load_script(path: str, name: str) -> ModuleType:
    """The script at ``path`` (relative to the repository root) as the module ``name``."""
    spec = importlib.util.spec_from_file_location(name, ROOT / path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def docs_generator() -> ModuleType:
    """docs/generate.py, loaded from this checkout."""
    return load_script("docs/generate.py", "docs_generate")
