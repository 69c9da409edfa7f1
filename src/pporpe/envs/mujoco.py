"""pporpe's own step of Gymnasium's MuJoCo locomotion tasks (-v4): the same numbers, less Python.

Gymnasium's ``HopperEnv.step`` (v4) spends about a quarter of its time in Python around
MuJoCo's ``mj_step``: ``is_healthy`` is a property evaluated twice per step (once for the
reward, once for ``terminated``), each time concatenating ``qpos`` and ``qvel``;
``self.dt`` is a property computed from the model at every call; the observation copies
``qpos`` and ``qvel`` before slicing them; the Ant reads its torso's position by name
(``data.body("torso")``) twice a step. In batch PPO, where the environment is most of a
member-step (``benchmarks/batch_population.py``), this is worth removing.

The classes here are Gymnasium's own (``HopperEnv``, ``Walker2dEnv``, ``HalfCheetahEnv``,
``AntEnv`` of ``-v4``, with their constructors, models, ``reset`` and seeding, inherited,
not rewritten) with :meth:`step` written again so that every number is computed by the
same operations on values of the same types, in the same order:

* the simulation is the same two calls, ``mj_step(model, data, nstep=frame_skip)`` and
  ``mj_rnePostConstraint`` (which fills ``cfrc_ext``, read by the Ant's contact forces);
* the step's length is ``model.opt.timestep * frame_skip`` (``self.dt``), computed at
  construction;
* the control cost is ``weight * np.sum(np.square(action))`` on the action as given (a
  float32 action gives a float32 cost, as in the reference);
* the health tests are evaluated once per step, with the reference's comparisons;
* the observation is the same slices of ``qpos`` and ``qvel`` (clipped where the reference
  clips) concatenated into a new float64 array;
* the reward is the reference's sum, ``(forward + healthy) - costs``, and ``info`` has
  the reference's keys and values.

``tests/test_mujoco_step.py`` checks observations, rewards, flags, ``info`` and reset
observations bit for bit over thousands of steps per task; ``benchmarks/mujoco_step.py``
over many more, and times both steps side by side.

The step falls back to the reference's own (``super().step``) where it would compute
something else: with ``render_mode="human"`` (the reference renders in its step), for an
Ant built with ``use_contact_forces=True`` (its observation holds the contact forces and
its reward their cost), and for an action of the wrong shape (the reference raises its
error). The -v5 tasks, and every other MuJoCo task, run Gymnasium's own step.

These classes are what :func:`pporpe.envs.make_env` builds for the -v4 tasks by default
(:data:`pporpe.envs.MUJOCO_LEAN_ENTRY_POINTS`);
``make_env(..., mujoco_step="reference")`` or the environment variable
``PPORPE_MUJOCO_STEP=reference`` builds Gymnasium's own classes instead, to check a result
against them.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium.envs.mujoco.ant_v4 import AntEnv
from gymnasium.envs.mujoco.half_cheetah_v4 import HalfCheetahEnv
from gymnasium.envs.mujoco.hopper_v4 import HopperEnv
from gymnasium.envs.mujoco.walker2d_v4 import Walker2dEnv
from gymnasium.error import DependencyNotInstalled

try:
    import mujoco
except ImportError as exc:  # Gymnasium's modules above raise this already; in case they do not
    raise DependencyNotInstalled(f"MuJoCo is not installed: {exc}") from exc

__all__ = [
    "AntLeanEnv",
    "HalfCheetahLeanEnv",
    "HopperLeanEnv",
    "Walker2dLeanEnv",
]

StepResult = tuple[np.ndarray, Any, bool, bool, dict[str, Any]]
"""``(observation, reward, terminated, truncated, info)``."""


def _sum_of_squares(action: Any) -> Any:
    """``np.sum(np.square(action))`` for a 1-D action (the same reduction, without
    ``np.sum``'s dispatch): a float32 action gives a float32 sum."""
    return np.add.reduce(np.square(action))


def _clip10(v: np.ndarray) -> np.ndarray:
    """``np.clip(v, -10, 10)`` of float64 values as two ufuncs: ``min(max(v, -10), 10)``,
    NaN kept, which is how NumPy clips floats."""
    return np.minimum(np.maximum(v, -10.0), 10.0)


def _inside(bounds: tuple[float, float], values: np.ndarray) -> bool:
    """``np.all(np.logical_and(low < values, values < high))``: every value strictly inside
    the bounds; False where a value is NaN (its min or max is NaN and compares False)."""
    low, high = bounds
    return bool(low < np.minimum.reduce(values) and np.maximum.reduce(values) < high)


class _LeanStep:
    """What the lean steps share: the simulation and the cases left to the reference."""

    model: Any
    data: Any
    frame_skip: int
    render_mode: str | None
    _ctrl_cost_weight: float

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)  # the task's own constructor, next in the MRO
        # read once what the reference reads at every step
        self._step_dt = self.model.opt.timestep * self.frame_skip
        self._action_shape = (self.model.nu,)

    def _lean(self, action: Any) -> bool:
        """Whether this step is the lean one (else the reference's ``step`` is called)."""
        return self.render_mode != "human" and np.shape(action) == self._action_shape

    def _simulate_forward(self, action: Any) -> tuple[Any, Any, Any]:
        """Simulate the step of a task rewarded for x velocity: ``(x after, x velocity,
        control cost)`` as the reference computes them."""
        qpos = self.data.qpos
        x_before = qpos[0]
        self._simulate(action)
        x_after = qpos[0]
        ctrl_cost = self._ctrl_cost_weight * _sum_of_squares(action)
        return x_after, (x_after - x_before) / self._step_dt, ctrl_cost

    def _simulate(self, action: Any) -> None:
        """The reference's ``do_simulation`` after its shape check."""
        self.data.ctrl[:] = action
        mujoco.mj_step(self.model, self.data, nstep=self.frame_skip)
        mujoco.mj_rnePostConstraint(self.model, self.data)


class _PlanarWalker(_LeanStep):
    """The step of a walker in the plane (Hopper, Walker2d): forward velocity, a healthy
    reward, a control cost, velocities clipped to [-10, 10] in the observation, and the end
    of the episode when it falls (:meth:`_healthy`, per task)."""

    _forward_reward_weight: float
    _healthy_reward: float
    _terminate_when_unhealthy: bool
    _exclude_current_positions_from_observation: bool

    def _healthy(self, qpos: np.ndarray, qvel: np.ndarray) -> bool:
        raise NotImplementedError

    def step(self, action: Any) -> StepResult:
        """Gymnasium's step of the walker, computed as the module docstring says."""
        if not self._lean(action):
            return super().step(action)  # type: ignore[misc]
        qpos, qvel = self.data.qpos, self.data.qvel
        x_after, x_velocity, ctrl_cost = self._simulate_forward(action)
        healthy = self._healthy(qpos, qvel)
        unhealthy_ends = self._terminate_when_unhealthy
        healthy_reward = float(healthy or unhealthy_ends) * self._healthy_reward
        reward = (self._forward_reward_weight * x_velocity + healthy_reward) - ctrl_cost
        start = 1 if self._exclude_current_positions_from_observation else 0
        observation = np.concatenate((qpos[start:], _clip10(qvel)))
        terminated = (not healthy) if unhealthy_ends else False
        info = {"x_position": x_after, "x_velocity": x_velocity}
        return observation, reward, terminated, False, info


class HopperLeanEnv(_PlanarWalker, HopperEnv):
    """Gymnasium's ``Hopper-v4`` with pporpe's step (the same numbers)."""

    def _healthy(self, qpos: np.ndarray, qvel: np.ndarray) -> bool:
        """``is_healthy``: every state but x and z inside its range, z and the angle too."""
        min_z, max_z = self._healthy_z_range
        min_angle, max_angle = self._healthy_angle_range
        return bool(
            _inside(self._healthy_state_range, np.concatenate((qpos[2:], qvel)))
            and min_z < qpos[1] < max_z
            and min_angle < qpos[2] < max_angle
        )


class Walker2dLeanEnv(_PlanarWalker, Walker2dEnv):
    """Gymnasium's ``Walker2d-v4`` with pporpe's step (the same numbers)."""

    def _healthy(self, qpos: np.ndarray, qvel: np.ndarray) -> bool:
        """``is_healthy``: z and the torso's angle inside their ranges."""
        min_z, max_z = self._healthy_z_range
        min_angle, max_angle = self._healthy_angle_range
        return bool((min_z < qpos[1] < max_z) and (min_angle < qpos[2] < max_angle))


class HalfCheetahLeanEnv(_LeanStep, HalfCheetahEnv):
    """Gymnasium's ``HalfCheetah-v4`` with pporpe's step (the same numbers)."""

    def step(self, action: Any) -> StepResult:
        """Gymnasium's ``HalfCheetah-v4`` step, computed as the module docstring says."""
        if not self._lean(action):
            return super().step(action)
        qpos, qvel = self.data.qpos, self.data.qvel
        x_after, x_velocity, ctrl_cost = self._simulate_forward(action)
        forward_reward = self._forward_reward_weight * x_velocity
        start = 1 if self._exclude_current_positions_from_observation else 0
        observation = np.concatenate((qpos[start:], qvel))
        info = {
            "x_position": x_after,
            "x_velocity": x_velocity,
            "reward_run": forward_reward,
            "reward_ctrl": -ctrl_cost,
        }
        return observation, forward_reward - ctrl_cost, False, False, info


class AntLeanEnv(_LeanStep, AntEnv):
    """Gymnasium's ``Ant-v4`` with pporpe's step (the same numbers); with
    ``use_contact_forces=True``, the reference's step."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self._torso = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, "torso")

    def step(self, action: Any) -> StepResult:
        """Gymnasium's ``Ant-v4`` step, computed as the module docstring says."""
        if self._use_contact_forces or not self._lean(action):
            return super().step(action)
        qpos, qvel, xpos = self.data.qpos, self.data.qvel, self.data.xpos
        xy_before = xpos[self._torso, :2].copy()
        self._simulate(action)
        xy_after = xpos[self._torso, :2].copy()
        xy_velocity = (xy_after - xy_before) / self._step_dt
        x_velocity, y_velocity = xy_velocity
        min_z, max_z = self._healthy_z_range
        healthy = np.isfinite(qpos).all() and np.isfinite(qvel).all() and min_z <= qpos[2] <= max_z
        unhealthy_ends = self._terminate_when_unhealthy
        healthy_reward = float(healthy or unhealthy_ends) * self._healthy_reward
        ctrl_cost = self._ctrl_cost_weight * _sum_of_squares(action)
        start = 2 if self._exclude_current_positions_from_observation else 0
        observation = np.concatenate((qpos[start:], qvel))
        info = {
            "reward_forward": x_velocity,
            "reward_ctrl": -ctrl_cost,
            "reward_survive": healthy_reward,
            "x_position": xy_after[0],
            "y_position": xy_after[1],
            "distance_from_origin": np.linalg.norm(xy_after, ord=2),
            "x_velocity": x_velocity,
            "y_velocity": y_velocity,
            "forward_reward": x_velocity,
        }
        terminated = (not healthy) if unhealthy_ends else False
        return observation, (x_velocity + healthy_reward) - ctrl_cost, terminated, False, info

