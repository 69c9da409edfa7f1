"""``pporpe`` commands and docs scripts in child processes that start warm.

A test that runs the CLI as a user does (``python -m pporpe.cli ...``) or a docs example as
a reader does (``python example.py``) pays about 3 s of CPU before the command reads its
first argument: the interpreter imports torch and loads the fused engine's kernels from
numba's cache. About a hundred such runs made a third of ``make test``'s CPU time.

Here each command runs in a child forked from one server process per test worker
(:mod:`multiprocessing`'s forkserver), which imported :data:`PRELOAD` and loaded the
kernels once, and ran nothing else. The child then becomes what ``python -m pporpe.cli
ARGS`` (or ``python SCRIPT``) would be: its own working folder, environment, ``sys.argv``,
``sys.path[0]`` (the working folder for ``-m``, the script's folder for a script) and
``PYTHONPATH`` entries, resource limits, standard streams (files the parent reads), exit
status (``sys.exit``'s code; 1 and a traceback for an uncaught exception) and ``atexit``
handlers. Everything the command imports beyond :data:`PRELOAD` is imported afresh.

What differs from a fresh interpreter, and where a test must not use this:

- modules in :data:`PRELOAD` are imported already, so environment variables they read at
  import (``NUMBA_*``, ``TORCH_*``, ``OMP_*``, ``MKL_*``, ``KMP_*``) cannot be changed for
  one command: :func:`run` takes a real subprocess when ``env`` changes any of them;
- CPU time and peak memory (:attr:`Finished.cpu_s`, :attr:`Finished.max_rss_kb`) count
  from the fork: the interpreter's start is not in them (the memory of the preloaded
  modules is, as it is in a process that imported them);
- ``PYTHONWARNINGS`` and the thread counts (:data:`THREAD_ENV`) are applied as the
  interpreter and torch would have at start;
- a test of the interpreter's start itself (what a cold process imports, say) keeps using
  :mod:`subprocess`. A test that signals or kills the command and its workers takes
  :func:`start`: a process group of its own, as a shell starts a job.
"""

from __future__ import annotations

import atexit
import json
import multiprocessing
import os
import resource
import runpy
import signal
import subprocess
import sys
import tempfile
import warnings
from dataclasses import dataclass
from multiprocessing import forkserver
from pathlib import Path
from typing import Any

PRELOAD = ["warm_process_preload"]
"""Modules the server imports before it forks anything (:mod:`warm_process_preload`)."""

IMPORT_TIME_ENV = ("NUMBA_", "TORCH_", "OMP_", "MKL_", "KMP_", "OPENBLAS_", "PYTHONHASHSEED")
"""Prefixes of environment variables read when a preloaded module is imported."""

THREAD_ENV = ("OMP_NUM_THREADS", "MKL_NUM_THREADS")
"""Of those, the ones a command may still set: the child applies them with
:func:`torch.set_num_threads` (the server ran no torch operation, so no thread pool was
sized yet)."""

_CONTEXT = multiprocessing.get_context("forkserver")
_CONTEXT.set_forkserver_preload(PRELOAD)


def start_the_server() -> None:
    """Start the server, if it is not running, with this folder on its ``PYTHONPATH``
    (where it finds :data:`PRELOAD`: Python 3.11's forkserver imports it before it applies
    the caller's ``sys.path``, and skips a module it cannot import), and with this
    process's environment otherwise.

    It is this process's one forkserver: a grid's local pool started by a test forks its
    workers from it as well (pporpe's own preload, a subset of :data:`PRELOAD`, is then
    not used), so ``conftest.py`` starts it before the first test, and :data:`PRELOAD` is
    set again here in case a pool set its own."""
    _CONTEXT.set_forkserver_preload(PRELOAD)
    before = os.environ.get("PYTHONPATH")
    here = str(Path(__file__).resolve().parent)
    os.environ["PYTHONPATH"] = os.pathsep.join(p for p in (here, before) if p)
    try:
        forkserver.ensure_running()
    finally:
        if before is None:
            del os.environ["PYTHONPATH"]
        else:
            os.environ["PYTHONPATH"] = before


@dataclass
class Finished:
    """A finished command, as :class:`subprocess.CompletedProcess` has it, and its usage."""

    args: list[str]
    returncode: int
    stdout: str
    stderr: str
    cpu_s: float | None = None
    """User + system CPU seconds of the command's process since the fork (None if it was
    killed before it could say)."""
    max_rss_kb: int | None = None
    """Its peak resident memory in kB (None as for :attr:`cpu_s`)."""


def run(
    args: list[str],
    *,
    script: Path | None = None,
    cwd: Path | None = None,
    env: dict[str, str] | None = None,
    limits: dict[int, tuple[int, int]] | None = None,
    timeout: float = 600,
) -> Finished:
    """``python -m pporpe.cli *args`` (or ``python script *args``) in ``cwd`` with the
    environment ``env`` (default: this process's), under the resource ``limits``
    (:mod:`resource` constants to soft and hard limits); killed after ``timeout`` wall
    seconds (exit status -9)."""
    env = dict(os.environ if env is None else env)
    if _import_time_env_changed(env):
        return _subprocess(args, script, cwd, env, limits, timeout)
    with tempfile.TemporaryDirectory() as folder:
        child = _fork(args, script, cwd, env, limits, folder, session=False)
        child.join(timeout)
        if child.is_alive():
            child.kill()
            child.join()
        usage = _read_json(str(Path(folder, "usage")))
        return Finished(
            args=list(args),
            returncode=child.exitcode if child.exitcode is not None else -9,
            stdout=Path(folder, "out").read_text(errors="replace"),
            stderr=Path(folder, "err").read_text(errors="replace"),
            cpu_s=usage.get("cpu_s"),
            max_rss_kb=usage.get("max_rss_kb"),
        )


def _fork(
    args: list[str],
    script: Path | None,
    cwd: Path | None,
    env: dict[str, str],
    limits: dict[int, tuple[int, int]] | None,
    folder: str,
    session: bool,
) -> Any:
    """The command's process, started from the server; its streams and usage go to files
    in ``folder`` (``out``, ``err``, ``usage``)."""
    start_the_server()
    where = str(Path(cwd or os.getcwd()).resolve())
    child = _CONTEXT.Process(
        target=_become_the_command,
        args=(args, None if script is None else str(script), where, env, limits, folder, session),
    )
    child.start()
    return child


class Started:
    """A command started by :func:`start`, waited on as :class:`subprocess.Popen` is."""

    def __init__(self, child: Any, folder: str) -> None:
        self._child = child
        self._folder = folder
        self.pid: int = child.pid
        self.returncode: int | None = None

    def poll(self) -> int | None:
        """The exit status, or None while it runs."""
        if self.returncode is None and self._child.exitcode is not None:
            self.returncode = self._child.exitcode
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        """Wait for the exit status; :class:`subprocess.TimeoutExpired` after ``timeout``."""
        self._child.join(timeout)
        if self.poll() is None:
            raise subprocess.TimeoutExpired(["pporpe"], timeout or 0.0)
        return self.returncode  # type: ignore[return-value]

    def communicate(self, timeout: float | None = None) -> tuple[str, str]:
        """Wait, then what it wrote to standard output and standard error."""
        self.wait(timeout)
        out, err = (Path(self._folder, n).read_text(errors="replace") for n in ("out", "err"))
        return out, err


def start(
    args: list[str], *, cwd: Path | None = None, env: dict[str, str] | None = None
) -> Started:
    """``python -m pporpe.cli *args`` started as :func:`run` runs it, in a session and
    process group of its own (as a shell starts a job, so ``os.killpg(started.pid, ...)``
    reaches the command and every process it starts), with Python's own Ctrl-C handler."""
    env = dict(os.environ if env is None else env)
    assert not _import_time_env_changed(env), "start() cannot change what torch read"
    folder = tempfile.mkdtemp(prefix="warm-process-")
    return Started(_fork(args, None, cwd, env, None, folder, session=True), folder)


def _import_time_env_changed(env: dict[str, str]) -> bool:
    keys = {k for k in set(env) | set(os.environ) if k.startswith(IMPORT_TIME_ENV)}
    keys -= set(THREAD_ENV)
    return any(env.get(k) != os.environ.get(k) for k in keys)


def _read_json(path: str) -> dict[str, Any]:
    try:
        return dict(json.loads(Path(path).read_text()))
    except (OSError, ValueError):
        return {}


def _subprocess(
    args: list[str],
    script: Path | None,
    cwd: Path | None,
    env: dict[str, str],
    limits: dict[int, tuple[int, int]] | None,
    timeout: float,
) -> Finished:
    """The same command in a fresh interpreter (for an ``env`` that a preloaded module
    would have read at import)."""
    head = [sys.executable, str(script)] if script else [sys.executable, "-m", "pporpe.cli"]

    def set_limits() -> None:
        for which, values in (limits or {}).items():
            resource.setrlimit(which, values)

    try:
        done = subprocess.run([*head, *args], cwd=cwd, env=env, capture_output=True,
                              text=True, timeout=timeout, preexec_fn=set_limits)  # fmt: skip
    except subprocess.TimeoutExpired as late:
        return Finished(list(args), -9, _text(late.stdout), _text(late.stderr))
    return Finished(list(args), done.returncode, done.stdout, done.stderr)


def _text(data: bytes | str | None) -> str:
    return data.decode(errors="replace") if isinstance(data, bytes) else (data or "")


def _become_the_command(
    args: list[str],
    script: str | None,
    cwd: str,
    env: dict[str, str],
    limits: dict[int, tuple[int, int]] | None,
    folder: str,
    session: bool,
) -> None:
    """In the forked child: become ``python -m pporpe.cli ARGS`` (or ``python SCRIPT
    ARGS``), then write this process's CPU time and peak memory."""
    import warm_process_preload  # the server's, imported already

    if session:  # start(): a job of its own, interrupted as a terminal would
        os.setsid()
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    for fd, name in ((1, "out"), (2, "err")):
        target = os.open(Path(folder, name), os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        os.dup2(target, fd)
        os.close(target)
    sys.stdout = open(1, "w", closefd=False, buffering=1)
    sys.stderr = open(2, "w", closefd=False, buffering=1)
    os.chdir(cwd)
    os.environ.clear()
    os.environ.update(env)
    first = str(Path(script).resolve().parent) if script else cwd
    given = env.get("PYTHONPATH", "")  # an empty entry of a set one is the working folder
    wanted = [os.path.abspath(p) for p in given.split(os.pathsep)] if given else []
    rest: list[str] = []  # made absolute and each once, as site.removeduppaths leaves them
    for entry in map(os.path.abspath, (*wanted, *warm_process_preload.INTERPRETER_PATH)):
        if entry not in rest:
            rest.append(entry)
    sys.path[:] = [first, *rest]
    if env.get("PYTHONWARNINGS") != warm_process_preload.WARNINGS:
        warnings.resetwarnings()
        warnings._processoptions(env.get("PYTHONWARNINGS", "").split(","))  # as at start
    threads = [env[k] for k in THREAD_ENV if k in env]
    if threads:
        warm_process_preload.torch.set_num_threads(int(threads[0]))
    for which, values in (limits or {}).items():
        resource.setrlimit(which, values)
    try:
        if script is None:
            sys.argv = [str(Path(__file__).parent), *args]  # replaced by runpy below
            runpy.run_module("pporpe.cli", run_name="__main__", alter_sys=True)
        else:
            sys.argv = [script, *args]
            runpy.run_path(script, run_name="__main__")
    finally:
        atexit._run_exitfuncs()
        _write_usage(str(Path(folder, "usage")))


def _write_usage(path: str) -> None:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    Path(path).write_text(json.dumps({"cpu_s": usage.ru_utime + usage.ru_stime,
                                      "max_rss_kb": usage.ru_maxrss}))  # fmt: skip
