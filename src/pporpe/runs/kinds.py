"""Learner kinds: how a learner plugs into the one run loop (:func:`pporpe.runs.train`).

A *learner kind* names a run configuration type and knows how to build a
:class:`Trainer` for it (the environment(s) and the learner, seeded), how to rebuild a
trained policy from a checkpoint, and how a grid spec's settings become a run
configuration. The run loop, the grid and the CLI only talk to this protocol, so a new
learner is one registration away from ``pporpe train``, ``pporpe evaluate`` and
``pporpe reproduce``.

Built in: ``"online"`` (the paper's Alg. 1, :mod:`pporpe.online`) and ``"batch"``
(batch PPO, :mod:`pporpe.batch`). They are imported lazily, on first use.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

if TYPE_CHECKING:
    from ..policy import Policy

__all__ = [
    "Episode",
    "LearnerKind",
    "NonFiniteError",
    "Progress",
    "SurrogateDiagnostics",
    "Trainer",
    "get_kind",
    "kind_of",
    "kinds",
    "register_kind",
]


class NonFiniteError(RuntimeError):
    """A non-finite observation, reward, loss or parameter stopped the run."""


@dataclass(frozen=True)
class SurrogateDiagnostics:
    """How a surrogate objective acted on the updates that learned from one episode:
    what a learner kind of the PPO family reports for each episode, besides the numbers
    every learner has (:class:`Episode`). Logged as four columns of ``episodes.csv``."""

    reg_amount: float
    """Mean sigma*(rho - rho_dagger) of the updates that learned from the episode."""
    past_threshold: float
    """Fraction of those updates whose ratio was past the surrogate's threshold."""
    ratio_dev: float
    """Mean |rho - 1| of those updates: how much one update changed the policy."""
    trace_decay: float | None = None
    """Mean adaptive trace decay over the episode; None for a learner without eligibility
    traces (batch PPO)."""


@dataclass(frozen=True)
class Episode:
    """A training episode that ended, as a trainer reports it (the loop adds its index
    and wall time to make an :class:`~pporpe.runs.logger.EpisodeRecord`)."""

    total_steps: int
    """Environment steps taken by the run when it ended."""
    ret: float
    """Undiscounted return (unscaled rewards)."""
    length: int
    """Steps in the episode."""
    diagnostics: SurrogateDiagnostics | None = None
    """The learner's diagnostics of the updates that learned from the episode (None for a
    learner that reports none)."""


@dataclass(frozen=True)
class Progress:
    """What one :meth:`Trainer.advance` did for one run."""

    episodes: list[Episode]
    """Episodes of the run that ended (possibly none)."""
    checkpoint_due: bool = False
    """Whether the run's checkpoint cadence asks for a checkpoint now."""
    bar_advance: int = 0
    """How far the run's progress bar moves (in the unit of :meth:`LearnerKind.budget`)."""
    scalars: Mapping[str, float] = field(default_factory=dict)
    """Extra scalars to log (e.g. a batch update's statistics), at :attr:`total_steps`."""
    total_steps: int = 0
    """Environment steps of the run after this advance."""
    error: str | None = None
    """Set when the run failed (e.g. a non-finite value): the run stops alone, with this
    message in its folder's ``error.txt``; the trainer's other runs go on."""


class Trainer(Protocol):
    """Runs in progress: up to :attr:`capacity` of them at once, in *slots*.

    A single-run learner has one slot; the online population learner trains K runs in
    lockstep. The run loop (:mod:`pporpe.runs.loop`) starts runs in free slots, advances
    all of them together, checkpoints, evaluates and stops them.
    """

    capacity: int
    """Number of slots."""

    def start(self, slot: int, cfg: Any, state: dict[str, Any] | None) -> None:
        """Begin a run in a free slot: fresh (seeded from ``cfg.seed``) when ``state`` is
        None, else continued from its checkpoint :meth:`state`."""
        ...

    def advance(self) -> dict[int, Progress]:
        """Do one unit of work (an environment step of every run, an update) and report
        what happened to each busy slot."""
        ...

    def finished(self, slot: int) -> bool:
        """Whether the run's budget is spent."""
        ...

    def counters(self, slot: int) -> dict[str, int]:
        """Counters saved in ``done.json``: at least ``total_steps`` and ``chunks`` (units
        of work done: episodes or updates)."""
        ...

    def bar_position(self, slot: int) -> int:
        """Where the run's progress bar stands."""
        ...

    def state(self, slot: int) -> dict[str, Any]:
        """Everything needed to continue the run exactly (the loop adds records and wall
        time); written as the run's ``checkpoint.pt``."""
        ...

    def parameters_finite(self, slot: int) -> bool:
        """Whether every parameter of the run is finite (checked before each checkpoint)."""
        ...

    def policy(self, slot: int) -> Callable[[Any], np.ndarray]:
        """The run's deterministic test-time policy ``act(obs) -> action`` (independent of
        the slot: it stays valid after :meth:`stop`)."""
        ...

    def stop(self, slot: int) -> None:
        """Free the slot."""
        ...

    def compact(self, keep: list[int]) -> None:
        """Shrink to ``len(keep)`` slots: the run in slot ``keep[j]`` moves to slot ``j``
        (called when the queue is empty and at most half the slots are busy)."""
        ...

    def close(self) -> None:
        """Release every environment."""
        ...


class LearnerKind(Protocol):
    """A learner that the run loop, the grid and the CLI can run."""

    @property
    def name(self) -> str:
        """The kind's name, saved as ``"kind"`` in every run's ``config.json``."""
        ...

    @property
    def config_type(self) -> type:
        """The run configuration dataclass (with ``env``, ``seed``, ``eval_episodes``)."""
        ...

    def make_trainer(self, cfg: Any, capacity: int) -> Trainer:
        """A trainer with up to ``capacity`` slots for runs shaped like ``cfg`` (the same
        task and network; kinds with one slot ignore ``capacity``)."""
        ...

    def budget(self, cfg: Any) -> tuple[int, str]:
        """A run's length for progress bars: ``(total, unit)``, unit ``"ep"`` or ``"step"``."""
        ...

    def pack_key(self, cfg: Any) -> Any:
        """Runs with equal keys can share a trainer (same task and network shape)."""
        ...

    def load_policy(self, cfg: Any, state: dict[str, Any]) -> Policy:
        """The trained policy of a checkpoint ``state`` (a :class:`pporpe.policy.Policy`:
        ``act(obs, deterministic=True)``, and ``policy(obs)`` for the test-time action)."""
        ...

    def grid_config(
        self,
        env: str,
        method: str,
        seed: int,
        budget: Mapping[str, int],
        common: Mapping[str, int],
        learner: Mapping[str, Any],
        where: str,
    ) -> Any:
        """A run configuration from a grid spec: ``budget`` holds ``episodes`` or
        ``steps``, ``common`` the spec's ``eval_episodes`` and ``checkpoint_every``, and
        ``learner`` the spec's learner overrides. Errors name ``where``."""
        ...

    def description(self, cfg: Any) -> str:
        """A short label for progress bars, e.g. ``"rpe pendulum s0"``."""
        ...


_BUILTIN = {"online": "pporpe.online.kind", "batch": "pporpe.batch.kind"}
_KINDS: dict[str, LearnerKind] = {}


def register_kind(kind: LearnerKind) -> LearnerKind:
    """Make a learner kind known to the run loop, the grid and the CLI (returns it)."""
    if not isinstance(getattr(kind, "name", None), str) or not kind.name:
        raise ValueError(f"a learner kind needs a non-empty name; got {kind!r}")
    _KINDS[kind.name] = kind
    return kind


def _load_builtins() -> None:
    for name, module in _BUILTIN.items():
        if name not in _KINDS:
            importlib.import_module(module)  # the module registers its kind


def kinds() -> list[str]:
    """Names of every registered learner kind."""
    _load_builtins()
    return sorted(_KINDS)


def get_kind(name: str) -> LearnerKind:
    """The learner kind of that name; ``ValueError`` listing the known kinds otherwise."""
    _load_builtins()
    if not isinstance(name, str) or name not in _KINDS:
        raise ValueError(f"kind must be one of {sorted(_KINDS)}; got kind={name!r}")
    return _KINDS[name]


def kind_of(cfg: Any) -> LearnerKind:
    """The learner kind whose run configuration type ``cfg`` is."""
    _load_builtins()
    for kind in _KINDS.values():
        if isinstance(cfg, kind.config_type):
            return kind
    types = sorted(k.config_type.__name__ for k in _KINDS.values())
    raise ValueError(f"no learner kind runs a {type(cfg).__name__}; expected one of {types}")
