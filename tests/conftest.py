"""Test settings: property-based tests explore the same examples on every run (derandomized,
no example database), so a test run is reproducible and CI sees what a developer saw.

Under pytest-xdist (``make test`` runs ``pytest -n auto --dist loadgroup``), the fused
engine's kernels are put in numba's disk cache once, before the workers start: on a fresh
clone the cache is empty, and every worker and every process a test starts that finds it
empty would otherwise compile them at the same time (half a minute of a core each)."""

from __future__ import annotations

import subprocess
import sys

import pytest
from hypothesis import settings

settings.register_profile("pporpe", derandomize=True, database=None, print_blob=True)
settings.load_profile("pporpe")

WARM_UP = "from pporpe.online.fused_engine import warm_up; warm_up()"
"""Load the kernels from numba's cache, compiling them into it first if they are not there."""


def pytest_configure(config: pytest.Config) -> None:
    workers = getattr(config.option, "numprocesses", None)
    if workers and not hasattr(config, "workerinput"):  # xdist's controller, before workers
        subprocess.run([sys.executable, "-c", WARM_UP], check=False)
