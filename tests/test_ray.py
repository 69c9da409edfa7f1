"""The Ray backend on a real local Ray head (loopback, 2 CPUs) against the local backend."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import pytest
import ray  # noqa: F401  - part of the test install (make test installs the ray extra)
from resume_points import checkpointed_records, resume_problems

from pporpe.experiments.grids.reproduce import reproduce
from pporpe.experiments.grids.spec import load_spec
from pporpe.runs.logger import read_records

pytestmark = pytest.mark.xdist_group("ray")  # one worker runs them all, on its one head

SPEC = """
name = "ray-tiny"
methods = ["rb", "rpe"]
seeds = [0, 1]
eval_episodes = 2
checkpoint_every = 2

[learner]
layers = 1
units = 8

[[tasks]]
env = "pendulum"
episodes = 3
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


HEADS: dict[str, Path] = {}
"""Each head's address and the home folder its processes were started with."""


def _processes() -> dict[int, tuple[int, bytes]]:
    """Every process of the machine: its parent's pid and its environment."""
    found = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            parent = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            environment = (entry / "environ").read_bytes()
        except (OSError, ValueError, IndexError):  # gone meanwhile
            continue
        found[int(entry.name)] = (parent, environment)
    return found


def head_processes(address: str) -> list[int]:
    """The processes of this module's head at ``address``: those started with its home
    folder (its GCS, raylet, client server, monitors) and all their descendants (its
    workers). Never another head's: ``ray stop`` and a ``pgrep`` by name would reach every
    Ray process of the user, another checkout's test session's included."""
    processes, mark = _processes(), f"\0HOME={HEADS[address]}\0".encode()
    own = {pid for pid, (_, env) in processes.items() if mark in b"\0" + env + b"\0"}
    while children := {pid for pid, (parent, _) in processes.items() if parent in own} - own:
        own |= children
    return sorted(own - {os.getpid()})


def _command(pid: int) -> str:
    with contextlib.suppress(OSError):
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode("latin-1")
    return ""


def _stop_head(address: str) -> None:
    """SIGKILL to the head's processes (as ``ray stop --force``), then wait until they are
    gone (10 s at most)."""
    deadline = time.monotonic() + 10
    while (pids := head_processes(address)) and time.monotonic() < deadline:
        for pid in pids:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        time.sleep(0.1)


@pytest.fixture(scope="module")
def ray_head(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A Ray head of this module's own, with its own home folder: Ray keeps an
    authentication token in ~/.ray once a local instance has made one, and a head and
    client that disagree about it refuse to connect; these tests neither read nor leave one
    in the user's home."""
    ray_bin = str(Path(sys.executable).with_name("ray"))
    port = _free_port()
    tmp = tmp_path_factory.mktemp("ray")
    home = tmp_path_factory.mktemp("home")
    saved_home = os.environ.get("HOME")
    os.environ["HOME"] = str(home)
    start = subprocess.run(
        [
            ray_bin,
            "start",
            "--head",
            "--node-ip-address",
            "127.0.0.1",
            "--port",
            str(port),
            "--num-cpus",
            "2",
            "--include-dashboard",
            "false",
            "--disable-usage-stats",
            "--temp-dir",
            str(tmp),
        ],
        capture_output=True,
        text=True,
        timeout=180,
    )
    address = f"127.0.0.1:{port}"
    HEADS[address] = home
    try:
        assert start.returncode == 0, start.stdout + start.stderr
        yield address
    finally:
        _stop_head(address)
        if saved_home is None:
            os.environ.pop("HOME", None)
        else:
            os.environ["HOME"] = saved_home


def test_ray_backend_matches_local_backend(ray_head: str, tmp_path: Path) -> None:
    spec_path = tmp_path / "spec.toml"
    spec_path.write_text(SPEC)
    spec = load_spec(spec_path)

    via_ray = reproduce(spec, tmp_path / "ray", backend="ray", address=ray_head, progress=False)
    assert via_ray.ok, via_ray.failed
    local = reproduce(spec, tmp_path / "local", backend="local", workers=2, progress=False)
    assert local.ok
    for run in spec.runs:
        got = read_records(tmp_path / "ray" / run.key / "episodes.csv")
        want = read_records(tmp_path / "local" / run.key / "episodes.csv")
        assert [r.episode for r in got] == [0, 1, 2]
        assert [replace(r, wall_time=0.0) for r in got] == [replace(r, wall_time=0.0) for r in want]
        assert (tmp_path / "ray" / run.key / "evaluation.json").read_text() == (
            tmp_path / "local" / run.key / "evaluation.json"
        ).read_text()


def test_a_ray_worker_killed_mid_task_is_retried_from_its_checkpoint(
    ray_head: str, tmp_path: Path
) -> None:
    """kill -9 of the Ray worker running a population: Ray runs the task again, which
    resumes from the population's checkpoint, and every record is what an uninterrupted
    local run writes."""
    import threading

    from pporpe.runs.population_checkpoint import CHECKPOINT

    spec_path = tmp_path / "spec.toml"
    spec_path.write_text(SPEC.replace("episodes = 3", "episodes = 80"))
    spec = load_spec(spec_path)
    out = tmp_path / "ray"
    outcome: list[object] = []
    def run_grid() -> None:
        outcome.append(reproduce(spec, out, backend="ray", address=ray_head, progress=False,
                                 checkpoint_seconds=0.1))  # fmt: skip

    grid = threading.Thread(target=run_grid)
    grid.start()
    killed = False
    for _ in range(1200):  # until the population's first checkpoint, then kill its worker
        if list(out.glob(f"populations/*/{CHECKPOINT}")):
            workers = [pid for pid in head_processes(ray_head) if "ray::run_job" in _command(pid)]
            done_before = len(list(out.glob("*/*/seed*/done.json")))
            saved = checkpointed_records(out)
            for pid in workers:
                os.kill(pid, signal.SIGKILL)
            killed = bool(workers)
            break
        grid.join(0.05)
    grid.join(600)
    assert killed and done_before < len(spec.runs), "the worker was not killed mid-task"
    assert outcome and outcome[0].ok  # type: ignore[attr-defined]
    assert resume_problems(saved) == []  # retried from the checkpoint, not started over
    local = reproduce(spec, tmp_path / "local", backend="local", workers=1, progress=False)
    assert local.ok
    for run in spec.runs:
        got = read_records(out / run.key / "episodes.csv")
        want = read_records(tmp_path / "local" / run.key / "episodes.csv")
        assert len(got) == 80
        assert [replace(r, wall_time=0.0) for r in got] == [replace(r, wall_time=0.0) for r in want]


def test_ray_start_up_lines_stay_out_of_the_grid_bar(ray_head: str, tmp_path: Path) -> None:
    """Ray's log lines on connecting (its token warning, "Connecting to existing Ray
    cluster", "Started a local Ray instance") were written into the grid's bar; now one
    line of pporpe's says where the jobs run, above the bar, and Ray's are not shown."""
    import re

    spec_path = tmp_path / "spec.toml"
    spec_path.write_text(SPEC.replace("seeds = [0, 1]", "seeds = [0]"))
    proc = subprocess.run(
        [sys.executable, "-m", "pporpe.cli", "reproduce", str(spec_path), "--out",
         str(tmp_path / "out"), "--backend", "ray", "--address", ray_head],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    err = proc.stderr.replace("\r", "\n")
    assert not re.search(r"\b(INFO|WARNING)\b \S+\.py:\d+ -- ", err), err
    assert re.search(r"^ray: 2 CPUs at \S+$", err, re.M), err
    assert "grid: 100%" in err and "episodes=6/6]" in err  # counted again at the end
