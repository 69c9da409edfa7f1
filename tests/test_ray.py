"""The Ray backend on a real local Ray head (loopback, 2 CPUs) against the local backend."""

from __future__ import annotations

import socket
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import pytest
import ray  # noqa: F401  - part of the test install (make test installs the ray extra)

from pporpe.experiments.grid import load_spec
from pporpe.experiments.reproduce import reproduce
from pporpe.runs.logger import read_records

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


@pytest.fixture(scope="module")
def ray_head(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    ray_bin = str(Path(sys.executable).with_name("ray"))
    port = _free_port()
    tmp = tmp_path_factory.mktemp("ray")
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
    assert start.returncode == 0, start.stdout + start.stderr
    try:
        yield f"127.0.0.1:{port}"
    finally:
        subprocess.run([ray_bin, "stop", "--force"], capture_output=True, timeout=120)


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
