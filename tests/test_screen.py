"""What the commands show on the screen: a bar for the test episodes, episodes counted from
1, "1 episode" and "0.00" (not "1 episodes", "-0.00"), "already done" for a finished run,
and the live progress a grid's bar reads between two checkpoints."""

from __future__ import annotations

import io
import json
import re
from pathlib import Path
from typing import Any

import pytest

from pporpe.cli import main
from pporpe.evaluation import evaluate_policy, summarize_returns
from pporpe.online import OnlineConfig, TrainConfig
from pporpe.runs import train
from pporpe.runs.cadence import LIVE_FILE
from pporpe.runs.loop import load_policy, run_queue
from pporpe.text import count, fixed

TINY = ("--layers", "1", "--units", "8", "--quiet")


class Terminal(io.StringIO):
    """Standard error as a terminal: the bars that draw only there draw."""

    def isatty(self) -> bool:
        return True


def test_counts_and_numbers_read_as_words() -> None:
    assert [count(n, "episode") for n in (0, 1, 2)] == ["0 episodes", "1 episode", "2 episodes"]
    assert count(1, "CPU") == "1 CPU" and count(3, "CPU") == "3 CPUs"
    assert [fixed(x) for x in (-0.001, -0.004999, 0.0, -0.0, -0.005, 1.234)] == [
        "0.00", "0.00", "0.00", "0.00", "-0.01", "1.23",
    ]  # fmt: skip
    assert fixed(-0.04, 1) == "0.0" and fixed(-0.06, 1) == "-0.1"


def test_a_test_return_near_zero_over_one_episode(capsys: pytest.CaptureFixture[str]) -> None:
    from pporpe.cli import _print_eval

    _print_eval(summarize_returns([-0.001]))
    assert capsys.readouterr().out == (
        "test return over 1 episode: median 0.00, mean 0.00, IQR 0.00 [0.00, 0.00]\n"
    )


def small_run(tmp_path: Path, episodes: int = 3, eval_episodes: int = 2) -> TrainConfig:
    return TrainConfig(env="pendulum", seed=1, episodes=episodes, checkpoint_every=1,
                       eval_episodes=eval_episodes,
                       learner=OnlineConfig(layers=1, units=8, compile=False))  # fmt: skip


def test_the_train_bar_counts_episodes_from_1_and_the_test_episodes_have_a_bar(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The train bar showed "3/3 [..., ep=2, ...]", a 0-based episode beside a 1-based
    count, and the test episodes ran without a bar (HalfCheetah: 40 s of silence)."""
    screen = Terminal()
    monkeypatch.setattr("sys.stderr", screen)
    train(small_run(tmp_path), tmp_path / "run", progress=True)
    text = screen.getvalue()
    last_train = [d for d in text.split("\r") if d.startswith("rpe pendulum s1")][-1]
    assert " 3/3 " in last_train and "ep=3," in last_train, last_train
    tests = [d for d in text.split("\r") if d.startswith("test episodes")]
    assert tests and " 2/2 " in tests[-1], text


def test_the_test_episode_bar_is_quiet_off_a_terminal_and_under_quiet(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    run = tmp_path / "run"
    train(small_run(tmp_path, eval_episodes=0), run, progress=False)
    policy = load_policy(run)
    pipe = io.StringIO()  # a log file or a pipe
    monkeypatch.setattr("sys.stderr", pipe)
    evaluate_policy(policy, "pendulum", 2, seed=0, progress=True)
    assert pipe.getvalue() == ""
    for args, shown in (([], True), (["--quiet"], False)):
        screen = Terminal()
        monkeypatch.setattr("sys.stderr", screen)
        assert main(["evaluate", str(run), "--episodes", "2", *args]) == 0
        assert ("test episodes" in screen.getvalue()) is shown, screen.getvalue()
        assert "test return over 2 episodes" in capsys.readouterr().out


def test_rerunning_a_finished_run_says_it_is_done(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """It printed "trained 1 episodes, 14 steps in 0.1 s" again, as if it had trained."""
    run = tmp_path / "run"
    args = ["train", "--env", "pendulum", "--episodes", "1", "--eval-episodes", "1", *TINY,
            "--out", str(run)]  # fmt: skip
    assert main(args) == 0
    first = capsys.readouterr().out
    assert first.startswith("trained 1 episode, ") and "test return over 1 episode:" in first
    stamp = (run / "done.json").stat().st_mtime_ns, (run / "episodes.csv").stat().st_mtime_ns
    assert main(args) == 0
    again = capsys.readouterr().out.splitlines()
    assert again[0] == (f"already done: {run} holds this run, complete (--force starts over)")
    # what it trained then, and its test return: the first call's lines
    assert again[1:] == first.splitlines()
    assert stamp == ((run / "done.json").stat().st_mtime_ns,
                     (run / "episodes.csv").stat().st_mtime_ns)  # fmt: skip


def test_batch_counts_read_as_words(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    args = ["train", "--learner", "batch", "--env", "pendulum", "--steps", "64", "--n-envs",
            "1", "--n-steps", "64", "--batch-size", "32", "--eval-episodes", "1", *TINY,
            "--out", str(tmp_path / "b")]  # fmt: skip
    assert main(args) == 0
    out = capsys.readouterr().out
    assert re.search(r"^trained 64 steps \(1 update, \d+ episodes?\) in ", out, re.M), out


def test_a_run_in_training_writes_its_live_progress_and_removes_it_at_the_end(
    tmp_path: Path,
) -> None:
    """The grid's bar counted only the episodes on disk, written at each checkpoint: a
    fresh grid showed "episodes=0/6000" until its first. Its runs now write
    progress.json every few seconds (here after every step), removed when they end."""
    seen: list[tuple[int, dict[str, Any]]] = []
    runs = [(small_run(tmp_path, episodes=4, eval_episodes=0), tmp_path / f"r{s}") for s in "ab"]

    def on_episode(rec: Any) -> None:
        live = json.loads((tmp_path / "ra" / LIVE_FILE).read_text())
        seen.append((rec.episode, live))

    cfg = runs[0][0]
    run_queue([(cfg, runs[0][1])], on_episode=on_episode, live_seconds=0.0)
    # written after the step before each episode's end: the episodes done until then
    assert [live["episodes"] for _, live in seen] == [episode for episode, _ in seen]
    assert all(live["total_steps"] > 0 for _, live in seen[1:])
    assert [len(live["lengths"]) for _, live in seen] == [0, 1, 2, 3]
    assert not (tmp_path / "ra" / LIVE_FILE).exists()  # removed when the run finished
    run_queue([(cfg, runs[1][1])], live_seconds=None)
    assert not (tmp_path / "rb" / LIVE_FILE).exists()  # never written unless asked
