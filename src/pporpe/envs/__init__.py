"""Environment construction for the paper's tasks (PyBullet through Gymnasium).

The paper evaluates on four PyBullet tasks; this module gives them short aliases,
validates names cheaply (no environment is built) and builds environments with
the checks the learners rely on: a Box action space (continuous control, the
policy maps into its bounds) and a 1-D Box observation space.

* :data:`ALIASES` maps the short names ``pendulum``, ``swingup``, ``halfcheetah``
  and ``ant`` to their Gymnasium ids. Any other registered Gymnasium id with a
  Box action space works too (e.g. ``Pendulum-v1``).
* :func:`resolve_env_id` turns an alias or id into a registered id, or raises a
  :class:`ValueError` that lists the aliases. It only reads
  ``gymnasium.envs.registry``.
* :func:`make_env` builds the environment with ``gymnasium.make``. Gymnasium's
  ``TimeLimit`` wrapper is kept, so ``terminated`` (a true end of the task: do
  not bootstrap) and ``truncated`` (the step limit, 1000 steps for the Bullet
  tasks: bootstrap) stay separate.
* :func:`env_spec_summary` reports dimensions, bounds and the step limit.

The Bullet environments are registered by importing ``pybullet_envs_gymnasium``,
done lazily here. PyBullet prints a "pybullet build time" banner from C when it is
first imported (to standard error); :func:`make_env` imports it with the
process's standard output and error silenced at the file-descriptor level. PyBullet
also prints ``argv[0]=`` lines to standard output when an environment's Bullet client
starts (on its first ``reset``), which would land in a progress bar: a Bullet
environment from :func:`make_env` is wrapped in :class:`QuietBulletStart`, which
silences the descriptors for that one reset.

The paper's four tasks are stepped by pporpe's own implementation
(:mod:`pporpe.envs.bullet`): pybullet_envs_gymnasium's classes and models with a step
computed from a few batched PyBullet calls, bit for bit the same numbers at about twice the
speed. ``make_env(..., bullet_step="reference")``, or the environment variable
``PPORPE_BULLET_STEP=reference`` for a whole process (``pporpe train``, a grid's workers),
builds pybullet_envs_gymnasium's own step instead, to check a result against it.
Gymnasium's -v4 locomotion tasks (Hopper, Walker2d, HalfCheetah, Ant) are stepped the same
way by :mod:`pporpe.envs.mujoco`: Gymnasium's classes with a step that computes the same
numbers with less Python; ``mujoco_step="reference"`` or ``PPORPE_MUJOCO_STEP=reference``
builds Gymnasium's own.

The package: this module is its face (names, ``make_env``, the wrappers);
:mod:`pporpe.envs.registration` names the aliases and pporpe's steps by entry-point string
and imports nothing; :mod:`pporpe.envs.bullet` and :mod:`pporpe.envs.mujoco` hold the steps
(imported by ``gymnasium.make`` when it builds one of their tasks, and never importing this
face); :mod:`pporpe.envs.side_by_side` steps two implementations of a task side by side.
"""

from __future__ import annotations

import contextlib
import copy
import ctypes
import dataclasses
import importlib
import os
import re
import sys
import warnings
from collections.abc import Iterator
from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces

from .registration import (
    ALIASES,
    BATCHED_ENTRY_POINTS,
    BULLET_STEP_VARIABLE,
    BULLET_STEPS,
    MUJOCO_INSTALL,
    MUJOCO_LEAN_ENTRY_POINTS,
    MUJOCO_STEP_VARIABLE,
    MUJOCO_STEPS,
    is_gymnasium_mujoco,
)
from .registration import BULLET_PACKAGE as _BULLET_PACKAGE

__all__ = [
    "ALIASES",
    "BULLET_STEPS",
    "MUJOCO_INSTALL",
    "MUJOCO_LEAN_ENTRY_POINTS",
    "MUJOCO_STEPS",
    "GymnasiumWarning",
    "MuJoCoWarning",
    "QuietBulletStart",
    "ReplayableEnv",
    "bullet_step_choice",
    "env_spec_summary",
    "make_env",
    "mujoco_step_choice",
    "resolve_env_id",
]


def _missing_dependency(env_id: str, entry_point: Any, exc: Exception) -> ImportError:
    """The one-line error of a task whose package is not installed, saying what to install."""
    if is_gymnasium_mujoco(entry_point):
        return ImportError(f"{env_id} needs MuJoCo, which is not installed: {MUJOCO_INSTALL}")
    reason = (str(exc).strip().splitlines() or ["a package is missing"])[0]
    return ImportError(f"{env_id} cannot be built: {reason}")


def _aliases_text() -> str:
    """Return the aliases as ``name -> id`` pairs for error messages."""
    return ", ".join(f"{alias!r} -> {env_id}" for alias, env_id in ALIASES.items())


@contextlib.contextmanager
def _quiet_output() -> Iterator[None]:
    """Silence the process's standard output and error (descriptors 1 and 2) briefly.

    C libraries write to the descriptors directly, so replacing ``sys.stdout`` is not
    enough, and the descriptors are 1 and 2 whatever ``sys.stdout`` is now (under a capture
    its ``fileno()`` may name another file). A descriptor that is not open is left alone.
    """
    saved: list[tuple[int, int]] = []
    with contextlib.ExitStack() as stack:
        devnull = stack.enter_context(open(os.devnull, "w"))
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(AttributeError, OSError, ValueError):
                stream.flush()
        for fd in (1, 2):
            try:
                saved.append((fd, os.dup(fd)))
            except OSError:
                continue
            os.dup2(devnull.fileno(), fd)
        try:
            yield
        finally:
            with contextlib.suppress(Exception):
                ctypes.CDLL(None).fflush(None)  # drop what C buffered meanwhile
            for fd, copy in reversed(saved):
                os.dup2(copy, fd)
                os.close(copy)


def _register_bullet() -> None:
    """Import ``pybullet_envs_gymnasium`` so that the Bullet ids are registered.

    Registration only; PyBullet itself is imported when an environment is built.
    A missing package is not an error here: other Gymnasium ids still resolve.
    """
    if _BULLET_PACKAGE in sys.modules:
        return
    with contextlib.suppress(ImportError):
        importlib.import_module(_BULLET_PACKAGE)


def _import_pybullet_quietly() -> None:
    """Import ``pybullet`` once with its C banner silenced."""
    if "pybullet" in sys.modules:
        return
    with _quiet_output(), contextlib.suppress(ImportError):
        importlib.import_module("pybullet")


def resolve_env_id(name: str) -> str:
    """Return the registered Gymnasium id for an alias or an id.

    ``name`` is one of :data:`ALIASES` (case-insensitive) or any id registered
    with Gymnasium (the Bullet ids are registered here on first use). A
    ``"module:EnvId"`` name imports ``module`` first, as ``gymnasium.make`` does.
    No environment is built, so this is cheap enough to validate command lines.

    Raises:
        ValueError: if the name is neither an alias nor a registered id; the
            message lists the aliases.
    """
    key = name.strip() if isinstance(name, str) else ""
    key = ALIASES.get(key.lower(), key)
    if key:
        _register_bullet()
        if ":" in key:
            module, _, key = key.partition(":")
            with contextlib.suppress(ImportError):
                importlib.import_module(module)
        if key in gymnasium.envs.registry:
            return key
    raise ValueError(
        f"unknown environment {name!r}. Use an alias ({_aliases_text()}) or any "
        "registered Gymnasium id whose action space is a Box (continuous actions), "
        "e.g. 'Pendulum-v1'."
    )


def _step_choice(value: str | None, param: str, variable: str, choices: tuple[str, ...]) -> str:
    """``value``, else the environment variable ``variable``, else ``choices[0]``; a value
    outside ``choices`` raises a :class:`ValueError` naming where it came from."""
    where = param
    if value is None:
        value = os.environ.get(variable) or choices[0]
        where = variable
    if value not in choices:
        raise ValueError(f"{where} must be one of {', '.join(choices)}, not {value!r}")
    return value


def bullet_step_choice(bullet_step: str | None = None) -> str:
    """The step implementation for the Bullet tasks: ``bullet_step``, else the environment
    variable ``PPORPE_BULLET_STEP``, else ``"batched"``; a value outside
    :data:`BULLET_STEPS` raises a :class:`ValueError` naming where it came from."""
    return _step_choice(bullet_step, "bullet_step", BULLET_STEP_VARIABLE, BULLET_STEPS)


def mujoco_step_choice(mujoco_step: str | None = None) -> str:
    """The step implementation for the MuJoCo -v4 tasks: ``mujoco_step``, else the
    environment variable ``PPORPE_MUJOCO_STEP``, else ``"lean"``; a value outside
    :data:`MUJOCO_STEPS` raises a :class:`ValueError` naming where it came from."""
    return _step_choice(mujoco_step, "mujoco_step", MUJOCO_STEP_VARIABLE, MUJOCO_STEPS)


def _spec(env_id: str, bullet_step: str, mujoco_step: str) -> Any:
    """What ``gymnasium.make`` is given for a registered id: the id itself, or its spec with
    pporpe's step as the entry point (a Bullet task, PyBullet imported quietly first; a
    MuJoCo -v4 walker), as ``bullet_step`` and ``mujoco_step`` choose."""
    entry_point = gymnasium.envs.registry[env_id].entry_point
    if isinstance(entry_point, str) and entry_point.startswith(_BULLET_PACKAGE):
        _import_pybullet_quietly()
        return _bullet_spec(env_id, bullet_step)
    gymnasiums = is_gymnasium_mujoco(entry_point)
    if mujoco_step == "lean" and gymnasiums and env_id in MUJOCO_LEAN_ENTRY_POINTS:
        spec = gymnasium.envs.registry[env_id]
        return dataclasses.replace(spec, entry_point=MUJOCO_LEAN_ENTRY_POINTS[env_id])
    return env_id


def _bullet_spec(env_id: str, bullet_step: str) -> Any:
    """The id's registered spec, with pporpe's step as its entry point where it has one."""
    spec = gymnasium.envs.registry[env_id]
    if bullet_step == "batched" and env_id in BATCHED_ENTRY_POINTS:
        return dataclasses.replace(spec, entry_point=BATCHED_ENTRY_POINTS[env_id])
    return env_id


def make_env(
    name: str,
    seed: int | None = None,
    bullet_step: str | None = None,
    mujoco_step: str | None = None,
    **kwargs: Any,
) -> gymnasium.Env:
    """Build a continuous-control environment by alias or Gymnasium id.

    Args:
        name: an alias from :data:`ALIASES` or a registered Gymnasium id.
        seed: if given, seeds the action and observation spaces (their
            ``sample``). The environment's own generator is seeded by the
            caller's first ``env.reset(seed=seed)``, as Gymnasium intends.
        bullet_step: for the paper's four Bullet tasks, ``"batched"`` (pporpe's step,
            :mod:`pporpe.envs.bullet`) or ``"reference"`` (pybullet_envs_gymnasium's): the
            same numbers bit for bit, the first about twice as fast. Default: the
            environment variable ``PPORPE_BULLET_STEP``, else ``"batched"``. Other tasks
            ignore it.
        mujoco_step: for Gymnasium's -v4 locomotion tasks (:data:`MUJOCO_LEAN_ENTRY_POINTS`),
            ``"lean"`` (pporpe's step, :mod:`pporpe.envs.mujoco`) or ``"reference"``
            (Gymnasium's): the same numbers bit for bit, the first with less Python per
            step. Default: the environment variable ``PPORPE_MUJOCO_STEP``, else
            ``"lean"``. Other tasks ignore it.
        **kwargs: passed to ``gymnasium.make`` (e.g. ``render_mode``,
            ``max_episode_steps``).

    Returns:
        The environment as ``gymnasium.make`` returns it, with its ``TimeLimit``
        wrapper: ``step`` returns ``(obs, reward, terminated, truncated, info)``
        where ``truncated`` marks the step limit. A PyBullet environment comes inside
        :class:`QuietBulletStart` (outermost), so that its first ``reset`` prints
        nothing.

    Raises:
        ValueError: unknown name; a ``bullet_step`` outside :data:`BULLET_STEPS`, a
            ``mujoco_step`` outside :data:`MUJOCO_STEPS`; an action space not a 1-D
            ``gymnasium.spaces.Box`` with finite bounds; an observation space not a 1-D Box.
        ImportError: the task's package is not installed (a MuJoCo task without MuJoCo:
            :data:`MUJOCO_INSTALL`), saying what to install.
    """
    env_id = resolve_env_id(name)
    spec = _spec(env_id, bullet_step_choice(bullet_step), mujoco_step_choice(mujoco_step))
    entry_point = gymnasium.envs.registry[env_id].entry_point
    mujoco_task = is_gymnasium_mujoco(entry_point)
    try:
        with _mujoco_warnings_once() if mujoco_task else contextlib.nullcontext():
            env = _make_with_plain_warnings(spec, **kwargs)
    except gymnasium.error.DependencyNotInstalled as exc:
        raise _missing_dependency(env_id, entry_point, exc) from None
    if hasattr(env.unwrapped, "physicsClientId"):
        env = QuietBulletStart(env)
    problem = _spaces_problem(env_id, env.action_space, env.observation_space)
    if problem is not None:
        env.close()
        raise ValueError(problem)
    if seed is not None:
        env.action_space.seed(seed)
        env.observation_space.seed(seed)
    return env


def _spaces_problem(env_id: str, act_space: Any, obs_space: Any) -> str | None:
    """Why a task's spaces do not suit the learners (a Box action space, 1-D with finite
    bounds; a 1-D Box observation space), or None."""
    if not isinstance(act_space, spaces.Box):
        return (
            f"environment {env_id!r} has action space {act_space}, but a "
            f"gymnasium.spaces.Box (continuous actions) is required. Aliases: "
            f"{_aliases_text()}"
        )
    if len(act_space.shape) != 1 or not (
        np.all(np.isfinite(act_space.low)) and np.all(np.isfinite(act_space.high))
    ):
        return (
            f"environment {env_id!r} has action space {act_space}, but a 1-D Box with "
            "finite bounds is required (policies map into the bounds)"
        )
    if not isinstance(obs_space, spaces.Box) or len(obs_space.shape) != 1:
        return (
            f"environment {env_id!r} has observation space {obs_space}, but a 1-D "
            "gymnasium.spaces.Box is required"
        )
    return None


_ANSI_CODES = re.compile(r"\x1b\[[0-9;]*m")
_GYMNASIUM_WARNINGS_SHOWN: set[str] = set()


class GymnasiumWarning(UserWarning):
    """A warning Gymnasium gave while building a task (e.g. that a ``-v4`` MuJoCo task is
    out of date), without the terminal colour codes Gymnasium writes into it."""


def _warn_if_out_of_date(env_id: str) -> None:
    """Gymnasium's deprecation warning for an id with a newer version registered (which
    ``gymnasium.make`` gives for an id, not for a spec)."""
    registration = gymnasium.envs.registration
    ns, name, version = registration.parse_env_id(env_id)
    latest = registration.find_highest_version(ns, name)
    if version is not None and latest is not None and latest > version:
        gymnasium.logger.deprecation(
            f"The environment {env_id} is out of date. You should consider "
            f"upgrading to version `v{latest}`."
        )


def _make_with_plain_warnings(spec: Any, **kwargs: Any) -> gymnasium.Env:
    """``gymnasium.make``, its warnings given again as :class:`GymnasiumWarning` in plain
    text, each message once per process. A spec given as an ``EnvSpec`` (pporpe's step of a
    task) gets the warning Gymnasium gives its id, that a newer version exists."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        if isinstance(spec, gymnasium.envs.registration.EnvSpec):
            _warn_if_out_of_date(spec.id)
        env = gymnasium.make(spec, **kwargs)
    for w in caught:
        message = _ANSI_CODES.sub("", str(w.message)).removeprefix("WARN: ")
        if message not in _GYMNASIUM_WARNINGS_SHOWN:
            _GYMNASIUM_WARNINGS_SHOWN.add(message)
            warnings.warn_explicit(message, GymnasiumWarning, "gymnasium", 0)
    return env


class MuJoCoWarning(UserWarning):
    """A warning MuJoCo gave while compiling a task's model (e.g. that the ``-v4`` models'
    ``settotalmass`` attribute is deprecated), which it would otherwise print for every
    environment built: given once per process."""


_MUJOCO_WARNINGS_SHOWN: set[str] = set()


@contextlib.contextmanager
def _mujoco_warnings_once() -> Iterator[None]:
    """While building a MuJoCo task, MuJoCo's warnings as :class:`MuJoCoWarning`, each
    message once per process, instead of a printed line per environment. A warning handler
    the user installed (``mujoco.set_mju_user_warning``) is left in charge."""
    try:
        import mujoco
    except ImportError:  # make_env then says what to install
        yield
        return
    if mujoco.get_mju_user_warning() is not None:
        yield
        return
    caught: list[str] = []
    mujoco.set_mju_user_warning(caught.append)
    try:
        yield
    finally:
        mujoco.set_mju_user_warning(None)
        for message in caught:
            if message not in _MUJOCO_WARNINGS_SHOWN:
                _MUJOCO_WARNINGS_SHOWN.add(message)
                warnings.warn_explicit(message, MuJoCoWarning, "mujoco", 0)


class QuietBulletStart(gymnasium.Wrapper):
    """Silences standard output and error while a PyBullet environment's client starts.

    A PyBullet environment connects to its physics server on its first ``reset``, and the
    C code prints ``argv[0]=`` lines to the process's descriptors as it does, into
    whatever progress bar is on the terminal. This wrapper runs a ``reset`` that starts the
    client (``physicsClientId < 0`` before it) with descriptors 1 and 2 sent to
    ``/dev/null``; every later ``reset`` and every ``step`` passes through untouched.
    Python exceptions still propagate, and are printed after the descriptors are back.
    """

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> Any:
        if getattr(self.env.unwrapped, "physicsClientId", 0) >= 0:
            return self.env.reset(seed=seed, options=options)
        with _quiet_output():
            return self.env.reset(seed=seed, options=options)


def env_spec_summary(env: gymnasium.Env) -> dict[str, Any]:
    """Summarise an environment built by :func:`make_env`.

    Returns:
        A dict with ``id`` (str or None), ``obs_dim`` and ``act_dim`` (int),
        ``action_low`` and ``action_high`` (lists of float) and
        ``max_episode_steps`` (int or None).
    """
    act_space, obs_space = env.action_space, env.observation_space
    if not isinstance(act_space, spaces.Box) or not isinstance(obs_space, spaces.Box):
        raise ValueError("env_spec_summary needs Box action and observation spaces")
    spec = env.spec
    return {
        "id": spec.id if spec is not None else None,
        "obs_dim": int(np.prod(obs_space.shape)),
        "act_dim": int(np.prod(act_space.shape)),
        "action_low": [float(x) for x in np.asarray(act_space.low).reshape(-1)],
        "action_high": [float(x) for x in np.asarray(act_space.high).reshape(-1)],
        "max_episode_steps": spec.max_episode_steps if spec is not None else None,
    }


class ReplayableEnv(gymnasium.Wrapper):
    """Records how the current episode was reached, so that a checkpoint can rebuild it.

    On ``reset`` it keeps the seed (or the environment's RNG state when no seed is given)
    and on ``step`` every action; :meth:`replay_record` returns them and
    :meth:`replay_apply` replays a record on a fresh environment.
    """

    def __init__(self, env: gymnasium.Env) -> None:
        super().__init__(env)
        self._start: dict[str, Any] = {}
        self._actions: list[np.ndarray] = []
        self.replay_pending: dict[str, Any] | None = None

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> Any:
        rng = None
        if seed is None:
            rng = copy.deepcopy(self.env.unwrapped.np_random.bit_generator.state)
        self._start = {"seed": seed, "rng": rng, "options": options}
        self._actions = []
        return self.env.reset(seed=seed, options=options)

    def step(self, action: Any) -> Any:
        self._actions.append(np.array(action, copy=True))
        return self.env.step(action)

    def replay_record(self) -> dict[str, Any]:
        """The current episode's start and actions (a copy)."""
        acts = np.stack(self._actions) if self._actions else np.zeros((0,))
        return {**copy.deepcopy(self._start), "actions": acts}

    def replay_apply(self) -> Any:
        """Rebuild the episode in :attr:`replay_pending` (set it first, e.g. through a vector
        environment's ``set_attr``); return its current observation."""
        rec = self.replay_pending
        assert rec is not None
        self.replay_pending = None
        return self.replay(rec)

    def replay(self, rec: dict[str, Any]) -> Any:
        """Rebuild the episode of a :meth:`replay_record`; return its current observation."""
        if rec["rng"] is not None:
            self.env.unwrapped.np_random.bit_generator.state = rec["rng"]
        obs = self.reset(seed=rec["seed"], options=rec["options"])[0]
        for a in rec["actions"]:
            obs = self.step(a)[0]
        return obs
