"""Training runs: run folder contents, resume after a crash, non-finite stops, the CLI."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch
from tiny import tiny_learner

from pporpe.cli import main
from pporpe.online.config import TrainConfig
from pporpe.runs import NonFiniteError, train
from pporpe.runs.logger import EpisodeRecord, read_records

TINY = tiny_learner(compile=True)


def cfg(**kw: Any) -> TrainConfig:
    base = dict(
        env="pendulum", seed=3, episodes=6, checkpoint_every=2, eval_episodes=2, learner=TINY
    )
    return TrainConfig(**{**base, **kw})  # type: ignore[arg-type]


def strip_time(records: list[EpisodeRecord]) -> list[EpisodeRecord]:
    return [replace(r, wall_time=0.0) for r in records]


def test_run_folder_contents(tmp_path: Path) -> None:
    result = train(cfg(), tmp_path, progress=False)
    names = {p.name for p in tmp_path.iterdir()}
    assert {
        "config.json",
        "episodes.csv",
        "checkpoint.pt",
        "evaluation.json",
        "done.json",
        "tensorboard",
    } <= names
    saved = json.loads((tmp_path / "config.json").read_text())
    assert saved["learner"]["method"] == "rpe" and saved["episodes"] == 6
    records = read_records(tmp_path / "episodes.csv")
    assert [r.episode for r in records] == list(range(6))
    assert records == result.records
    steps = [r.total_steps for r in records]
    assert steps == list(np.cumsum([r.length for r in records]))
    diags = [r.diagnostics for r in records]
    assert all(d is not None and d.trace_decay is not None for d in diags)  # all four
    assert all(0.0 <= d.past_threshold <= 1.0 and 0.0 < d.trace_decay <= 1.0 for d in diags)
    assert all(d.reg_amount >= 0.0 and d.ratio_dev >= 0.0 for d in diags)
    ev = json.loads((tmp_path / "evaluation.json").read_text())
    assert ev["episodes"] == 2 and ev["median"] == pytest.approx(np.median(ev["returns"]))
    assert list((tmp_path / "tensorboard").iterdir())  # event file written


def test_same_seed_same_records_and_parameters(tmp_path: Path) -> None:
    a = train(cfg(eval_episodes=0), tmp_path / "a", progress=False)
    b = train(cfg(eval_episodes=0), tmp_path / "b", progress=False)
    assert strip_time(a.records) == strip_time(b.records)
    sa = torch.load(tmp_path / "a" / "checkpoint.pt", weights_only=False)
    sb = torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=False)
    assert torch.equal(sa["learner"]["params"], sb["learner"]["params"])


class Crash(RuntimeError):
    pass


def test_resume_after_crash_matches_uninterrupted_run(tmp_path: Path) -> None:
    full = train(cfg(eval_episodes=0), tmp_path / "full", progress=False)

    def crash_after_episode_3(rec: EpisodeRecord) -> None:
        if rec.episode == 3:
            raise Crash

    run = tmp_path / "crashed"
    with pytest.raises(Crash):
        train(cfg(eval_episodes=0), run, progress=False, on_episode=crash_after_episode_3)
    # the last checkpoint was after episode index 1 (2 episodes); 2 and 3 are lost
    assert len(read_records(run / "episodes.csv")) == 2
    assert not (run / "done.json").exists()
    resumed = train(cfg(eval_episodes=0), run, progress=False)
    assert resumed.resumed_from == 2
    assert strip_time(resumed.records) == strip_time(full.records)
    assert strip_time(read_records(run / "episodes.csv")) == strip_time(full.records)
    s_full = torch.load(tmp_path / "full" / "checkpoint.pt", weights_only=False)
    s_res = torch.load(run / "checkpoint.pt", weights_only=False)
    assert torch.equal(s_full["learner"]["params"], s_res["learner"]["params"])
    # a finished run is not trained again
    again = train(cfg(eval_episodes=0), run, progress=False)
    assert again.resumed_from == 6 and strip_time(again.records) == strip_time(full.records)


def test_resume_refuses_a_different_config(tmp_path: Path) -> None:
    train(cfg(episodes=2, eval_episodes=0), tmp_path, progress=False)
    with pytest.raises(ValueError, match="different config"):
        train(cfg(episodes=3, eval_episodes=0), tmp_path, progress=False)


def test_step_budget(tmp_path: Path) -> None:
    result = train(cfg(episodes=None, steps=50, eval_episodes=0), tmp_path, progress=False)
    assert result.records[-1].total_steps == 50


class NaNRewardAfter(gym.Env):  # type: ignore[type-arg]
    """A 1-D Box task whose reward turns NaN at global step 40."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def __init__(self) -> None:
        self.t = 0
        self.global_t = 0

    def reset(self, *, seed: int | None = None, options: Any = None) -> Any:
        super().reset(seed=seed)
        self.t = 0
        return np.zeros(2, np.float32), {}

    def step(self, action: Any) -> Any:
        self.t += 1
        self.global_t += 1
        reward = float("nan") if self.global_t >= 40 else 1.0
        return np.full(2, 0.1, np.float32), reward, False, self.t >= 10, {}


gym.register("pporpe-test/NaNReward-v0", entry_point=NaNRewardAfter)


def test_non_finite_reward_stops_with_episode_and_step_and_keeps_checkpoint(
    tmp_path: Path,
) -> None:
    c = cfg(env="pporpe-test/NaNReward-v0", episodes=10, checkpoint_every=1, eval_episodes=0)
    with pytest.raises(NonFiniteError, match=r"non-finite reward at episode 3, step 10"):
        train(c, tmp_path, progress=False)
    state = torch.load(tmp_path / "checkpoint.pt", weights_only=False)
    assert len(state["records"]) == 3  # the last good checkpoint survives
    assert torch.isfinite(state["learner"]["params"]).all()
    assert len(read_records(tmp_path / "episodes.csv")) == 3


# ------------------------------------------------------------------------------------
# The CLI
# ------------------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["rb", "spo"])
def test_cli_train_then_evaluate(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], method: str
) -> None:
    run = tmp_path / "run"
    code = main(
        [
            "train",
            "--method",
            method,
            "--env",
            "pendulum",
            "--seed",
            "1",
            "--episodes",
            "3",
            "--out",
            str(run),
            "--eval-episodes",
            "0",
            "--quiet",
        ]
    )
    assert code == 0
    assert "trained 3 episodes" in capsys.readouterr().out
    assert json.loads((run / "config.json").read_text())["learner"]["method"] == method
    assert main(["evaluate", str(run), "--episodes", "3"]) == 0
    out = capsys.readouterr().out
    ev = json.loads((run / "evaluation.json").read_text())
    assert ev["episodes"] == 3 and len(ev["returns"]) == 3
    assert f"median {ev['median']:.2f}" in out


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--eps", "1.5"], "eps"),
        (["--method", "rpe", "--beta", "0.99"], "beta"),
        (["--method", "spo", "--eps", "0"], "eps must be a number in the open interval (0, 1)"),
        (["--env", "NoSuchEnv-v9"], "pendulum"),  # lists the aliases
    ],
)
def test_cli_train_rejects_bad_input_before_work(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], message: str
) -> None:
    out = tmp_path / "never"
    assert main(["train", "--episodes", "2", "--out", str(out), *args]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_cli_rejects_negative_episodes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["train", "--episodes", "-5", "--out", str(tmp_path / "x")]) == 2
    assert "episodes" in capsys.readouterr().err and not (tmp_path / "x").exists()


def test_cli_evaluate_rejects_non_run_folder(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["evaluate", str(tmp_path)]) == 2
    assert "not a run folder" in capsys.readouterr().err


@pytest.mark.parametrize("method", ["rpe", "spo"])
def test_cli_train_batch_then_evaluate(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], method: str
) -> None:
    run = tmp_path / "batch"
    code = main(
        [
            "train",
            "--learner",
            "batch",
            "--method",
            method,
            "--env",
            "pendulum",
            "--steps",
            "256",
            "--n-envs",
            "1",
            "--n-steps",
            "128",
            "--batch-size",
            "64",
            "--n-epochs",
            "2",
            "--out",
            str(run),
            "--eval-episodes",
            "0",
            "--quiet",
        ]
    )
    assert code == 0
    assert "trained 256 steps (2 updates" in capsys.readouterr().out
    saved = json.loads((run / "config.json").read_text())
    assert saved["kind"] == "batch" and saved["method"] == method and saved["n_steps"] == 128
    assert main(["evaluate", str(run), "--episodes", "2"]) == 0
    ev = json.loads((run / "evaluation.json").read_text())
    assert ev["episodes"] == 2 and len(ev["returns"]) == 2
    assert f"median {ev['median']:.2f}" in capsys.readouterr().out


def test_cli_batch_rejects_episodes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "never"
    assert main(["train", "--learner", "batch", "--episodes", "3", "--out", str(out)]) == 2
    assert "--steps" in capsys.readouterr().err and not out.exists()


def test_cli_evaluate_rejects_non_positive_episodes(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["evaluate", "some/run", "--episodes", "0"])
    assert info.value.code == 2
    assert "--episodes" in capsys.readouterr().err


def test_load_evaluation_reads_what_train_saved(tmp_path: Path) -> None:
    from pporpe.evaluation import load_evaluation

    result = train(cfg(episodes=2), tmp_path, progress=False)
    assert load_evaluation(tmp_path) == result.evaluation
    assert load_evaluation(tmp_path / "missing") is None


class NaNRewardForSeed(gym.Env):  # type: ignore[type-arg]
    """A 1-D Box task whose reward turns NaN at step 25 of runs seeded with 1 only."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def __init__(self) -> None:
        self.t = self.global_t = 0
        self.poisoned = False

    def reset(self, *, seed: int | None = None, options: Any = None) -> Any:
        super().reset(seed=seed)
        if seed is not None:
            self.poisoned = seed == 1
        self.t = 0
        return np.zeros(2, np.float32), {}

    def step(self, action: Any) -> Any:
        self.t += 1
        self.global_t += 1
        reward = float("nan") if self.poisoned and self.global_t >= 25 else float(action[0])
        return np.full(2, 0.1 * self.t, np.float32), reward, False, self.t >= 10, {}


gym.register("pporpe-test/NaNForSeed1-v0", entry_point=NaNRewardForSeed)


def test_a_member_that_goes_non_finite_stops_alone(tmp_path: Path) -> None:
    """In a population of three runs, the run whose rewards turn NaN stops with the reason
    in its error.txt and keeps its last good checkpoint; the others finish, with the same
    records as in a population (of the same packing) where that run stays healthy."""
    from pporpe.runs.loop import run_queue

    def runs(root: Path, seeds: list[int]) -> list[tuple[TrainConfig, Path]]:
        return [
            (cfg(env="pporpe-test/NaNForSeed1-v0", seed=s, episodes=6, checkpoint_every=1,
                 eval_episodes=0), root / f"s{s}")
            for s in seeds
        ]  # fmt: skip

    results = run_queue(runs(tmp_path / "a", [0, 1, 2]), capacity=3, home=tmp_path / "a")
    assert [r.error is None for r in results] == [True, False, True]
    err = (tmp_path / "a" / "s1" / "error.txt").read_text()
    assert "non-finite reward at episode 2, step 5" in err
    assert not (tmp_path / "a" / "s1" / "done.json").exists()
    state = torch.load(tmp_path / "a" / "s1" / "checkpoint.pt", weights_only=False)
    assert len(state["records"]) == 2 and torch.isfinite(state["learner"]["params"]).all()
    assert all(len(r.records) == 6 for r in (results[0], results[2]))
    control = run_queue(runs(tmp_path / "b", [0, 3, 2]), capacity=3, home=tmp_path / "b")
    assert all(r.error is None for r in control)
    assert strip_time(control[0].records) == strip_time(results[0].records)
    assert strip_time(control[2].records) == strip_time(results[2].records)


def test_cli_out_that_is_a_file_is_a_one_line_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    target = tmp_path / "FILE"
    target.write_text("keep me")
    code = main(["train", "--env", "pendulum", "--episodes", "2", "--out", str(target)])
    err = capsys.readouterr().err
    assert code == 2 and "is an existing file" in err and "Traceback" not in err
    assert err.count("\n") == 1 and target.read_text() == "keep me"
