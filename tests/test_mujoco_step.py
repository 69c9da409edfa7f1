"""pporpe's step of Gymnasium's MuJoCo -v4 tasks against Gymnasium's own: the same
observations, rewards, flags and info bit for bit, and the same training records."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

pytest.importorskip("mujoco")

from tiny import same_run_either_way

from pporpe.batch import BatchConfig
from pporpe.envs import MUJOCO_LEAN_ENTRY_POINTS, make_env
from pporpe.envs.mujoco import HopperLeanEnv, _clip10, _inside, _sum_of_squares
from pporpe.envs.side_by_side import side_by_side

TASKS = list(MUJOCO_LEAN_ENTRY_POINTS)
IDENTITY_STEPS = 4000


def _lean(task: str, **kwargs: Any) -> gymnasium.Env:
    return make_env(task, mujoco_step="lean", **kwargs)


def _reference(task: str, **kwargs: Any) -> gymnasium.Env:
    return make_env(task, mujoco_step="reference", **kwargs)


@pytest.mark.parametrize("task", TASKS)
def test_the_lean_step_is_gymnasiums_bit_for_bit(task: str) -> None:
    """4,000 steps from the same seeds and actions (outside the bounds too, and +-1.2 held
    on every joint, which ends the Hopper's and the Walker's episodes by ``terminated``), with
    resets at the ends of episodes and at random times: every observation, reward, flag,
    info and reset observation the same, bit for bit and type for type."""
    seen = side_by_side(task, IDENTITY_STEPS, seed=2, make=_lean, reference=_reference)
    assert seen.first_difference is None
    assert seen.resets > 0
    if task != "HalfCheetah-v4":  # the cheetah never falls
        assert seen.terminations > 0


def test_make_env_builds_the_lean_step_by_default(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("PPORPE_MUJOCO_STEP", raising=False)
    env = make_env("Hopper-v4")
    assert type(env.unwrapped) is HopperLeanEnv
    assert env.spec is not None and env.spec.id == "Hopper-v4"
    assert env.spec.max_episode_steps == 1000
    assert type(make_env("Hopper-v4", mujoco_step="reference").unwrapped).__name__ == "HopperEnv"
    monkeypatch.setenv("PPORPE_MUJOCO_STEP", "reference")
    assert type(make_env("Hopper-v4").unwrapped).__name__ == "HopperEnv"
    # a task without a lean step is Gymnasium's, whatever the choice
    monkeypatch.setenv("PPORPE_MUJOCO_STEP", "lean")
    assert type(make_env("Hopper-v5").unwrapped).__name__ == "HopperEnv"


def test_a_bad_mujoco_step_is_refused_naming_where_it_came_from(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    with pytest.raises(ValueError, match=r"mujoco_step must be one of lean, reference"):
        make_env("Hopper-v4", mujoco_step="fast")
    monkeypatch.setenv("PPORPE_MUJOCO_STEP", "refrence")
    with pytest.raises(ValueError, match=r"PPORPE_MUJOCO_STEP must be one of .*'refrence'"):
        make_env("Hopper-v4")


def test_the_comparison_catches_a_control_cost_summed_in_float64() -> None:
    """The control cost of a float32 action is a float32 sum in Gymnasium; summed in float64
    the reward changes in its last bits, and the side-by-side comparison says where."""

    class Float64Cost(HopperLeanEnv):
        def step(self, a: Any) -> Any:
            return super().step(np.asarray(a, dtype=np.float64))

    seen = side_by_side(
        "Hopper-v4", 200, seed=2,
        make=lambda _: gymnasium.wrappers.TimeLimit(Float64Cost(), 1000), reference=_reference,
    )  # fmt: skip
    assert seen.first_difference is not None and "reward" in seen.first_difference


def test_an_ant_with_contact_forces_takes_gymnasiums_step() -> None:
    """``use_contact_forces=True`` puts the contact forces into the observation and their
    cost into the reward: the lean class then steps as Gymnasium does."""
    env = _lean("Ant-v4", use_contact_forces=True)
    assert env.observation_space.shape == (27 + 84,)  # 14 bodies x 6 contact forces
    env.close()
    seen = side_by_side(
        "Ant-v4", 300, seed=3,
        make=lambda t: _lean(t, use_contact_forces=True),
        reference=lambda t: _reference(t, use_contact_forces=True),
    )  # fmt: skip
    assert seen.first_difference is None


def test_an_action_of_the_wrong_shape_gets_gymnasiums_error() -> None:
    env = _lean("Hopper-v4")
    env.reset(seed=0)
    with pytest.raises(ValueError, match="Action dimension mismatch"):
        env.unwrapped.step(np.zeros(4))
    env.close()


def test_the_helpers_hand_worked() -> None:
    assert _inside((-1.0, 1.0), np.array([0.5, -0.99])) is True
    assert _inside((-1.0, 1.0), np.array([0.5, 1.0])) is False  # strict, as the reference
    assert _inside((-1.0, 1.0), np.array([0.5, np.nan])) is False
    assert _clip10(np.array([-12.0, 3.5, 10.0, np.inf])).tolist() == [-10.0, 3.5, 10.0, 10.0]
    cost = _sum_of_squares(np.array([1.0, 2.0, 0.5], dtype=np.float32))
    assert cost == 5.25 and cost.dtype == np.float32


_floats = st.floats(allow_nan=True, allow_infinity=True, width=64)


@settings(max_examples=300, deadline=None)
@given(values=hnp.arrays(np.float64, st.integers(1, 20), elements=_floats))
def test_the_health_test_and_the_clip_are_numpys(values: np.ndarray) -> None:
    """Against the reference's own expressions on any float64 values, NaN and inf included."""
    for bounds in [(-100.0, 100.0), (-0.2, 0.2)]:
        low, high = bounds
        expected = bool(np.all(np.logical_and(low < values, values < high)))
        assert _inside(bounds, values) == expected
    assert _clip10(values).tobytes() == np.clip(values, -10, 10).tobytes()


@settings(max_examples=300, deadline=None)
@given(
    action=hnp.arrays(
        st.sampled_from([np.float32, np.float64]),
        st.integers(1, 17),
        elements=st.floats(-1e3, 1e3, width=32),
    )
)
def test_the_control_cost_sum_is_numpys(action: np.ndarray) -> None:
    ours, theirs = _sum_of_squares(action), np.sum(np.square(action))
    assert type(ours) is type(theirs) and ours.tobytes() == theirs.tobytes()


def test_a_hopper_batch_run_is_the_same_with_either_step(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A short batch run on Hopper-v4 writes the same records, per-update log and test
    returns, to the last digit, whichever step computes the environment."""
    cfg = BatchConfig(env="Hopper-v4", seed=5, n_envs=2, n_steps=256, batch_size=128,
                      n_epochs=2, total_steps=1024, checkpoint_every=1,
                      eval_episodes=2)  # fmt: skip
    same_run_either_way(cfg, "PPORPE_MUJOCO_STEP", ("lean", "reference"), tmp_path, monkeypatch)
