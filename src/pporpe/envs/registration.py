"""The names of pporpe's tasks and the entry points of its own steps, as strings.

Like Gymnasium's registration module, this one imports nothing: it says which class steps a
task (``"pporpe.envs.bullet:AntBatchedEnv"``) without importing PyBullet or MuJoCo, so that
:func:`pporpe.envs.resolve_env_id` stays cheap and a family's module is imported only when
``gymnasium.make`` builds one of its tasks. :mod:`pporpe.envs` (the face: ``make_env`` and
name resolution) reads these tables; :mod:`pporpe.envs.bullet` and :mod:`pporpe.envs.mujoco`
hold the classes they name.
"""

from __future__ import annotations

__all__ = [
    "ALIASES",
    "BATCHED_ENTRY_POINTS",
    "BULLET_PACKAGE",
    "BULLET_STEPS",
    "BULLET_STEP_VARIABLE",
    "GYMNASIUM_MUJOCO_PACKAGE",
    "MUJOCO_INSTALL",
    "MUJOCO_LEAN_ENTRY_POINTS",
    "MUJOCO_STEPS",
    "MUJOCO_STEP_VARIABLE",
    "is_gymnasium_mujoco",
]

ALIASES: dict[str, str] = {
    "pendulum": "InvertedPendulumBulletEnv-v0",
    "swingup": "InvertedPendulumSwingupBulletEnv-v0",
    "halfcheetah": "HalfCheetahBulletEnv-v0",
    "ant": "AntBulletEnv-v0",
}
"""Short names of the paper's four tasks and their Gymnasium ids."""

BULLET_PACKAGE = "pybullet_envs_gymnasium"
"""The package that registers the Bullet tasks (its entry points start with its name)."""

BULLET_STEPS = ("batched", "reference")
"""How the paper's four Bullet tasks are stepped: ``"batched"`` (pporpe's step,
:mod:`pporpe.envs.bullet`, the default) or ``"reference"`` (pybullet_envs_gymnasium's)."""

BULLET_STEP_VARIABLE = "PPORPE_BULLET_STEP"
"""The environment variable that sets the default of ``make_env``'s ``bullet_step``."""

BATCHED_ENTRY_POINTS: dict[str, str] = {
    "InvertedPendulumBulletEnv-v0": "pporpe.envs.bullet:InvertedPendulumBatchedEnv",
    "InvertedPendulumSwingupBulletEnv-v0": "pporpe.envs.bullet:InvertedPendulumSwingupBatchedEnv",
    "HalfCheetahBulletEnv-v0": "pporpe.envs.bullet:HalfCheetahBatchedEnv",
    "AntBulletEnv-v0": "pporpe.envs.bullet:AntBatchedEnv",
}
"""The Gymnasium ids whose step pporpe computes, and the class that computes it."""

MUJOCO_INSTALL = 'pip install -c constraints.txt -e ".[mujoco]"'
"""What to install for Gymnasium's MuJoCo tasks (``HalfCheetah-v5``, ``Ant-v5``, ...): the
one place the error of a MuJoCo task without MuJoCo takes it from."""

GYMNASIUM_MUJOCO_PACKAGE = "gymnasium.envs.mujoco"
"""Where Gymnasium's MuJoCo tasks live (their entry points start with it)."""


def is_gymnasium_mujoco(entry_point: object) -> bool:
    """Whether a registered entry point is one of Gymnasium's MuJoCo tasks (which need the
    mujoco package, and read ``MUJOCO_GL`` when it is imported)."""
    return isinstance(entry_point, str) and entry_point.startswith(GYMNASIUM_MUJOCO_PACKAGE)

MUJOCO_STEPS = ("lean", "reference")
"""How Gymnasium's -v4 locomotion tasks are stepped: ``"lean"`` (pporpe's step,
:mod:`pporpe.envs.mujoco`, the default) or ``"reference"`` (Gymnasium's)."""

MUJOCO_STEP_VARIABLE = "PPORPE_MUJOCO_STEP"
"""The environment variable that sets the default of ``make_env``'s ``mujoco_step``."""

MUJOCO_LEAN_ENTRY_POINTS: dict[str, str] = {
    "Hopper-v4": "pporpe.envs.mujoco:HopperLeanEnv",
    "Walker2d-v4": "pporpe.envs.mujoco:Walker2dLeanEnv",
    "HalfCheetah-v4": "pporpe.envs.mujoco:HalfCheetahLeanEnv",
    "Ant-v4": "pporpe.envs.mujoco:AntLeanEnv",
}
"""The Gymnasium ids that :mod:`pporpe.envs.mujoco` steps, and its classes for them."""
