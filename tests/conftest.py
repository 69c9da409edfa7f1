"""Test settings: property-based tests explore the same examples on every run (derandomized,
no example database), so a test run is reproducible and CI sees what a developer saw.

Under pytest-xdist (``make test`` runs ``pytest -n auto --dist loadgroup``), the fused
engine's kernels are put in numba's disk cache once, before the workers start: on a fresh
clone the cache is empty, and every worker and every process a test starts that finds it
empty would otherwise compile them at the same time (half a minute of a core each). The
process that compiles them is ``kernels_once.py``'s, whose numbers tests/test_fused.py
then takes as those of a process that compiled (instead of compiling them once more)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import warm_process
from hypothesis import settings
from kernels_once import COMPILED_HASH

settings.register_profile("pporpe", derandomize=True, database=None, print_blob=True)
settings.load_profile("pporpe")

WARM_UP = Path(__file__).with_name("kernels_once.py")
"""Loads the kernels from numba's cache, compiling them into it first if they are not there,
and prints whether it compiled them and the numbers it then got (:mod:`kernels_once`)."""


def pytest_configure(config: pytest.Config) -> None:
    workers = getattr(config.option, "numprocesses", None)
    if workers and not hasattr(config, "workerinput"):  # xdist's controller, before workers
        done = subprocess.run(
            [sys.executable, str(WARM_UP)], check=False, capture_output=True, text=True
        )
        said = done.stdout.split()
        if done.returncode == 0 and len(said) == 2 and said[0] == "compiled":
            os.environ[COMPILED_HASH] = said[1]  # the workers inherit it


@pytest.fixture(autouse=True, scope="session")
def warm_server_first() -> None:
    """:mod:`warm_process`'s server started before the first test of this process: it is the
    process's one forkserver, which a grid's local pool run by a test shares (a pool that
    started it first would leave it without what warm_process's commands need)."""
    warm_process.start_the_server()
