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
import warm_process

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


# -- issue 56: one line, every time ---------------------------------------------------------
def cli(*args: str, env: dict[str, str] | None = None) -> tuple[int, str, list[str]]:
    """``pporpe ARGS`` in a process of its own (:mod:`warm_process`), as a user runs it:
    exit status, standard output and the lines of standard error."""
    proc = warm_process.run(list(args), env=env, timeout=300)
    return proc.returncode, proc.stdout, proc.stderr.splitlines()


@pytest.fixture(scope="module")
def pendulum_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    run = tmp_path_factory.mktemp("screen") / "run"
    train(small_run(run, episodes=1, eval_episodes=0), run, progress=False)
    return run


def test_evaluate_into_a_folder_it_cannot_write_prints_the_returns_and_says_where(
    pendulum_run: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """It ran every episode, printed only "Operation not permitted: .../.evaluation.json.tmp"
    and the returns were lost."""
    import errno

    import pporpe.io

    def read_only(path: Any, data: Any) -> None:
        raise OSError(errno.EROFS, "Read-only file system", str(path))

    with monkeypatch.context() as patched:
        patched.setattr(pporpe.io, "atomic_write_json", read_only)
        assert main(["evaluate", str(pendulum_run), "--episodes", "3", "--quiet"]) == 2
    out, err = capsys.readouterr()
    target = pendulum_run / "evaluation.json"
    assert err.splitlines() == [
        f"pporpe evaluate: error: could not save the test returns in {target}: Read-only "
        "file system (the returns are printed above)"
    ]
    assert not target.exists()
    # the same evaluation where it can write: the printed returns are the saved ones
    assert main(["evaluate", str(pendulum_run), "--episodes", "3", "--quiet"]) == 0
    saved = json.loads(target.read_text())["returns"]
    lines = out.splitlines()
    assert lines[0] == capsys.readouterr().out.splitlines()[0]  # the test-return line
    assert lines[1:] == ["test returns (not saved): " + " ".join(map(repr, saved))]


def test_evaluate_in_a_read_only_mount_through_the_command(
    pendulum_run: Path, tmp_path: Path
) -> None:
    """The same on a read-only bind mount (needs root and mount), as a shared results
    folder is: one line on standard error, exit status 2, the folder unchanged."""
    import subprocess

    mounted = tmp_path / "ro"
    mounted.mkdir()
    done = subprocess.run(["mount", "--bind", "-o", "ro", str(pendulum_run), str(mounted)],
                          capture_output=True, text=True, check=False)  # fmt: skip
    if done.returncode != 0:
        pytest.skip(f"cannot make a read-only mount here: {done.stderr.strip()}")
    try:
        if not subprocess.run(["touch", str(mounted / "probe")], check=False).returncode:
            pytest.skip("the bind mount is writable here")
        before = sorted(p.name for p in mounted.iterdir())
        code, out, err = cli("evaluate", str(mounted), "--episodes", "2", "--quiet")
        assert code == 2 and out.startswith("test return over 2 episodes: median ")
        assert "test returns (not saved): " in out
        assert err == [
            f"pporpe evaluate: error: could not save the test returns in "
            f"{mounted / 'evaluation.json'}: Read-only file system (the returns are printed "
            "above)"
        ]
        assert sorted(p.name for p in mounted.iterdir()) == before
    finally:
        subprocess.run(["umount", "-l", str(mounted)], check=False)


def test_a_run_of_the_other_learner_kind_is_refused_naming_the_kind(
    tmp_path: Path, pendulum_run: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An online run pointed at a batch folder listed 37 "differing" fields."""
    batch = tmp_path / "batch"
    assert main(["train", "--learner", "batch", "--env", "pendulum", "--steps", "32",
                 "--n-envs", "1", "--n-steps", "32", "--batch-size", "32", "--eval-episodes",
                 "0", *TINY, "--out", str(batch)]) == 0  # fmt: skip
    capsys.readouterr()
    files = sorted(p.name for p in batch.iterdir())
    assert main(["train", "--episodes", "1", *TINY, "--out", str(batch)]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"pporpe train: error: {batch}: this folder holds a batch run, not the online run of "
        "this command (--learner); use another --out folder, or --force to start over in it"
    ]
    assert sorted(p.name for p in batch.iterdir()) == files
    assert main(["train", "--learner", "batch", "--steps", "32", *TINY,
                 "--out", str(pendulum_run)]) == 2  # fmt: skip
    assert capsys.readouterr().err.splitlines() == [
        f"pporpe train: error: {pendulum_run}: this folder holds an online run, not the batch "
        "run of this command (--learner); use another --out folder, or --force to start over "
        "in it"
    ]


def test_a_task_that_cannot_be_built_is_named_and_force_removes_nothing(
    pendulum_run: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Hopper-v3 is registered but moved out of Gymnasium: its error did not name the task,
    and --force had already emptied the folder."""
    files = {p.name: p.stat().st_mtime_ns for p in pendulum_run.iterdir()}
    code = main(["train", "--env", "Hopper-v3", "--episodes", "1", "--force", *TINY,
                 "--out", str(pendulum_run)])  # fmt: skip
    err = capsys.readouterr().err.splitlines()
    assert code == 2 and len(err) == 1
    assert err[0].startswith("pporpe train: error: task 'Hopper-v3': "), err
    assert {p.name: p.stat().st_mtime_ns for p in pendulum_run.iterdir()} == files


# -- recording a MuJoCo task on a machine without a display -----------------------------------
def test_egl_is_chosen_only_without_a_display_and_when_unset(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import os
    import sys

    from pporpe.evaluation import prefer_egl_without_display

    monkeypatch.setattr(sys, "platform", "linux")
    for variable in ("MUJOCO_GL", "DISPLAY", "WAYLAND_DISPLAY"):
        monkeypatch.delenv(variable, raising=False)
    assert prefer_egl_without_display() is True and os.environ["MUJOCO_GL"] == "egl"
    monkeypatch.setenv("MUJOCO_GL", "osmesa")  # the user's choice stays
    assert prefer_egl_without_display() is False and os.environ["MUJOCO_GL"] == "osmesa"
    for display in ("DISPLAY", "WAYLAND_DISPLAY"):
        monkeypatch.delenv("MUJOCO_GL", raising=False)
        monkeypatch.setenv(display, ":0")
        assert prefer_egl_without_display() is False and "MUJOCO_GL" not in os.environ
        monkeypatch.delenv(display)
    monkeypatch.setattr(sys, "platform", "darwin")  # macOS renders without a display
    assert prefer_egl_without_display() is False and "MUJOCO_GL" not in os.environ


@pytest.fixture(scope="module")
def mujoco_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    pytest.importorskip("mujoco")
    pytest.importorskip("moviepy")
    run = tmp_path_factory.mktemp("mujoco") / "pendulum"
    cfg = TrainConfig(env="InvertedPendulum-v5", seed=0, episodes=1, eval_episodes=0,
                      learner=OnlineConfig(layers=1, units=8, compile=False))  # fmt: skip
    train(cfg, run, progress=False)
    return run


def headless(**variables: str) -> dict[str, str]:
    import os

    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    env.pop("MUJOCO_GL", None)
    env.pop("PYOPENGL_PLATFORM", None)
    return {**env, **variables}


def test_video_of_a_mujoco_task_without_a_display_uses_egl(
    mujoco_run: Path, tmp_path: Path
) -> None:
    """It was a mujoco.FatalError traceback (GLFW needs a display). Now MUJOCO_GL=egl is
    tried; where EGL is missing too, one line names MUJOCO_GL."""
    video = tmp_path / "video"
    code, out, err = cli("evaluate", str(mujoco_run), "--episodes", "1", "--video", str(video),
                         "--quiet", env=headless())  # fmt: skip
    if code == 0:
        assert err == [] and (video / "rl-video-episode-0.mp4").stat().st_size > 0, out
    else:
        assert code == 2 and len(err) == 1 and "and MUJOCO_GL=egl gave none" in err[0], err


@pytest.mark.parametrize(
    ("gl", "start"),
    [
        ("glfw", "pporpe evaluate: error: recording video of InvertedPendulum-v5 needs an OpenGL "
         "context, and MUJOCO_GL=glfw gave none (FatalError: "),
        ("nonsense", "pporpe evaluate: error: InvertedPendulum-v5 is a MuJoCo task, and MuJoCo "
         "cannot load the OpenGL backend MUJOCO_GL=nonsense (RuntimeError: "),
    ],
)  # fmt: skip
def test_a_mujoco_gl_that_cannot_render_is_one_line_naming_it(
    mujoco_run: Path, tmp_path: Path, gl: str, start: str
) -> None:
    video = tmp_path / "video"
    code, out, err = cli("evaluate", str(mujoco_run), "--episodes", "1", "--video", str(video),
                         "--quiet", env=headless(MUJOCO_GL=gl))  # fmt: skip
    assert code == 2 and out == "" and len(err) == 1, err
    assert err[0].startswith(start) and err[0].endswith(
        "set MUJOCO_GL=egl (a GPU driver's EGL) or MUJOCO_GL=osmesa (software, needs "
        "libOSMesa)" + (", or unset it" if gl == "nonsense" else "") + " (docs/getting-started.md)"
    ), err
    assert not video.exists()
