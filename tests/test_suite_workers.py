"""How ``make test`` spreads the suite over its workers: tests marked with the same
``xdist_group`` run on one worker (``--dist loadgroup``), so that they share what a
module-scoped fixture made once (a Ray head, a reference grid, a trained sweep)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

GROUPED = """
import os
import pytest

pytestmark = pytest.mark.xdist_group("one")


@pytest.mark.parametrize("i", range(8))
def test_where(i: int) -> None:
    print("worker", os.environ["PYTEST_XDIST_WORKER"])
"""


def test_tests_of_one_group_run_on_one_worker(tmp_path: Path) -> None:
    """Eight tests of one group over two workers: one worker runs them all (the Makefile's
    options; pytest 9.2 with pytest-xdist 3.8.0 spread them over both)."""
    (tmp_path / "test_grouped.py").write_text(GROUPED)
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "-n", "2", "--dist", "loadgroup", "-v", "-s",
         "-p", "no:cacheprovider", "--rootdir", str(tmp_path), str(tmp_path)],
        capture_output=True, text=True, timeout=300, cwd=tmp_path,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    workers = {line.split()[0] for line in done.stdout.splitlines() if " PASSED " in line}
    assert done.stdout.count(" PASSED ") == 8 and len(workers) == 1, done.stdout
