"""pporpe's batched step of the four Bullet tasks against pybullet_envs_gymnasium's own step:
the same observations, rewards and flags bit for bit, and the same training records."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pybullet_envs_gymnasium.gym_locomotion_envs import AntBulletEnv, HalfCheetahBulletEnv
from tiny import same_run_either_way

from pporpe.batch import BatchConfig
from pporpe.envs import ALIASES, make_env
from pporpe.envs.bullet import (
    _AT_LIMIT,
    AntBatchedEnv,
    HalfCheetahBatchedEnv,
    InvertedPendulumBatchedEnv,
    mean_xy,
    numpy_mean,
)
from pporpe.envs.side_by_side import side_by_side
from pporpe.online.config import TrainConfig

TASKS = list(ALIASES)
IDENTITY_STEPS = 5000


@pytest.mark.parametrize("task", TASKS)
def test_batched_step_is_the_reference_bit_for_bit(task: str) -> None:
    """5,000 steps from the same seeds and actions (outside the bounds too), with resets
    at the ends of episodes and at random times: every observation, reward, flag and reset
    observation the same bit for bit."""
    seen = side_by_side(task, IDENTITY_STEPS, seed=1)
    assert seen.first_difference is None
    assert seen.identical
    assert seen.resets >= 3
    if task == "ant":
        assert seen.terminations >= 3  # natural ends of the task, not only the time limit
    if task == "pendulum":
        assert seen.terminations >= 100
    if task in ("swingup", "halfcheetah"):
        assert seen.truncations >= 1


class ReorderedReward(HalfCheetahBatchedEnv):  # type: ignore[misc]
    """A mutant: the reward's five terms summed in another order (the electricity cost
    after the joints-at-limit cost)."""

    def step(self, a: Any) -> Any:
        obs, _, terminated, truncated, info = super().step(a)
        alive, progress, electricity, at_limit, feet = self.rewards
        return obs, sum([alive, progress, at_limit, electricity, feet]), terminated, truncated, info


def test_the_comparison_catches_a_reward_summed_in_another_order() -> None:
    """Summing the same five terms in another order changes the reward in its last bits
    within a few hundred steps, and the side-by-side comparison says where."""
    seen = side_by_side(
        "halfcheetah", IDENTITY_STEPS, seed=1,
        make=lambda _: gymnasium.wrappers.TimeLimit(ReorderedReward(), 1000),
    )  # fmt: skip
    assert not seen.identical
    assert seen.first_difference is not None and "reward" in seen.first_difference


def test_the_comparison_catches_an_observation_off_by_one_ulp() -> None:
    class OneUlp(InvertedPendulumBatchedEnv):  # type: ignore[misc]
        def step(self, a: Any) -> Any:
            obs, *rest = super().step(a)
            obs[0] = np.nextafter(obs[0], np.float32(np.inf))
            return (obs, *rest)

    seen = side_by_side("pendulum", 50, make=lambda _: gymnasium.wrappers.TimeLimit(OneUlp(), 1000))
    assert seen.first_difference is not None
    assert seen.first_difference.startswith("step 0: the observation differs")


@settings(max_examples=300, deadline=None)
@given(
    st.lists(st.floats(-1e6, 1e6, allow_nan=False, width=32), min_size=1, max_size=70),
    st.sampled_from([np.float32, np.float64]),
    st.integers(1, 3),
)
def test_numpy_mean_is_numpys_mean(values: list[float], dtype: Any, stride: int) -> None:
    """The step's mean is ``ndarray.mean`` bit for bit, strided views included (the part
    positions' mean is over every third element), float32 (the electricity cost) and
    float64."""
    x = np.array(values, dtype=dtype)[::stride]
    got, want = numpy_mean(x), x.mean()
    assert type(got) is type(want)
    assert got.tobytes() == want.tobytes()


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(*[st.floats(-1e6, 1e6, allow_nan=False)] * 3), min_size=1, max_size=70))
def test_mean_xy_is_the_reference_mean(positions: list[tuple[float, float, float]]) -> None:
    """The parts' mean x and mean y are the reference's: ``ndarray.mean`` of every third
    element of the flattened ``(parts, 3)`` array, from 0 and from 1, bit for bit."""
    flat = np.array(positions).flatten()
    for got, want in zip(mean_xy(positions), (flat[0::3].mean(), flat[1::3].mean()), strict=True):
        assert type(got) is type(want)
        assert got.tobytes() == want.tobytes()


def test_the_joints_at_limit_threshold_is_numpys() -> None:
    """``abs(x) > _AT_LIMIT`` on a float32 number as a Python float is numpy's
    ``np.abs(x) > 0.99`` on the float32 array, at the float32 neighbours of 0.99 too."""
    t = np.float32(0.99)
    edges = [np.nextafter(t, np.float32(2)), t, np.nextafter(t, np.float32(0)), 0.99]
    rng = np.random.default_rng(0)
    x = np.array([*edges, *(-e for e in edges), np.nan, np.inf, -np.inf], dtype=np.float32)
    x = np.concatenate([x, rng.uniform(-1.5, 1.5, 10_000).astype(np.float32)])
    want = np.abs(x) > 0.99
    got = np.array([abs(v) > _AT_LIMIT for v in x.tolist()])
    assert (got == want).all()


def test_a_static_base_is_read_once_and_never_moves() -> None:
    """The floor (a base without mass) is read at reset, not each step: PyBullet never
    moves it, and the robot's own base (the Ant's torso, with mass) is read each step."""
    import pybullet

    for task in ("halfcheetah", "ant"):
        env = make_env(task, seed=0)
        env.reset(seed=0)
        layout = env.unwrapped._layout  # type: ignore[attr-defined]
        static = [(body, position) for _, body, position in layout.bases if position is not None]
        assert [body for body, _ in static] == layout.grounds
        assert all(position is None for _, body, position in layout.bases if body == layout.body)
        for _ in range(300):
            env.step(env.action_space.sample())
        for body, position in static:
            now = pybullet.getBasePositionAndOrientation(body, physicsClientId=layout.client)
            assert now[0] == position
        env.close()


def test_numpy_mean_hand_worked() -> None:
    # float32: the sum 0.1f + 0.2f + 0.4f is rounded in float32, then divided in float64 by
    # the intp count and rounded back to float32, as numpy does
    x = np.array([0.1, 0.2, 0.4], dtype=np.float32)
    total = np.float32(np.float32(np.float32(0.1) + np.float32(0.2)) + np.float32(0.4))
    assert numpy_mean(x) == np.float32(np.float64(total) / 3)
    assert numpy_mean(np.array([1.0, 2.0, 4.5])) == 2.5


def test_make_env_builds_the_batched_step_by_default(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("PPORPE_BULLET_STEP", raising=False)
    for task, batched, reference in [
        ("halfcheetah", HalfCheetahBatchedEnv, HalfCheetahBulletEnv),
        ("ant", AntBatchedEnv, AntBulletEnv),
    ]:
        env = make_env(task)
        assert type(env.unwrapped) is batched
        assert env.spec is not None and env.spec.id == ALIASES[task]
        assert env.spec.max_episode_steps == 1000
        env.close()
        env = make_env(task, bullet_step="reference")
        assert type(env.unwrapped) is reference
        env.close()
        monkeypatch.setenv("PPORPE_BULLET_STEP", "reference")
        env = make_env(task)
        assert type(env.unwrapped) is reference
        env.close()
        monkeypatch.delenv("PPORPE_BULLET_STEP")
    assert type(make_env("Pendulum-v1", bullet_step="reference").unwrapped).__name__ == (
        "PendulumEnv"
    )


def test_a_bad_bullet_step_is_refused_naming_where_it_came_from(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    with pytest.raises(ValueError, match=r"bullet_step must be one of batched, reference"):
        make_env("halfcheetah", bullet_step="fast")
    monkeypatch.setenv("PPORPE_BULLET_STEP", "refrence")
    with pytest.raises(ValueError, match=r"PPORPE_BULLET_STEP must be one of .*'refrence'"):
        make_env("ant")


@pytest.mark.parametrize("learner", ["online", "batch"])
def test_a_halfcheetah_run_is_the_same_with_either_step(
    learner: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A short run on HalfCheetah writes the same records and test returns, to the last
    digit, whichever step computes the environment."""
    if learner == "online":
        cfg: Any = TrainConfig(env="halfcheetah", seed=5, episodes=2, checkpoint_every=1,
                               eval_episodes=1)  # fmt: skip
    else:
        cfg = BatchConfig(env="halfcheetah", seed=5, n_envs=2, n_steps=512, batch_size=256,
                          n_epochs=2, total_steps=2048, checkpoint_every=1,
                          eval_episodes=1)  # fmt: skip
    same_run_either_way(cfg, "PPORPE_BULLET_STEP", ("batched", "reference"), tmp_path, monkeypatch)
