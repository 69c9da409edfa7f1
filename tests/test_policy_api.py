"""pporpe.load_policy and `pporpe evaluate --video` (issue 12)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path
from typing import Any

import imageio
import numpy as np
import pytest
import torch

from pporpe import OnlineConfig, TrainConfig, load_policy, train, zoo_config
from pporpe.cli import main
from pporpe.evaluation import EVAL_SEED_OFFSET, evaluate_policy
from pporpe.policy import Policy


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """An online and a batch run trained here, each with its test returns."""
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("runs")
    online = TrainConfig(
        env="pendulum",
        seed=3,
        episodes=None,
        steps=300,
        eval_episodes=3,
        learner=OnlineConfig(method="rpe", compile=False),
    )
    batch = zoo_config(
        "pendulum",
        method="rpe",
        seed=4,
        total_steps=512,
        n_envs=2,
        n_steps=128,
        batch_size=64,
        eval_episodes=3,
    )
    out = {}
    for name, cfg in (("online", online), ("batch", batch)):
        result = train(cfg, root / name, progress=False)
        out[name] = {"dir": root / name, "config": cfg, "returns": result.evaluation.returns}
    return out


@pytest.mark.parametrize("name", ["online", "batch"])
def test_load_policy_acts_as_the_trained_learner(runs: dict[str, Any], name: str) -> None:
    run = runs[name]
    policy = load_policy(run["dir"])
    assert isinstance(policy, Policy) and policy.kind == name
    assert policy.config == run["config"] and policy.env == "pendulum"
    # The test episodes of training (acted by the learner itself) replay exactly.
    seed = run["config"].seed + EVAL_SEED_OFFSET
    assert evaluate_policy(policy, "pendulum", 3, seed).returns == run["returns"]
    obs = np.random.default_rng(0).normal(size=(6, 5)).astype(np.float32)
    batch = policy.act(obs)
    assert batch.shape == (6, 1) and batch.dtype == np.float32
    np.testing.assert_allclose(policy.act(obs[2]), batch[2], rtol=1e-5, atol=1e-6)
    assert np.all(np.abs(policy.act(obs, deterministic=False)) <= 1.0)


def test_stochastic_actions_come_from_the_policys_own_stream(runs: dict[str, Any]) -> None:
    policy = load_policy(runs["online"]["dir"])
    obs = np.zeros((200, 5), np.float32)
    torch.manual_seed(123)
    before = torch.get_rng_state()
    policy.seed(7)
    a = policy.act(obs, deterministic=False)
    assert torch.equal(torch.get_rng_state(), before)  # the global stream did not move
    policy.seed(7)
    np.testing.assert_array_equal(policy.act(obs, deterministic=False), a)
    b = policy.act(obs, deterministic=False)
    assert not np.array_equal(a, b)  # the stream goes on
    # The samples follow pi(.|s): their pre-bound location is the deterministic action's.
    u = policy.distribution(obs).sample((50,))
    loc = policy.distribution(obs).mean
    assert torch.allclose(u.median(0).values.mean(), loc.mean(), atol=0.1)
    assert a.std() > 0.0


def test_bad_observations_are_refused(runs: dict[str, Any]) -> None:
    policy = load_policy(runs["batch"]["dir"])
    with pytest.raises(ValueError, match=r"obs must have shape \[5\] or \[N, 5\]; got \(4,\)"):
        policy.act(np.zeros(4))
    with pytest.raises(ValueError, match=r"not a run folder|config\.json"):
        load_policy(runs["batch"]["dir"].parent)


def test_evaluate_records_a_playable_video(
    runs: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = runs["online"]["dir"]
    video = tmp_path / "video"
    assert main(["evaluate", str(run), "--episodes", "2", "--video", str(video)]) == 0
    assert "recorded 1 video in" in capsys.readouterr().out
    returns = json.loads((run / "evaluation.json").read_text())["returns"]
    # Rendering does not change the episodes: the same returns as the run's own test.
    assert returns == runs["online"]["returns"][:2]
    files = sorted(video.glob("*.mp4"))
    assert [f.name for f in files] == ["rl-video-episode-0.mp4"]
    reader = imageio.get_reader(files[0])
    frames = [np.asarray(f) for f in reader]
    # InvertedPendulum pays 1 per step: one frame per step plus the reset frame.
    assert len(frames) == int(returns[0]) + 1
    assert frames[0].ndim == 3 and frames[0].shape[2] == 3 and frames[0].std() > 0


def test_video_needs_moviepy_and_says_so(
    runs: dict[str, Any],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda n, *a: None if n == "moviepy" else real(n, *a)
    )
    run = runs["online"]["dir"]
    before = (run / "evaluation.json").read_bytes()
    assert main(["evaluate", str(run), "--video", str(tmp_path / "v")]) == 2
    err = capsys.readouterr().err
    assert 'recording video needs moviepy: pip install "pporpe[video]"' in err
    assert (run / "evaluation.json").read_bytes() == before  # refused before any work
    assert not (tmp_path / "v").exists()


def test_video_episodes_beyond_the_test_episodes_are_refused(
    runs: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = ["evaluate", str(runs["online"]["dir"]), "--episodes", "2", "--video", str(tmp_path)]
    assert main([*args, "--video-episodes", "3"]) == 2
    assert "--video-episodes must be in [1, --episodes=2]; got 3" in capsys.readouterr().err
