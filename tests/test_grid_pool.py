"""The local backend's pool: workers forked from one server that imported torch, the
trainers and the kernels once (``forkserver`` with :mod:`pporpe.experiments.grids.pool_preload`),
yet each worker as a freshly started one would be: the grid process's environment as it is
when the pool starts, and one torch thread unless ``OMP_NUM_THREADS`` says otherwise."""

from __future__ import annotations

import os
import subprocess
import sys
from concurrent.futures import ProcessPoolExecutor

import pytest

from pporpe.experiments.grids import backends


def probe() -> tuple[str | None, int, bool]:
    """In a worker: a variable set after the server started, torch's threads, and whether
    torch was there before the job (imported by the server)."""
    already = "torch" in sys.modules
    import torch

    return os.environ.get("PPORPE_PROBE"), torch.get_num_threads(), already


@pytest.mark.parametrize("threads", [None, "2"])
def test_a_worker_has_the_grid_processs_environment_and_its_thread_count(
    threads: str | None, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The server runs already (this test process's, started before the first test), so the
    variable set here reaches the worker only through the pool's initializer."""
    monkeypatch.setenv("PPORPE_PROBE", f"set after the server started ({threads})")
    if threads is None:
        monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    else:
        monkeypatch.setenv("OMP_NUM_THREADS", threads)
    ctx = backends._pool_context()
    assert ctx.get_start_method() == "forkserver"
    with ProcessPoolExecutor(
        1, ctx, initializer=backends._worker_init, initargs=(None, dict(os.environ))
    ) as pool:
        got = pool.submit(probe).result(timeout=120)
    assert got == (f"set after the server started ({threads})", int(threads or 1), True)


def test_the_preload_prints_nothing_and_leaves_sigterm_to_the_grid() -> None:
    """Imported in a process of its own (as the server does): no output that would break
    the grid's bar, SIGTERM ignored (the grid process decides when its workers stop), and
    torch, the kernels and torch's optimizer machinery in memory."""
    code = (
        "import signal, sys\n"
        "import pporpe.experiments.grids.pool_preload\n"
        "assert signal.getsignal(signal.SIGTERM) is signal.SIG_IGN\n"
        "assert {'torch', 'torch._dynamo', 'numba', 'pporpe.runs.loop'} <= set(sys.modules)\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                          timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert done.stdout == "" and done.stderr == ""
