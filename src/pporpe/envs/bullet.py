"""pporpe's own step of the paper's four PyBullet tasks: the same numbers, fewer calls.

pybullet_envs_gymnasium computes a step of HalfCheetah or Ant with about 40 calls into
PyBullet (one per joint to set its torque and read its state, one per body part for its
position, one per foot for its contacts), each through ``BulletClient.__getattr__`` (an
``inspect`` test and a ``functools.partial`` per call), around numpy on arrays of a few
elements: two thirds of the step's time, the physics a third. The environments here are
pybullet_envs_gymnasium's classes with :meth:`step` computed from a handful of batched
calls made straight to ``pybullet`` with the client's id:

* one ``setJointMotorControlArray`` sets every joint's torque,
* one ``getJointStates`` reads every joint, one ``getLinkStates`` every body part that is a
  link (``getBasePositionAndOrientation`` for a part that is the base of a body with mass,
  the Ant's torso; the floor, a body without mass that PyBullet never moves, is read once
  per reset),
* the torso's velocity, and one robot-floor ``getContactPoints`` for the feet.

Every number is computed as the reference computes it, operation for operation, so that
observations, rewards and flags are bit for bit the same (``tests/test_bullet_step.py``
checks it over thousands of steps; ``benchmarks/bullet_identity.py`` over 30,000 per task):
the part positions' mean x and y are numpy's pairwise sums of the same numbers in the same
order, divided by the count in float64; the 2-element norm, the 3x3 rotation, ``arctan2``,
``sin`` and ``cos`` stay numpy calls on numbers of the reference's types; the rest of the
observation is Python float arithmetic (the same IEEE operations as numpy's on scalars),
made float32 in one array; the joints-at-limit test and the electricity cost stay float32;
the foot contacts in an observation are the previous step's; and the reward is Python's
``sum`` of the same five terms in the same order. ``reset`` and seeding are the
reference's own (inherited, not rewritten): only the step is pporpe's.

The classes are what :func:`pporpe.envs.make_env` builds for the Bullet tasks by default;
``make_env(..., bullet_step="reference")`` or the environment variable
``PPORPE_BULLET_STEP=reference`` builds pybullet_envs_gymnasium's own classes instead, to
check a result against them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import pybullet
from pybullet_envs_gymnasium.gym_locomotion_envs import AntBulletEnv, HalfCheetahBulletEnv
from pybullet_envs_gymnasium.gym_pendulum_envs import (
    InvertedPendulumBulletEnv,
    InvertedPendulumSwingupBulletEnv,
)

from .registration import BATCHED_ENTRY_POINTS

__all__ = [
    "BATCHED_ENTRY_POINTS",
    "AntBatchedEnv",
    "HalfCheetahBatchedEnv",
    "InvertedPendulumBatchedEnv",
    "InvertedPendulumSwingupBatchedEnv",
    "WalkerLayout",
]


Pose = tuple[tuple[float, float, float], tuple[float, float, float, float]]
"""A position and an orientation (a quaternion), as PyBullet returns them."""


@dataclass(frozen=True)
class WalkerLayout:
    """Where a walker's joints, parts and feet are in PyBullet, read once per reset.

    A part is ``(body, link)``, ``link = -1`` for a body's base. The reference iterates
    over ``robot.parts`` (a dict, in its insertion order, the floor last) and
    ``robot.ordered_joints``; the layout keeps both orders. Per-joint numbers are Python
    floats, so that the step's arithmetic on them is the reference's, operation for operation.
    """

    client: int
    """The physics client's id, passed to every call."""
    body: int
    """The robot's body id (all its joints, links and feet belong to it)."""
    joints: list[int]
    """Joint indices in ``ordered_joints`` order (the action's order)."""
    torque_scale: list[float]
    """Per joint ``robot.power * joint.power_coef``, the torque of action 1."""
    lower: list[float]
    """Per joint its lower limit."""
    span: list[float]
    """Per joint ``upper - lower``."""
    links: list[int]
    """Link indices of the parts that are links of :attr:`body`, in parts order."""
    bases: list[tuple[int, int, tuple[float, float, float] | None]]
    """Per part that is a base, in parts order: its place in parts order, its body id, and
    its position if the body is static (no mass, as the floor: PyBullet never moves it, so
    it is read at reset), else None (read each step)."""
    torso: tuple[int, int]
    """``(body, link)`` of the robot's body part (the torso)."""
    torso_row: int
    """Where the torso's pose is among the links' states followed by the moving bases'."""
    feet: list[int]
    """Link indices of the feet on :attr:`body` (``robot.feet`` order)."""
    grounds: list[int]
    """Body ids of the ground parts, whose contacts with the feet count."""
    ground_ids: frozenset[tuple[int, int]]
    """``(body, link)`` of the ground parts, as the reference's ``ground_ids``."""

    @classmethod
    def of(cls, env: Any) -> WalkerLayout:
        """Read the layout of a walker environment that has been reset."""
        robot, c = env.robot, env.physicsClientId
        joints = robot.ordered_joints
        body = _where(joints[0])[0]
        parts = [_where(p) for p in robot.parts.values()]
        links = [link for b, link in parts if link >= 0 and b == body]
        bases = [(k, b, _static_position(b, c)) for k, (b, link) in enumerate(parts) if link < 0]
        torso = _where(robot.robot_body)
        rows = [(body, link) for link in links] + [(b, -1) for _, b, p in bases if p is None]
        if (
            len(links) + len(bases) != len(parts)
            or torso not in rows
            or any(_where(j)[0] != body for j in [*joints, *robot.feet])
        ):
            raise ValueError("a batched step needs every joint, link and foot on one body")
        return cls(
            client=c,
            body=body,
            joints=[j.jointIndex for j in joints],
            torque_scale=[robot.power * j.power_coef for j in joints],
            lower=[j.lowerLimit for j in joints],
            span=[j.upperLimit - j.lowerLimit for j in joints],
            links=links,
            bases=bases,
            torso=torso,
            torso_row=rows.index(torso),
            feet=[_where(f)[1] for f in robot.feet],
            grounds=sorted({b for b, _ in env.ground_ids}),
            ground_ids=frozenset(env.ground_ids),
        )


def _where(part: Any) -> tuple[int, int]:
    """``(body id, link or joint index)`` of a pybullet_envs_gymnasium part or joint."""
    index = part.bodyPartIndex if hasattr(part, "bodyPartIndex") else part.jointIndex
    return int(part.bodies[part.bodyIndex]), int(index)


def _static_position(body: int, client: int) -> tuple[float, float, float] | None:
    """The position of ``body``'s base if the body is static (its base has no mass), else
    None."""
    if pybullet.getDynamicsInfo(body, -1, physicsClientId=client)[0] != 0:
        return None
    return pybullet.getBasePositionAndOrientation(body, physicsClientId=client)[0]


def numpy_mean(x: np.ndarray) -> Any:
    """``x.mean()`` of a 1-D float array, computed as numpy computes it (numpy's
    ``_methods._mean``: the pairwise ``add.reduce``, divided by the count, an ``intp``, which
    promotes the sum to float64, and cast back to the array's type), without the Python
    around it. The division is done on Python floats: the same IEEE division.
    ``tests/test_bullet_step.py`` holds it to ``x.mean()`` bit for bit."""
    total = np.add.reduce(x)
    return total.dtype.type(float(total) / x.shape[0])


def mean_xy(positions: list[Any]) -> tuple[np.float64, np.float64]:
    """The mean x and the mean y of 3-D positions, each ``ndarray.mean`` of the x (or y)
    column as numpy computes it: the pairwise ``add.reduce`` of the same numbers in the
    same order (contiguous here, every third element of the flattened array in the
    reference: the pairwise sum depends on the count, not the stride), divided by the
    count in float64."""
    xs, ys, _ = zip(*positions, strict=True)
    n = len(xs)
    sx, sy = float(np.add.reduce(np.array(xs))), float(np.add.reduce(np.array(ys)))
    return np.float64(sx / n), np.float64(sy / n)


def apply_torques(layout: WalkerLayout, action: Any) -> None:
    """``robot.apply_action``: each joint's torque ``power * power_coef * clip(a, -1, 1)``.

    ``np.isfinite(a).all()`` is ``math.isfinite`` of every element, and
    ``float(np.clip(a_n, -1, 1))`` is ``float(a_n)`` bounded to [-1, 1] (NaN kept).
    """
    values = np.asarray(action).tolist()
    assert all(map(math.isfinite, values))
    forces = [
        k * (1.0 if x > 1.0 else -1.0 if x < -1.0 else x)
        for k, x in zip(layout.torque_scale, values, strict=True)
    ]
    pybullet.setJointMotorControlArray(
        layout.body, layout.joints, pybullet.TORQUE_CONTROL, forces=forces,
        physicsClientId=layout.client,
    )  # fmt: skip


def joint_features(layout: WalkerLayout) -> list[float]:
    """Per joint its position scaled to [-1, 1] between its limits and 0.1 x its speed,
    interleaved (``Joint.current_relative_position`` of every joint), as Python floats."""
    states = pybullet.getJointStates(layout.body, layout.joints, physicsClientId=layout.client)
    features: list[float] = []
    for s, low, span in zip(states, layout.lower, layout.span, strict=True):
        features += (2 * (s[0] - low) / span - 1.0, 0.1 * s[1])
    return features


def part_poses(layout: WalkerLayout) -> tuple[list[Any], Pose]:
    """Every part's position in parts order, and the torso's pose."""
    c = layout.client
    states = pybullet.getLinkStates(layout.body, layout.links, physicsClientId=c)
    positions = [s[0] for s in states]
    rows = list(states)
    for k, body, static in layout.bases:
        if static is None:
            pose = pybullet.getBasePositionAndOrientation(body, physicsClientId=c)
            rows.append(pose)
            static = pose[0]
        positions.insert(k, static)
    torso = rows[layout.torso_row]
    return positions, (torso[0], torso[1])


def torso_speed(layout: WalkerLayout) -> tuple[float, float, float]:
    """The torso's linear velocity in the world frame (``BodyPart.speed``)."""
    body, link = layout.torso
    if link < 0:
        return pybullet.getBaseVelocity(body, physicsClientId=layout.client)[0]
    return pybullet.getLinkState(body, link, 1, physicsClientId=layout.client)[6]


def feet_on_ground(layout: WalkerLayout, feet_contact: np.ndarray) -> None:
    """Set ``feet_contact[i]`` to 1 where foot i touches a ground part, else 0."""
    touching = {
        x[3]
        for ground in layout.grounds
        for x in pybullet.getContactPoints(layout.body, ground, physicsClientId=layout.client)
        if (x[2], x[4]) in layout.ground_ids
    }
    feet_contact[:] = [1.0 if foot in touching else 0.0 for foot in layout.feet]


_AT_LIMIT = float(np.float32(0.99))
"""The joints-at-limit threshold: numpy compares a float32 array with the Python float 0.99
in float32 (a Python scalar takes the array's type), that is with float32(0.99)."""


def walker_state(env: Any, layout: WalkerLayout) -> tuple[np.ndarray, list[float]]:
    """``WalkerBase.calc_state``: the observation, the same as Python floats, and the robot's
    attributes it sets.

    The observation's numbers are computed as Python floats (numpy scalars where the
    reference calls numpy on them) and made float32 in one array, which holds the
    reference's float32 joint features before the clip."""
    robot = env.robot
    features = joint_features(layout)
    positions, (torso_xyz, torso_quat) = part_poses(layout)
    robot.body_real_xyz = np.array(torso_xyz)
    robot.body_xyz = (*mean_xy(positions), torso_xyz[2])
    robot.body_rpy = pybullet.getEulerFromQuaternion(torso_quat)
    r, p, yaw = robot.body_rpy
    dy = robot.walk_target_y - robot.body_xyz[1]
    dx = robot.walk_target_x - robot.body_xyz[0]
    robot.walk_target_theta = np.arctan2(dy, dx)
    to_target = np.array([dy, dx])
    # np.linalg.norm's own steps; math.sqrt rounds as np.sqrt does (both IEEE)
    robot.walk_target_dist = np.float64(math.sqrt(to_target.dot(to_target)))
    angle_to_target = robot.walk_target_theta - yaw
    cos, sin = np.cos(-yaw), np.sin(-yaw)
    rot_speed = np.array([cos, -sin, 0.0, sin, cos, 0.0, 0.0, 0.0, 1.0]).reshape(3, 3)
    vx, vy, vz = np.dot(rot_speed, torso_speed(layout)).tolist()
    more = [torso_xyz[2] - robot.initial_z, np.sin(angle_to_target), np.cos(angle_to_target),
            0.3 * vx, 0.3 * vy, 0.3 * vz, r, p]  # fmt: skip
    full = np.array(more + features + robot.feet_contact.tolist(), dtype=np.float32)
    end = 8 + len(features)
    robot.joint_speeds = full[9:end:2]
    state = np.maximum(full, -5)
    np.minimum(state, +5, out=state)  # np.clip's own steps
    values = state.tolist()
    # |clip(x)| > 0.99 exactly where |x| > 0.99
    robot.joints_at_limit = sum([abs(x) > _AT_LIMIT for x in values[8:end:2]])
    return state, values


class BatchedWalkerStep:
    """``WalkerBaseBulletEnv.step`` from batched PyBullet calls (mixed into the task's class).

    ``reset`` is the reference's; afterwards the layout of joints, parts and feet is read
    once (:class:`WalkerLayout`), and each step uses it.
    """

    _layout: WalkerLayout | None = None

    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None) -> Any:
        out = super().reset(seed=seed, options=options)  # type: ignore[misc]
        self._layout = WalkerLayout.of(self)
        return out

    def step(self, a: Any) -> Any:
        env: Any = self
        layout = self._layout
        if layout is None:
            raise RuntimeError("call reset() before step()")
        robot = env.robot
        apply_torques(layout, a)
        pybullet.stepSimulation(physicsClientId=layout.client)
        state, values = walker_state(env, layout)
        env._alive = float(robot.alive_bonus(values[0] + robot.initial_z, robot.body_rpy[1]))
        done = env._isDone()
        # the clipped state is finite but where NaN, and the sum of its numbers in [-5, 5]
        # cannot overflow: the sum is NaN exactly where np.isfinite(state).all() is False
        if math.isnan(sum(values)):
            print("~INF~", state)
            done = True
        potential_old = env.potential
        env.potential = robot.calc_potential()
        progress = float(env.potential - potential_old)
        feet_on_ground(layout, robot.feet_contact)
        electricity = numpy_mean(np.abs(a * robot.joint_speeds))
        electricity_cost = env.electricity_cost * float(electricity)
        electricity_cost += env.stall_torque_cost * float(numpy_mean(np.square(a)))
        joints_at_limit_cost = float(env.joints_at_limit_cost * robot.joints_at_limit)
        env.rewards = [env._alive, progress, electricity_cost, joints_at_limit_cost, 0.0]
        reward = sum(env.rewards)
        env.reward += reward
        return state, reward, bool(done), False, {}


class HalfCheetahBatchedEnv(BatchedWalkerStep, HalfCheetahBulletEnv):
    """``HalfCheetahBulletEnv-v0`` with the batched step: the same numbers, about 1.8x as fast."""


class AntBatchedEnv(BatchedWalkerStep, AntBulletEnv):
    """``AntBulletEnv-v0`` with the batched step: the same numbers, about 1.8x as fast."""


class BatchedPendulumStep:
    """``InvertedPendulumBulletEnv.step`` with one call to read both joints."""

    _joints: tuple[int, int, int, int] | None = None

    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None) -> Any:
        out = super().reset(seed=seed, options=options)  # type: ignore[misc]
        robot: Any = self.robot  # type: ignore[attr-defined]
        hinge, slider = _where(robot.j1), _where(robot.slider)
        if hinge[0] != slider[0]:
            raise ValueError("a batched step needs the hinge and the slider on one body")
        self._joints = (self.physicsClientId, hinge[0], hinge[1], slider[1])  # type: ignore[attr-defined]
        return out

    def step(self, a: Any) -> Any:
        env: Any = self
        if self._joints is None:
            raise RuntimeError("call reset() before step()")
        client, body, hinge, slider = self._joints
        assert np.isfinite(a).all()
        torque = 100 * float(np.clip(a[0], -1, +1))
        pybullet.setJointMotorControl2(
            bodyIndex=body, jointIndex=slider, controlMode=pybullet.TORQUE_CONTROL,
            force=torque, physicsClientId=client,
        )  # fmt: skip
        pybullet.stepSimulation(physicsClientId=client)
        state = _pendulum_state(env.robot, pybullet.getJointStates(
            body, [hinge, slider], physicsClientId=client))  # fmt: skip
        if env.robot.swingup:
            reward = state[2]  # np.cos(theta), as computed for the observation
            done = False
        else:
            reward = 1.0
            done = np.abs(env.robot.theta) > 0.2
        env.rewards = [float(reward)]
        return state.astype(np.float32), sum(env.rewards), bool(done), False, {}


def _pendulum_state(robot: Any, joints: Any) -> np.ndarray:
    """``InvertedPendulum.calc_state`` from the hinge's and the slider's joint states."""
    robot.theta, theta_dot = joints[0][0], joints[0][1]
    x, vx = joints[1][0], joints[1][1]
    assert math.isfinite(x)
    if not math.isfinite(vx):
        print("vx is inf")
        vx = 0
    if not math.isfinite(robot.theta):
        print("theta is inf")
        robot.theta = 0
    if not math.isfinite(theta_dot):
        print("theta_dot is inf")
        theta_dot = 0
    return np.array([x, vx, np.cos(robot.theta), np.sin(robot.theta), theta_dot])


class InvertedPendulumBatchedEnv(BatchedPendulumStep, InvertedPendulumBulletEnv):
    """``InvertedPendulumBulletEnv-v0`` with the batched step: the same numbers."""


class InvertedPendulumSwingupBatchedEnv(
    BatchedPendulumStep, InvertedPendulumSwingupBulletEnv
):
    """``InvertedPendulumSwingupBulletEnv-v0`` with the batched step: the same numbers."""
