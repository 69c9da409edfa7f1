"""A command forked warm (:mod:`warm_process`) sees what a fresh interpreter would: the same
``sys.path``, ``sys.argv``, working folder, environment, ``__name__``, warning filters and
thread count, the same exit status and streams; only the modules it preloads are already
imported. Each case runs the same script both ways and compares what it printed."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import warm_process

VIEW = """
import json, os, sys, warnings
import torch
print(json.dumps({
    "path": sys.path,
    "argv": sys.argv[1:],
    "argv0": os.path.basename(sys.argv[0]),
    "cwd": os.getcwd(),
    "env": {k: os.environ.get(k) for k in ("PYTHONPATH", "PPORPE_PROBE", "OMP_NUM_THREADS")},
    "name": __name__,
    "filters": [f[0] for f in warnings.filters[:1]],
    "threads": torch.get_num_threads(),
    "evil": "evil_probe" in sys.modules,
}))
sys.stderr.write("to stderr\\n")
raise SystemExit(int(sys.argv[1]))
"""


def both(script: Path, args: list[str], cwd: Path, env: dict[str, str]) -> list[tuple]:
    fresh = subprocess.run([sys.executable, str(script), *args], cwd=cwd, env=env,
                           capture_output=True, text=True, timeout=120)  # fmt: skip
    warm = warm_process.run(args, script=script, cwd=cwd, env=env, timeout=120)
    return [(p.returncode, p.stdout, p.stderr) for p in (fresh, warm)]


@pytest.mark.parametrize("base", ["inherited", "absent", "relative"])
def test_a_script_sees_what_a_fresh_interpreter_shows_it(tmp_path: Path, base: str) -> None:
    """With this process's ``PYTHONPATH`` after a folder of the test's, with none (an
    empty entry: the working folder), and with a relative one."""
    script = tmp_path / "view.py"
    script.write_text(VIEW)
    extra = tmp_path / "extra"
    extra.mkdir()
    (extra / "evil_probe.py").write_text("raise SystemExit('imported')\n")
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(extra), {
            "inherited": os.environ.get("PYTHONPATH", ""), "absent": "", "relative": "extra"
        }[base]]),
        "PPORPE_PROBE": "1",
        "OMP_NUM_THREADS": "1",
        "PYTHONWARNINGS": "ignore",
    }
    fresh, warm = both(script, ["3", "x"], tmp_path, env)
    assert fresh == warm
    assert fresh[0] == 3 and fresh[2] == "to stderr\n"


def test_a_command_gets_its_own_folder_path_and_environment(tmp_path: Path) -> None:
    """``-m pporpe.cli``: the working folder first on the path, as ``python -m`` puts it."""
    folder = tmp_path / "here"
    folder.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "PPORPE_PROBE"}
    proc = warm_process.run(["train", "--method", "trpo", "--out", "x"], cwd=folder, env=env)
    fresh = subprocess.run([sys.executable, "-m", "pporpe.cli", "train", "--method", "trpo",
                            "--out", "x"], cwd=folder, env=env, capture_output=True,
                           text=True, timeout=120)  # fmt: skip
    assert (proc.returncode, proc.stdout, proc.stderr) == (
        fresh.returncode, fresh.stdout, fresh.stderr
    )
    assert proc.returncode == 2 and not (folder / "x").exists()


def test_an_uncaught_exception_exits_1_with_its_traceback(tmp_path: Path) -> None:
    script = tmp_path / "boom.py"
    script.write_text("raise ValueError('boom')\n")
    proc = warm_process.run([], script=script, cwd=tmp_path)
    assert proc.returncode == 1
    assert proc.stderr.splitlines()[-1] == "ValueError: boom"


def test_an_environment_torch_reads_at_import_takes_a_fresh_interpreter(tmp_path: Path) -> None:
    script = tmp_path / "probe.py"
    script.write_text("import os, sys; print(os.getppid() == int(sys.argv[1]))\n")
    env = {**os.environ, "NUMBA_DISABLE_JIT": "1"}
    proc = warm_process.run([str(os.getpid())], script=script, cwd=tmp_path, env=env)
    assert proc.stdout.strip() == "True"  # a child of this process: not forked by the server
    assert proc.cpu_s is None


def test_a_started_command_is_a_job_of_its_own(tmp_path: Path) -> None:
    """:func:`warm_process.start`: its own process group (``os.killpg`` reaches it), waited
    on as :class:`subprocess.Popen` is. (Ctrl-C through it: tests/test_stopping.py.)"""
    args = ["train", "--env", "pendulum", "--episodes", "100000", "--eval-episodes", "0",
            "--quiet", "--out", "r"]  # fmt: skip
    job = warm_process.start(args, cwd=tmp_path)
    deadline = time.monotonic() + 120
    while not (tmp_path / "r" / "config.json").exists():
        assert job.poll() is None, job.communicate()
        assert time.monotonic() < deadline
        time.sleep(0.05)
    assert os.getpgid(job.pid) == job.pid != os.getpgid(0)
    with pytest.raises(subprocess.TimeoutExpired):
        job.wait(timeout=0.01)
    os.killpg(job.pid, signal.SIGKILL)
    assert job.wait(timeout=60) == -signal.SIGKILL and job.poll() == -signal.SIGKILL
