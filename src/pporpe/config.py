"""Typed, frozen configurations with validation.

Names follow the paper's symbols (see ``docs/glossary.md``). Every field has a
docstring; every invalid value raises ``ValueError`` in ``__post_init__`` naming the
field, its value and what is allowed, so bad input fails before any work starts.
Configurations round-trip through plain dictionaries (:func:`config_to_dict`,
``from_dict``) and are saved as JSON with every run.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Literal, TypeVar, get_args

from .surrogates import METHODS, Method, RPEForm, check_surrogate_params

__all__ = [
    "Activation",
    "OnlineConfig",
    "TrainConfig",
    "config_from_dict",
    "config_to_dict",
    "validate_network_fields",
    "validate_surrogate_fields",
]

PolicyKind = Literal["student_t", "normal"]
Activation = Literal["swish", "relu", "tanh"]


def _require(cond: bool, name: str, value: object, allowed: str) -> None:
    if not cond:
        raise ValueError(f"{name} must be {allowed}; got {name}={value!r}")


def _is_num(x: object) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and not math.isnan(x)


def _is_int(x: object) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def validate_surrogate_fields(cfg: Any) -> None:
    """Validate the surrogate fields every learner config has: method, eps, beta, eta, rpe_form.

    Raises ``ValueError`` naming the field, its value and the allowed range. ``beta`` and
    ``eta`` are range-checked even for the methods that ignore them, so a typo is caught.
    """
    _require(cfg.method in METHODS, "method", cfg.method, f"one of {list(METHODS)}")
    for name in ("eps", "beta", "eta"):
        _require(_is_num(getattr(cfg, name)), name, getattr(cfg, name), "a number")
    check_surrogate_params(cfg.method, cfg.eps, cfg.beta, cfg.eta)
    if cfg.method != "rpe":
        _require(0.0 <= cfg.beta <= 1.0, "beta", cfg.beta, "in [0, 1]")
    if cfg.method != "rb":
        _require(0.0 <= cfg.eta < math.inf, "eta", cfg.eta, "a finite number >= 0")
    _require(
        cfg.rpe_form in ("derived", "printed"), "rpe_form", cfg.rpe_form, "'derived' or 'printed'"
    )


def validate_network_fields(cfg: Any) -> None:
    """Validate the network fields the learner configs share: layers, units, activation."""
    _require(_is_int(cfg.layers) and cfg.layers >= 1, "layers", cfg.layers, "an int >= 1")
    _require(_is_int(cfg.units) and cfg.units >= 1, "units", cfg.units, "an int >= 1")
    _require(
        cfg.activation in get_args(Activation),
        "activation",
        cfg.activation,
        f"one of {list(get_args(Activation))}",
    )


@dataclass(frozen=True)
class OnlineConfig:
    """Settings of the paper's online actor-critic learner (Alg. 1, Table 1).

    Defaults are the paper's. Optimiser constants the paper leaves at "default" are
    documented in :class:`pporpe.optim.TDAmsProp`.
    """

    method: Method = "rpe"
    """Surrogate: ``"ppo"`` (clip), ``"rb"`` (rollback) or ``"rpe"`` (relative Pearson)."""
    eps: float = 0.1
    """Threshold parameter epsilon, in (0, 1)."""
    beta: float = 0.5
    """PPO-RPE mixture ratio beta, in [0, 1] with beta*(1+eps) < 1."""
    eta: float = 0.3
    """PPO-RB rollback slope eta >= 0 (ignored by the other methods)."""
    rpe_form: RPEForm = "derived"
    """A~ of PPO-RPE: ``"derived"`` (exact derivative, default) or the paper's ``"printed"`` eq."""
    gamma: float = 0.99
    """Discount factor gamma, in [0, 1)."""
    lr: float = 3e-4
    """Learning rate alpha of td-AmsProp, > 0."""
    opt_betas: tuple[float, float] = (0.9, 0.999)
    """td-AmsProp (beta1, beta2): momentum and second-moment rates, each in [0, 1)."""
    opt_eps: float = 1e-8
    """td-AmsProp denominator epsilon, > 0."""
    k_dof: float = 1.0
    """t-momentum degrees of freedom per parameter, > 0 (``inf`` gives LaProp)."""
    amsgrad_decay: float = 0.999
    """Decay of the AMSGrad running maximum, in [0, 1] (1 = AMSGrad, 0 = none)."""
    tau: float = 0.3
    """t-soft target update rate tau, in (0, 1]."""
    nu: float = 1.0
    """t-soft degrees of freedom nu > 0 (``inf`` gives Polyak averaging)."""
    lambdas: tuple[float, float] = (0.5, 0.95)
    """Maximum trace decays (lambda_max1, lambda_max2) of the two time scales, in [0, 1]."""
    kappa: float = 10.0
    """Sensitivity kappa >= 0 of the adaptive trace decay exp(-kappa * divergence)."""
    beta_td: float = 0.01
    """Gain beta_TD >= 0 of TD regularisation (Parisi et al. 2019)."""
    beta_de: float = 0.01
    """Gain beta_DE >= 0 of entropy regularisation (SAC-style)."""
    reward_scale: float | None = None
    """Multiplier of rewards; ``None`` means 1 - gamma (the author's test bed)."""
    layers: int = 5
    """Hidden layers L of each network, >= 1."""
    units: int = 100
    """Units N per hidden layer, >= 1."""
    layer_norm: bool = True
    """LayerNorm after each hidden linear layer."""
    activation: Activation = "swish"
    """Hidden activation: ``"swish"`` (x*sigmoid(x)), ``"relu"`` or ``"tanh"``."""
    policy: PolicyKind = "student_t"
    """Policy distribution: diagonal ``"student_t"`` (paper) or ``"normal"``."""
    compile: bool = False
    """Compile the forward pass and loss with ``torch.compile`` (5-30% faster on a 2-core CPU
    after a compile of tens of seconds; see docs/online-learner.md)."""

    def __post_init__(self) -> None:
        validate_surrogate_fields(self)
        for name in ("gamma", "lr", "opt_eps", "k_dof", "tau", "nu"):
            _require(_is_num(getattr(self, name)), name, getattr(self, name), "a number")
        _require(0.0 <= self.gamma < 1.0, "gamma", self.gamma, "in [0, 1)")
        _require(0.0 < self.lr < math.inf, "lr", self.lr, "a finite number > 0")
        _require(
            len(self.opt_betas) == 2 and all(_is_num(b) and 0.0 <= b < 1.0 for b in self.opt_betas),
            "opt_betas",
            self.opt_betas,
            "two numbers in [0, 1)",
        )
        _require(self.opt_eps > 0.0, "opt_eps", self.opt_eps, "> 0")
        _require(self.k_dof > 0.0, "k_dof", self.k_dof, "> 0 (inf allowed)")
        _require(
            _is_num(self.amsgrad_decay) and 0.0 <= self.amsgrad_decay <= 1.0,
            "amsgrad_decay",
            self.amsgrad_decay,
            "in [0, 1]",
        )
        _require(0.0 < self.tau <= 1.0, "tau", self.tau, "in (0, 1]")
        _require(self.nu > 0.0, "nu", self.nu, "> 0 (inf allowed)")
        _require(
            len(self.lambdas) == 2 and all(_is_num(x) and 0.0 <= x <= 1.0 for x in self.lambdas),
            "lambdas",
            self.lambdas,
            "two numbers in [0, 1]",
        )
        _require(
            _is_num(self.kappa) and 0.0 <= self.kappa < math.inf,
            "kappa",
            self.kappa,
            "a finite number >= 0",
        )
        for name in ("beta_td", "beta_de"):
            v = getattr(self, name)
            _require(_is_num(v) and 0.0 <= v < math.inf, name, v, "a finite number >= 0")
        _require(
            self.reward_scale is None
            or (_is_num(self.reward_scale) and 0.0 < self.reward_scale < math.inf),
            "reward_scale",
            self.reward_scale,
            "None or a finite number > 0",
        )
        validate_network_fields(self)
        _require(
            self.policy in get_args(PolicyKind),
            "policy",
            self.policy,
            f"one of {list(get_args(PolicyKind))}",
        )

    @property
    def effective_reward_scale(self) -> float:
        """The reward multiplier in use: ``reward_scale`` or 1 - gamma."""
        return 1.0 - self.gamma if self.reward_scale is None else self.reward_scale


@dataclass(frozen=True)
class TrainConfig:
    """One training run: which task, how long, where, and the learner's settings."""

    env: str = "pendulum"
    """Task: an alias (pendulum, swingup, halfcheetah, ant) or a Gymnasium id with Box actions."""
    seed: int = 0
    """Seed of the networks, the sampling and the environment, >= 0."""
    episodes: int | None = 200
    """Training length in episodes (>= 1); ``None`` when ``steps`` sets it."""
    steps: int | None = None
    """Training length in environment steps (>= 1); ``None`` when ``episodes`` sets it."""
    checkpoint_every: int = 10
    """Write a checkpoint every this many episodes (>= 1), and at the end."""
    eval_episodes: int = 50
    """Test episodes after training (>= 0; the paper's score is the median of 50)."""
    learner: OnlineConfig = field(default_factory=OnlineConfig)
    """Settings of the online learner."""

    def __post_init__(self) -> None:
        _require(isinstance(self.env, str) and bool(self.env), "env", self.env, "a task name")
        _require(_is_int(self.seed) and self.seed >= 0, "seed", self.seed, "an int >= 0")
        _require(
            (self.episodes is None) != (self.steps is None),
            "episodes/steps",
            (self.episodes, self.steps),
            "exactly one of the two set",
        )
        if self.episodes is not None:
            _require(
                _is_int(self.episodes) and self.episodes >= 1,
                "episodes",
                self.episodes,
                "an int >= 1",
            )
        if self.steps is not None:
            _require(_is_int(self.steps) and self.steps >= 1, "steps", self.steps, "an int >= 1")
        _require(
            _is_int(self.checkpoint_every) and self.checkpoint_every >= 1,
            "checkpoint_every",
            self.checkpoint_every,
            "an int >= 1",
        )
        _require(
            _is_int(self.eval_episodes) and self.eval_episodes >= 0,
            "eval_episodes",
            self.eval_episodes,
            "an int >= 0",
        )
        _require(isinstance(self.learner, OnlineConfig), "learner", self.learner, "an OnlineConfig")


def config_to_dict(cfg: Any) -> dict[str, Any]:
    """A JSON-ready dictionary of a config dataclass (nested configs become dicts)."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            value = config_to_dict(value)
        elif isinstance(value, tuple):
            value = list(value)
        elif isinstance(value, float) and math.isinf(value):
            value = "inf"
        out[f.name] = value
    return out


C = TypeVar("C")


def config_from_dict(cls: type[C], data: dict[str, Any], where: str = "config") -> C:
    """Build ``cls`` from a dictionary, rejecting unknown fields and wrong types by name.

    Nested dataclass fields accept dictionaries; lists become tuples; the string
    ``"inf"`` becomes ``math.inf``. ``where`` prefixes error messages (e.g. a file name).
    """
    if not isinstance(data, dict):
        raise ValueError(f"{where}: expected a table of settings; got {data!r}")
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ValueError(
            f"{where}: unknown field(s) {unknown}; allowed fields are {sorted(fields)}"
        )
    kwargs: dict[str, Any] = {}
    hints = {f.name: f.default_factory for f in fields.values()}  # nested config factories
    for name, value in data.items():
        factory = hints[name]
        if factory is not dataclasses.MISSING and dataclasses.is_dataclass(factory):
            value = config_from_dict(factory, value, f"{where}.{name}")
        elif isinstance(value, list):
            value = tuple(value)
        elif value == "inf":
            value = math.inf
        kwargs[name] = value
    try:
        return cls(**kwargs)
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None
    except TypeError as exc:
        raise ValueError(f"{where}: {exc}") from None
