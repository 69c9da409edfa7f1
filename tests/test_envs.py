"""Tests of pporpe.envs: aliases, validation and the four Bullet tasks."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest

from pporpe.envs import ALIASES, QuietBulletStart, env_spec_summary, make_env, resolve_env_id

BULLET_TASKS = [
    ("pendulum", 5, 1),
    ("swingup", 5, 1),
    ("halfcheetah", 26, 6),
    ("ant", 28, 8),
]


def test_aliases_resolve_to_registered_ids() -> None:
    assert ALIASES == {
        "pendulum": "InvertedPendulumBulletEnv-v0",
        "swingup": "InvertedPendulumSwingupBulletEnv-v0",
        "halfcheetah": "HalfCheetahBulletEnv-v0",
        "ant": "AntBulletEnv-v0",
    }
    for alias, env_id in ALIASES.items():
        assert resolve_env_id(alias) == env_id
        assert resolve_env_id(alias.upper()) == env_id
        assert resolve_env_id(env_id) == env_id
        assert env_id in gymnasium.envs.registry
    assert resolve_env_id("Pendulum-v1") == "Pendulum-v1"


@pytest.mark.parametrize("name", ["no-such-env", "Pendulum-v99", "", "pendulumm"])
def test_unknown_name_lists_aliases(name: str) -> None:
    with pytest.raises(ValueError) as info:
        resolve_env_id(name)
    message = str(info.value)
    for alias, env_id in ALIASES.items():
        assert alias in message
        assert env_id in message
    assert "Box" in message
    with pytest.raises(ValueError):
        make_env(name)


def test_discrete_action_env_is_rejected() -> None:
    with pytest.raises(ValueError) as info:
        make_env("CartPole-v1")
    message = str(info.value)
    assert "CartPole-v1" in message
    assert "Discrete" in message
    assert "halfcheetah" in message


def test_non_bullet_box_env_works() -> None:
    env = make_env("Pendulum-v1", seed=0)
    try:
        obs, _ = env.reset(seed=0)
        assert obs.shape == (3,)
        out = env.step(env.action_space.sample())
        assert len(out) == 5
        summary = env_spec_summary(env)
        assert summary == {
            "id": "Pendulum-v1",
            "obs_dim": 3,
            "act_dim": 1,
            "action_low": [-2.0],
            "action_high": [2.0],
            "max_episode_steps": 200,
        }
    finally:
        env.close()


def test_kwargs_reach_gymnasium_make_and_time_limit_truncates() -> None:
    env = make_env("Pendulum-v1", max_episode_steps=3)
    try:
        env.reset(seed=1)
        flags = [env.step(env.action_space.sample())[3] for _ in range(3)]
        assert flags == [False, False, True]
        assert env_spec_summary(env)["max_episode_steps"] == 3
    finally:
        env.close()


def test_seed_seeds_the_spaces() -> None:
    env_a = make_env("Pendulum-v1", seed=7)
    env_b = make_env("Pendulum-v1", seed=7)
    try:
        np.testing.assert_array_equal(env_a.action_space.sample(), env_b.action_space.sample())
        np.testing.assert_array_equal(
            env_a.observation_space.sample(), env_b.observation_space.sample()
        )
    finally:
        env_a.close()
        env_b.close()


@pytest.mark.parametrize(("alias", "obs_dim", "act_dim"), BULLET_TASKS)
def test_bullet_task_builds_resets_and_steps(alias: str, obs_dim: int, act_dim: int) -> None:
    env = make_env(alias, seed=3)
    twin = make_env(ALIASES[alias], seed=3)
    try:
        summary = env_spec_summary(env)
        assert summary["id"] == ALIASES[alias]
        assert summary["obs_dim"] == obs_dim
        assert summary["act_dim"] == act_dim
        assert summary["max_episode_steps"] == 1000
        assert summary["action_low"] == [-1.0] * act_dim
        assert summary["action_high"] == [1.0] * act_dim
        assert isinstance(env, QuietBulletStart)
        assert isinstance(env.env, gymnasium.wrappers.TimeLimit)

        obs, info = env.reset(seed=3)
        assert obs.shape == (obs_dim,)
        assert isinstance(info, dict)
        twin_obs, _ = twin.reset(seed=3)
        np.testing.assert_array_equal(obs, twin_obs)

        action = env.action_space.sample()
        assert action.shape == (act_dim,)
        np.testing.assert_array_equal(action, twin.action_space.sample())
        result = env.step(action)
        assert len(result) == 5
        next_obs, reward, terminated, truncated, info = result
        assert next_obs.shape == (obs_dim,)
        assert np.all(np.isfinite(next_obs))
        assert np.isfinite(float(reward))
        assert isinstance(terminated, bool)
        assert isinstance(truncated, bool)
        assert not truncated
    finally:
        env.close()
        twin.close()


def test_a_bullet_client_starts_without_printing(capfd: pytest.CaptureFixture[str]) -> None:
    """PyBullet's C code prints two ``argv[0]=`` lines to descriptor 1 when an environment's
    client connects (its first reset), into the progress bar of ``pporpe train``; they are
    silenced for that reset, and what Python prints afterwards still comes through."""
    env = make_env("pendulum", seed=0)
    try:
        capfd.readouterr()
        env.reset(seed=0)
        env.step(env.action_space.sample())
        env.reset()
        print("after the start")
        out, err = capfd.readouterr()
        assert "argv[0]" not in out + err
        assert out == "after the start\n"
    finally:
        env.close()
    assert not isinstance(make_env("Pendulum-v1"), QuietBulletStart)  # no Bullet client


@pytest.mark.parametrize(("env_id", "obs_dim", "act_dim"), [
    ("Hopper-v4", 11, 3), ("Hopper-v5", 11, 3), ("HalfCheetah-v4", 17, 6),
    ("Walker2d-v4", 17, 6), ("Ant-v4", 27, 8),
])  # fmt: skip
def test_mujoco_tasks_build_and_step(env_id: str, obs_dim: int, act_dim: int) -> None:
    """Gymnasium's MuJoCo tasks (the ``mujoco`` extra, installed by ``make test``)."""
    pytest.importorskip("mujoco")
    env = make_env(env_id, seed=0)
    try:
        summary = env_spec_summary(env)
        assert (summary["obs_dim"], summary["act_dim"]) == (obs_dim, act_dim)
        obs, _ = env.reset(seed=0)
        assert obs.shape == (obs_dim,)
        out = env.step(env.action_space.sample())
        assert np.isfinite(out[1])
    finally:
        env.close()


def test_gymnasium_warnings_come_once_without_colour_codes(
    recwarn: pytest.WarningsRecorder, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Gymnasium warns that a -v4 MuJoCo task is out of date, in terminal colour codes that
    show as raw text in a log or a progress bar: pporpe gives the warning once per process,
    in plain text."""
    pytest.importorskip("mujoco")
    from pporpe import envs
    from pporpe.envs import GymnasiumWarning

    monkeypatch.setattr(envs, "_GYMNASIUM_WARNINGS_SHOWN", set())
    for _ in range(3):
        make_env("Walker2d-v4").close()
    ours = [w for w in recwarn if w.category is GymnasiumWarning and "Walker2d" in str(w.message)]
    assert len(ours) == 1
    assert "\x1b[" not in str(ours[0].message) and "out of date" in str(ours[0].message)
    assert not [w for w in recwarn if "\x1b[" in str(w.message)]


def test_mujoco_model_warnings_come_once_and_a_users_handler_stays(
    recwarn: pytest.WarningsRecorder,
    monkeypatch: pytest.MonkeyPatch,
    capfd: pytest.CaptureFixture[str],
) -> None:
    """MuJoCo prints a line per HalfCheetah-v4 built (its model's ``settotalmass`` is
    deprecated): pporpe gives it once per process as a MuJoCoWarning and prints nothing; a
    warning handler the user installed gets MuJoCo's warnings instead, and stays."""
    mujoco = pytest.importorskip("mujoco")
    from pporpe import envs
    from pporpe.envs import MuJoCoWarning

    monkeypatch.setattr(envs, "_MUJOCO_WARNINGS_SHOWN", set())
    for _ in range(3):
        make_env("HalfCheetah-v4").close()
    ours = [w for w in recwarn if w.category is MuJoCoWarning]
    assert len(ours) == 1 and "settotalmass" in str(ours[0].message)
    assert "settotalmass" not in "".join(capfd.readouterr())
    assert mujoco.get_mju_user_warning() is None
    seen: list[str] = []
    mujoco.set_mju_user_warning(seen.append)
    try:
        make_env("HalfCheetah-v4").close()
        assert mujoco.get_mju_user_warning() is not None
    finally:
        mujoco.set_mju_user_warning(None)
    assert any("settotalmass" in m for m in seen)
    assert len([w for w in recwarn if w.category is MuJoCoWarning]) == 1
