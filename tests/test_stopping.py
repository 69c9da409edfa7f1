"""Ctrl-C and missing packages reach the user as one line, never a traceback.

Ctrl-C (SIGINT) stops ``pporpe train`` and ``pporpe reproduce`` at the next step with a
checkpoint there (exit 130), and the same command resumes to the numbers of an
uninterrupted run; a video of a task whose renderer is missing and a MuJoCo task without
MuJoCo are refused with one line saying what to install, leaving nothing behind.
"""

from __future__ import annotations

import importlib.util
import json
import os
import re
import signal
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
import warm_process
from resume_points import checkpointed_records, resume_problems
from tiny import tiny_grid_toml

from pporpe.batch import BatchConfig
from pporpe.envs import MUJOCO_INSTALL
from pporpe.online import OnlineConfig, TrainConfig
from pporpe.runs import read_records
from pporpe.runs.folder import load_checkpoint
from pporpe.runs.loop import run_queue
from pporpe.runs.stopping import Interrupted

SMALL = OnlineConfig(layers=1, units=8, compile=False)


def strip_time(records: list[Any]) -> list[Any]:
    return [replace(r, wall_time=0.0) for r in records]


def stop_after(calls: int) -> Any:
    """A ``stop`` that asks to stop after ``calls`` units of work."""
    count = [0]

    def stop() -> bool:
        count[0] += 1
        return count[0] >= calls

    return stop


def online_runs(root: Path) -> list[tuple[Any, Path]]:
    return [
        (TrainConfig(seed=s, episodes=6, checkpoint_every=2, eval_episodes=1, learner=SMALL),
         root / f"s{s}")
        for s in (0, 1)
    ]  # fmt: skip


def batch_runs(root: Path) -> list[tuple[Any, Path]]:
    cfg = BatchConfig(
        env="pendulum", seed=3, n_envs=2, n_steps=32, batch_size=16, n_epochs=2,
        total_steps=256, layers=1, units=16, checkpoint_every=3, eval_episodes=1,
    )  # fmt: skip
    return [(cfg, root / "b")]


# (runs, population slots, units of work before the stop): a single online run stopped
# mid-episode between its checkpoints, a population of two, a batch run between checkpoints
CASES = {
    "online": (lambda root: online_runs(root)[:1], 1, 70),
    "population": (online_runs, 2, 70),
    "batch": (batch_runs, 1, 2),
}


@pytest.mark.parametrize("case", list(CASES))
def test_a_stop_checkpoints_at_that_step_and_resumes_to_the_same_numbers(
    tmp_path: Path, case: str
) -> None:
    runs, slots, calls = CASES[case]
    full = run_queue(runs(tmp_path / "full"), capacity=slots, home=tmp_path / "full")
    root = tmp_path / "stopped"
    with pytest.raises(Interrupted) as info:
        run_queue(runs(root), capacity=slots, home=root, stop=stop_after(calls))
    for (_, run), result in zip(runs(root), full, strict=True):
        logged = info.value.episodes[run]
        assert 0 < logged < len(result.records)  # stopped part-way, at the stop's step
        assert len(read_records(run / "episodes.csv")) == logged
        assert not (run / "done.json").exists()
    holder = root if slots > 1 else runs(root)[0][1]
    saved = load_checkpoint(holder)
    members = saved["members"].values() if slots > 1 else [saved]
    assert sorted(len(m["records"]) for m in members) == sorted(info.value.episodes.values())
    again = run_queue(runs(root), capacity=slots, home=root)
    for a, b in zip(again, full, strict=True):
        assert strip_time(a.records) == strip_time(b.records)
        assert a.evaluation == b.evaluation


def test_a_population_home_restarted_with_another_queue_continues_the_runs_it_shares(
    tmp_path: Path,
) -> None:
    """A population of two stopped part-way, then its home given a queue of three runs (a
    seed added): the saved packing is not this queue's, yet the two runs it holds go on
    from their saved states (their first records are the saved ones, wall times included)
    to the numbers of an uninterrupted queue, and the new run starts fresh."""
    root = tmp_path / "home"
    with pytest.raises(Interrupted):
        run_queue(online_runs(root), capacity=2, home=root, stop=stop_after(70))
    saved = load_checkpoint(root)["members"]
    extra = (replace(online_runs(root)[0][0], seed=2), root / "s2")
    again = run_queue([*online_runs(root), extra], capacity=2, home=root)
    full = run_queue(online_runs(tmp_path / "full"), capacity=2, home=tmp_path / "full")
    for (_, run), a, b in zip(online_runs(root), again[:2], full, strict=True):
        kept = saved[run.name]["records"]
        assert 0 < a.resumed_from == len(kept) < len(b.records)
        assert [r.wall_time for r in a.records[: len(kept)]] == [r["wall_time"] for r in kept]
        assert strip_time(a.records) == strip_time(b.records)
    assert again[2].resumed_from == 0 and len(again[2].records) == 6


# ------------------------------------------------------------------------------------
# The commands, in a process of their own, as a user sees them
# ------------------------------------------------------------------------------------
def launch(*args: str, env: dict[str, str] | None = None) -> warm_process.Started:
    """``pporpe ARGS`` as a terminal's job (:func:`warm_process.start`: a process group of
    its own, SIGINT handled and delivered as in a terminal, whatever the test process
    inherited or set)."""
    return warm_process.start(list(args), env=env)


def wait_for(condition: Any, proc: warm_process.Started, seconds: float = 120) -> None:
    deadline = time.monotonic() + seconds
    while not condition():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "the command did not start training in time"
        time.sleep(0.02)


def rows(path: Path) -> int:
    try:
        return len(read_records(path))
    except ValueError:  # not written yet, or being replaced
        return 0


def one_line(proc: warm_process.Started, timeout: float = 120) -> tuple[int, str]:
    _, err = proc.communicate(timeout=timeout)
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    return proc.returncode, lines[0]


TRAIN = ("train", "--env", "pendulum", "--episodes", "20000", "--checkpoint-every", "1",
         "--eval-episodes", "0", "--layers", "1", "--units", "8", "--quiet")  # fmt: skip


def test_ctrl_c_in_train_checkpoints_says_one_line_and_the_same_command_resumes(
    tmp_path: Path,
) -> None:
    run = tmp_path / "run"
    proc = launch(*TRAIN, "--out", str(run))
    wait_for(lambda: rows(run / "episodes.csv") >= 2, proc)
    os.killpg(proc.pid, signal.SIGINT)  # what Ctrl-C in a terminal does
    code, line = one_line(proc)
    assert code == 130
    match = re.fullmatch(
        r"pporpe train: interrupted at episode (\d+) \(checkpointed\); resume with the same "
        r"command",
        line,
    )
    assert match, line
    episodes = int(match.group(1))
    assert len(load_checkpoint(run)["records"]) == episodes == rows(run / "episodes.csv")
    assert not (run / "done.json").exists()
    first = strip_time(read_records(run / "episodes.csv"))
    saved = checkpointed_records(tmp_path)

    proc = launch(*TRAIN, "--out", str(run))  # the same command resumes from there
    wait_for(lambda: rows(run / "episodes.csv") > episodes + 1, proc)
    os.killpg(proc.pid, signal.SIGINT)
    code, line = one_line(proc)
    assert code == 130 and "interrupted at episode" in line
    assert strip_time(read_records(run / "episodes.csv"))[:episodes] == first
    assert resume_problems(saved) == []  # resumed from the checkpoint, not started over


GRID = tiny_grid_toml(seeds=(0,), episodes=20000)


def test_ctrl_c_in_a_grid_checkpoints_every_run_and_says_one_line(tmp_path: Path) -> None:
    spec = tmp_path / "tiny.toml"
    spec.write_text(GRID)
    out = tmp_path / "out"
    args = ("--out", str(out), "--workers", "1", "--population", "2", "--checkpoint-seconds",
            "0", "--quiet")  # fmt: skip
    proc = launch("reproduce", str(spec), *args)
    csvs = [out / "pendulum" / m / "seed0" / "episodes.csv" for m in ("ppo", "rpe")]
    wait_for(lambda: min(rows(c) for c in csvs) >= 2, proc)
    os.killpg(proc.pid, signal.SIGINT)  # the parent and its worker, as from a terminal
    code, line = one_line(proc)
    assert (code, line) == (
        130,
        "pporpe reproduce: interrupted: 0 of 2 runs done; resume with the same command",
    )
    assert not list(out.rglob("error.txt"))  # an interruption is no failure
    (home,) = (out / "populations").iterdir()
    members = load_checkpoint(home)["members"]
    assert sorted(len(m["records"]) for m in members.values()) == sorted(rows(c) for c in csvs)
    status = json.loads((out / "status.json").read_text())
    assert (status["done"], status["failed"]) == ([], {})
    assert status["pending"] == ["pendulum/ppo/seed0", "pendulum/rpe/seed0"]


def missing(module: str) -> bool:
    return importlib.util.find_spec(module) is None


@pytest.mark.skipif(not missing("pygame"), reason="pygame is installed: Pendulum-v1 renders")
@pytest.mark.skipif(missing("moviepy"), reason="needs the video extra")
def test_a_video_without_the_renderer_says_what_to_install(tmp_path: Path) -> None:
    run, video = tmp_path / "run", tmp_path / "video"
    proc = launch("train", "--env", "Pendulum-v1", "--episodes", "1", "--eval-episodes", "0",
                  "--layers", "1", "--units", "8", "--quiet", "--out", str(run))  # fmt: skip
    assert proc.wait(timeout=120) == 0, proc.communicate()
    before = (run / "evaluation.json").exists()
    proc = launch("evaluate", str(run), "--episodes", "1", "--video", str(video))
    code, line = one_line(proc)
    assert code == 2
    assert line.startswith("pporpe evaluate: error: recording video of Pendulum-v1 needs")
    assert "pygame" in line and "gymnasium[classic_control]" in line
    assert not video.exists()  # no empty folder left behind
    assert (run / "evaluation.json").exists() == before


@pytest.mark.parametrize("gl", [None, "egl"])
def test_a_mujoco_task_without_mujoco_says_what_to_install(tmp_path: Path, gl: str | None) -> None:
    """Run where ``import mujoco`` fails (a stand-in package that raises ImportError first
    on the path), as on a machine without the mujoco extra: whatever ``MUJOCO_GL`` says,
    the missing package is named, not the OpenGL backend."""
    shadow = tmp_path / "shadow" / "mujoco"
    shadow.mkdir(parents=True)
    (shadow / "__init__.py").write_text("raise ImportError(\"No module named 'mujoco'\")\n")
    path = os.pathsep.join([str(shadow.parent), os.environ.get("PYTHONPATH", "")])
    out = tmp_path / "run"
    env = {k: v for k, v in os.environ.items() if k != "MUJOCO_GL"} | {"PYTHONPATH": path}
    proc = launch("train", "--env", "HalfCheetah-v5", "--episodes", "1", "--quiet", "--out",
                  str(out), env=env | ({"MUJOCO_GL": gl} if gl else {}))  # fmt: skip
    code, line = one_line(proc)
    assert (code, line) == (
        2,
        f"pporpe train: error: HalfCheetah-v5 needs MuJoCo, which is not installed: "
        f"{MUJOCO_INSTALL}",
    )
    assert not out.exists()


def test_sigterm_to_a_grid_checkpoints_every_run_as_ctrl_c_does(tmp_path: Path) -> None:
    """What a scheduler (or ``kill``) sends before it kills: to the parent alone, then to
    the whole group; each time the runs are checkpointed at a step, one line is printed
    and the exit status is 143 (128 + SIGTERM); the same command resumes."""
    spec = tmp_path / "tiny.toml"
    spec.write_text(GRID)
    out = tmp_path / "out"
    args = ("--out", str(out), "--workers", "1", "--population", "2", "--checkpoint-seconds",
            "0", "--quiet")  # fmt: skip
    csvs = [out / "pendulum" / m / "seed0" / "episodes.csv" for m in ("ppo", "rpe")]
    for target in (os.kill, os.killpg):
        before = min(rows(c) for c in csvs)  # 0, then what the first stop checkpointed
        proc = launch("reproduce", str(spec), *args)
        wait_for(lambda b=before: min(rows(c) for c in csvs) >= b + 2, proc)  # type: ignore[misc]
        target(proc.pid, signal.SIGTERM)
        code, line = one_line(proc)
        assert (code, line) == (
            143,
            "pporpe reproduce: interrupted: 0 of 2 runs done; resume with the same command",
        )
        (home,) = (out / "populations").iterdir()
        members = load_checkpoint(home)["members"]
        assert sorted(len(m["records"]) for m in members.values()) == sorted(
            rows(c) for c in csvs
        )
    assert not list(out.rglob("error.txt"))


def test_the_first_signal_asks_the_second_interrupts_and_the_handlers_come_back() -> None:
    """SIGTERM and SIGINT alike: the first sets the request (and says which signal), the
    second raises KeyboardInterrupt at once; on exit the previous handlers are back, and
    an ignored SIGINT (a background process) stays ignored."""
    from pporpe.runs.stopping import stop_on_signals

    # SIGINT as a foreground process has it, whoever started pytest (a shell's background
    # job inherits it ignored, the case checked last)
    launched_with = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
        for sig in (signal.SIGTERM, signal.SIGINT):
            with stop_on_signals() as stop:
                assert not stop()
                os.kill(os.getpid(), sig)
                assert stop() and stop.signum == sig
                with pytest.raises(KeyboardInterrupt):
                    os.kill(os.getpid(), sig)
            assert {s: signal.getsignal(s) for s in before} == before
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        with stop_on_signals():
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
            assert signal.getsignal(signal.SIGTERM) is not before[signal.SIGTERM]
    finally:
        signal.signal(signal.SIGINT, launched_with)
