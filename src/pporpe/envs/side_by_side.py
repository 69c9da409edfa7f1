"""Two steps of one task side by side, compared bit for bit: pporpe's and the reference's.

:func:`side_by_side` steps two environments of a task with the same actions and resets and
reports the first observation, reward or flag that differs. By default they are
:func:`pporpe.envs.make_env`'s two steps of a Bullet task (``bullet_step="batched"`` and
``"reference"``); ``make`` and ``reference`` build others (the MuJoCo steps of
:mod:`pporpe.envs.mujoco`). ``tests/test_bullet_step.py``, ``tests/test_mujoco_step.py``,
``benchmarks/bullet_identity.py`` and ``benchmarks/mujoco_step.py`` hold pporpe's steps to it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from . import make_env

__all__ = ["SideBySide", "side_by_side"]


@dataclass(frozen=True)
class SideBySide:
    """What :func:`side_by_side` saw: counts, and the first difference if any."""

    task: str
    """The task's alias or id."""
    steps: int
    """Steps taken in each environment."""
    seed: int
    """The seed of the first reset and of the action sequence."""
    resets: int
    """Resets after the first (after an end of episode, or at random times)."""
    terminations: int
    """Episodes that ended by ``terminated`` (a natural end of the task)."""
    truncations: int
    """Episodes that ended by ``truncated`` (the time limit)."""
    first_difference: str | None
    """The first step whose outputs differ, and what differs; None when all were equal."""

    @property
    def identical(self) -> bool:
        """Whether every observation, reward and flag was the same bit for bit."""
        return self.first_difference is None


def _same_bits(a: Any, b: Any) -> bool:
    """Whether two observations or two rewards are the same value of the same type, bit
    for bit (so ``-0.0`` and ``0.0``, or a float32 and a float64, differ)."""
    if type(a) is not type(b):
        return False
    if isinstance(a, np.ndarray):
        return bool(a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes())
    return bool(np.asarray(a).tobytes() == np.asarray(b).tobytes())


def _difference(t: int, out_a: Any, out_b: Any) -> str | None:
    """What differs between two ``step`` results ``(obs, reward, terminated, truncated,
    info)`` or two ``reset`` results ``(obs, info)`` (``t = -1`` names the first reset)."""
    names: tuple[str, ...] = ("observation", "reward", "terminated", "truncated", "info")
    if len(out_a) == 2:
        names = ("observation", "info")
    for name, a, b in zip(names, out_a, out_b, strict=True):
        if name in ("observation", "reward"):
            same = _same_bits(a, b)
        else:
            same = type(a) is type(b) and a == b
        if not same:
            return f"step {t}: the {name} differs ({a!r} against {b!r})"
    return None


def side_by_side(
    task: str, steps: int, seed: int = 0, make: Any = None, reference: Any = None
) -> SideBySide:
    """Step the batched and the reference environment of ``task`` with the same actions.

    The actions are held for 1-60 steps each, half of them drawn in [-1.5, 1.5] (outside
    the bounds [-1, 1] included) and half at +-1.2 on every joint (which topples the Ant: its
    episodes end by ``terminated``). Besides the ends of episodes, both are reset at random
    times, with a new seed or none. Every observation, reward, ``terminated``,
    ``truncated`` and reset observation is compared bit for bit; the first difference ends
    the run. ``make`` and ``reference`` build the two environments (default:
    :func:`pporpe.envs.make_env` with ``bullet_step="batched"`` and ``"reference"``).
    """
    env_a = make(task) if make is not None else make_env(task, bullet_step="batched")
    env_b = reference(task) if reference is not None else make_env(task, bullet_step="reference")
    rng = np.random.default_rng(seed)
    dim = int(np.prod(np.shape(env_a.action_space.sample())))
    counts = {"resets": 0, "terminations": 0, "truncations": 0}
    try:
        found = _difference(-1, env_a.reset(seed=seed), env_b.reset(seed=seed))
        action, hold = None, 0
        for t in range(steps if found is None else 0):
            if hold == 0:
                action, hold = _held_action(rng, dim)
            hold -= 1
            out_a, out_b = env_a.step(action), env_b.step(action)
            found = _difference(t, out_a, out_b)
            if found is not None:
                break
            counts["terminations"] += int(out_a[2])
            counts["truncations"] += int(out_a[3] and not out_a[2])
            if out_a[2] or out_a[3] or rng.random() < 1 / 1500:
                counts["resets"] += 1
                new_seed = int(rng.integers(2**31)) if rng.random() < 0.5 else None
                found = _difference(t, env_a.reset(seed=new_seed), env_b.reset(seed=new_seed))
                if found is not None:
                    break
    finally:
        env_a.close()
        env_b.close()
    return SideBySide(task=task, steps=steps, seed=seed, first_difference=found, **counts)


def _held_action(rng: np.random.Generator, dim: int) -> tuple[np.ndarray, int]:
    """An action (float32) and how many steps to hold it."""
    if rng.random() < 0.5:
        action = rng.uniform(-1.5, 1.5, dim)
    else:
        action = rng.choice([-1.2, 1.2], dim)
    return action.astype(np.float32), int(rng.integers(1, 61))
