"""Settings of the paper's online learner (:class:`OnlineConfig`) and of one online run
(:class:`TrainConfig`): typed, frozen, validated in ``__post_init__``."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Literal, get_args

from ..config import (
    Activation,
    Method,
    PolicyKind,
    RPEForm,
    is_real,
    require,
    validate_network_fields,
    validate_surrogate_fields,
)
from ..limits import MAX_EPISODES, MAX_EVAL_EPISODES, MAX_SEED, MAX_STEPS, check_int_in

__all__ = [
    "AMSGRAD_MAXES",
    "AUTHOR_CHOICES",
    "BASELINE_CHOICES",
    "CRITIC_SIGNALS",
    "DEFAULT_CHOICES",
    "ENGINES",
    "ENTROPY_DENSITIES",
    "HEAD_TENSORS",
    "POLICY_GRADIENTS",
    "TD_UNITS",
    "TESTBED",
    "TESTBED_WEIGHTS",
    "TIME_LIMITS",
    "TRACE_DIVERGENCES",
    "OnlineConfig",
    "TrainConfig",
]

CriticSignal = Literal["td", "actor"]
CRITIC_SIGNALS: tuple[str, ...] = get_args(CriticSignal)
TDUnits = Literal["scaled", "unscaled"]
TD_UNITS: tuple[str, ...] = get_args(TDUnits)
EntropyDensity = Literal["action", "pre_squash"]
ENTROPY_DENSITIES: tuple[str, ...] = get_args(EntropyDensity)
AmsgradMax = Literal["bias_corrected", "raw"]
AMSGRAD_MAXES: tuple[str, ...] = get_args(AmsgradMax)
TraceDivergence = Literal["sample", "analytic"]
TRACE_DIVERGENCES: tuple[str, ...] = get_args(TraceDivergence)
PolicyGradient = Literal["surrogate", "weighted_score"]
POLICY_GRADIENTS: tuple[str, ...] = get_args(PolicyGradient)
TimeLimit = Literal["bootstrap", "terminal"]
TIME_LIMITS: tuple[str, ...] = get_args(TimeLimit)
HeadTensors = Literal["joint", "per_output"]
HEAD_TENSORS: tuple[str, ...] = get_args(HeadTensors)
Engine = Literal["torch", "fused"]
ENGINES: tuple[str, ...] = get_args(Engine)


AUTHOR_CHOICES: Mapping[str, Any] = MappingProxyType(
    {
        "critic_signal": "actor",
        "td_units": "unscaled",
        "entropy_density": "pre_squash",
        "amsgrad_max": "raw",
        "amsgrad_decay": 0.99999,
        "layer_norm_affine": False,
        "trace_divergence": "analytic",
    }
)
"""The choices where the paper is silent, as the author's test bed makes them
(``OnlineConfig(**AUTHOR_CHOICES)``): the settings of the committed reproduction of the
paper (experiments/paper.toml, results/paper) and the ablation's ``all`` variant."""

BASELINE_CHOICES: Mapping[str, Any] = MappingProxyType(
    {
        "critic_signal": "td",
        "td_units": "scaled",
        "entropy_density": "action",
        "amsgrad_max": "bias_corrected",
        "amsgrad_decay": 0.999,
        "layer_norm_affine": True,
        "trace_divergence": "sample",
    }
)
"""The same fields as pporpe's first learner set them, before the author's test bed was read
(``OnlineConfig(**BASELINE_CHOICES)``): the ablation's ``baseline`` variant, against which
each of the author's choices was measured (docs/online-learner.md). What a run folder
written before these fields existed ran with is fixed in :mod:`pporpe.runs.migrate`."""

DEFAULT_CHOICES: Mapping[str, Any] = MappingProxyType(
    {
        **AUTHOR_CHOICES,
        "critic_signal": BASELINE_CHOICES["critic_signal"],
        "entropy_density": BASELINE_CHOICES["entropy_density"],
    }
)
"""pporpe's defaults: the author's choices but two, the critic trained with the
TD error (``critic_signal="td"``) and the entropy bonus of the bounded action
(``entropy_density="action"``), each of which made the learner worse in the ablation
(benchmarks/ablation.py, docs/online-learner.md)."""

TESTBED_WEIGHTS: Mapping[str, Any] = MappingProxyType(
    {"beta_td": 0.025, "beta_de": 0.025, "reward_scale": 0.0095}
)
"""The author's test bed's regulariser weights and reward scale, where the paper states
others (beta_TD = beta_DE = 0.01, reward scale 1 - gamma), so never a default: the test
bed folds both regularisers into the TD error with one weight w = 0.1 and a balance
b = 0.5, which make w*b*b = w*b*(1 - b) = 0.025 per term, and scales the reward by
(1 - gamma)(1 - w*b) = 0.0095 at gamma = 0.99 (the paper's; another gamma needs its own
reward scale). They give the test bed's signal only with ``td_units="unscaled"``, the
default. ``OnlineConfig(**TESTBED_WEIGHTS)`` is the defaults with them; the ablation
measured that on both pendulum tasks (docs/online-learner.md)."""

TESTBED: Mapping[str, Any] = MappingProxyType(
    {
        **AUTHOR_CHOICES,
        **TESTBED_WEIGHTS,
        "method": "ppo",
        "eps": 0.1,
        "gamma": 0.99,
        "lr": 1e-4,
        "layers": 5,
        "units": 128,
        "lambdas": (0.5, 0.9),
        "kappa": 1.0,
        "tau": 1.0,
        "policy_gradient": "weighted_score",
        "time_limit": "terminal",
        "min_scale": 1e-8,
        "head_tensors": "per_output",
    }
)
"""The learner of the author's public test bed (GitHub kbys-t/test_et, ``modules/ac.py``
with the last entry of ``test.py``'s METHODS), field by field:
``OnlineConfig(**TESTBED)`` is that learner. For comparison, never a default (the paper's
Table I states other values); ``benchmarks/testbed.py`` runs both side by side.

* :data:`AUTHOR_CHOICES`: where the paper is silent, the test bed's choices (critic
  trained with the actor's signal, unscaled TD units, pre-squash entropy, raw AMSGrad
  maximum decayed by 0.99999, LayerNorm without scale and shift, analytic trace KL);
* :data:`TESTBED_WEIGHTS`: one regulariser weight 0.1 with balance 0.5, i.e. 0.025 per
  term, and the reward scaled by (1 - gamma)(1 - 0.05);
* ``method="ppo"``, ``eps=0.1``: its only surrogate is PPO's clip with threshold 0.1,
  applied to the importance weight of the gradient (``policy_gradient="weighted_score"``);
* ``gamma=0.99``: its default, the paper's too;
* ``lr=1e-4``, ``layers=5``, ``units=128``: AC's defaults (the paper: 3e-4, 5 x 100);
* ``lambdas=(0.5, 0.9)``, ``kappa=1``: test.py's last METHODS entry (lambda1 0.5,
  lambda2 0.9, div_weight 1; the paper: 0.95 and 10);
* ``tau=1``: it has no target network (its TD target is the online V), which the t-soft
  update with rate 1 reproduces (the target equals the online network after every step);
* ``time_limit="terminal"``: its TD target drops the bootstrap at every ``done``, the
  time limit's included;
* ``min_scale=1e-8``: its scale is softplus + 1e-8;
* ``head_tensors="per_output"``: its policy head is three output layers (degrees of
  freedom, location, scale), each a weight and a bias with their own t-momentum statistics.

The remaining differences (the multivariate student-t of more than one action dimension,
the random streams) are listed in docs/testbed.md."""


_CHOICE_FIELDS = (
    ("td_units", TD_UNITS),
    ("entropy_density", ENTROPY_DENSITIES),
    ("critic_signal", CRITIC_SIGNALS),
    ("trace_divergence", TRACE_DIVERGENCES),
    ("amsgrad_max", AMSGRAD_MAXES),
    ("policy_gradient", POLICY_GRADIENTS),
    ("time_limit", TIME_LIMITS),
    ("head_tensors", HEAD_TENSORS),
    ("engine", ENGINES),
)
"""The fields of :class:`OnlineConfig` that take one of a few names, with those names."""


@dataclass(frozen=True)
class OnlineConfig:
    """Settings of the paper's online actor-critic learner (Algorithm 1, Table I).

    Defaults are the paper's. Where the paper is silent, they are :data:`DEFAULT_CHOICES`:
    the author's public test bed (:data:`AUTHOR_CHOICES`) except for the two choices the
    ablation measured to make the learner worse (docs/online-learner.md).
    ``OnlineConfig(**AUTHOR_CHOICES)`` takes all of the author's choices,
    ``OnlineConfig(**BASELINE_CHOICES)`` none, ``OnlineConfig(**TESTBED)`` is the author's
    test bed's learner. The history of the defaults is in CHANGELOG.md.
    Optimiser constants the paper leaves at "default" are documented in
    :class:`pporpe.online.torch_engine.optim.TDAmsProp`.
    """

    method: Method = "rpe"
    """Surrogate: ``"ppo"`` (clip), ``"rb"`` (rollback), ``"rpe"`` (relative Pearson) or
    ``"spo"`` (Simple Policy Optimization, eps only)."""
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
    amsgrad_decay: float = 0.99999
    """Decay of the AMSGrad running maximum, in [0, 1] (1 = AMSGrad, 0 = none): 0.99999 as
    the author's optimiser."""
    amsgrad_max: AmsgradMax = "raw"
    """td-AmsProp's running maximum: over the raw second moment, bias-corrected after
    (``"raw"``, the author's optimiser, default) or over the bias-corrected one
    (``"bias_corrected"``)."""
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
    td_units: TDUnits = "unscaled"
    """Units of delta in the TD regulariser: ``"unscaled"`` (default, as the author's test
    bed), beta_TD * (delta / (1 - gamma))^2, or ``"scaled"``, beta_TD *
    delta^2 with delta in scaled-reward units, 1 / (1 - gamma)^2 = 10^4 times weaker at
    gamma = 0.99."""
    entropy_density: EntropyDensity = "action"
    """Log-density in the entropy regulariser: of the bounded action, the map's Jacobian
    included (``"action"``, default), or of the pre-map variable u
    (``"pre_squash"``, the author's test bed: its bonus does not penalise
    a location in the map's saturated tails, and on Swingup its policies drive the cart
    at the action bounds)."""
    critic_signal: CriticSignal = "td"
    """What trains the value network: the TD error (``"td"``, default:
    delta * grad V), or the actor's signal and weight (``"actor"``, the author's test bed:
    A * rho_dagger * grad V with rho_dagger = obj(rho, A) / A detached,
    the surrogate's effective ratio; the test bed trains both networks with
    -A * rho_w * (V + log pi))."""
    trace_divergence: TraceDivergence = "analytic"
    """Divergence that cuts the adaptive traces: ``"analytic"`` (default, as the author's
    test bed), KL(pi || pi_b) between the two policies at s_t (a normal-gamma
    approximation for the student-t) + (V - V_b)^2 / 2, or ``"sample"``,
    (rho - 1 - log rho) + (V - V_b)^2 at the sampled action."""
    policy_gradient: PolicyGradient = "surrogate"
    """How the surrogate enters the actor's gradient: the gradient of the surrogate
    objective, -sigma grad obj(rho, sigma) per unit of A (``"surrogate"``, default, the
    paper's eq.), or the score weighted by the surrogate's effective ratio,
    -rho_dagger grad log pi with rho_dagger = sigma obj(rho, sigma) detached
    (``"weighted_score"``, the author's test bed: for PPO, w = sigma min(sigma rho,
    sigma clip(rho, 1 - eps, 1 + eps)), which where the clip is active weights the score
    by 1 +- eps instead of zeroing it). The two agree wherever obj(rho, sigma) = sigma rho."""
    time_limit: TimeLimit = "bootstrap"
    """The TD target at a time limit (an episode truncated by the task): bootstrap from
    V(s_{t+1}) as at any other step (``"bootstrap"``, default), or drop the bootstrap as at
    a termination (``"terminal"``, the author's test bed, whose ``done`` includes it)."""
    reward_scale: float | None = None
    """Multiplier of rewards; ``None`` means 1 - gamma (the author's test bed)."""
    layers: int = 5
    """Hidden layers L of each network, in [1, 64]."""
    units: int = 100
    """Units N per hidden layer, in [1, 4096], with units * units * layers at most 2**24
    (:mod:`pporpe.limits`)."""
    layer_norm: bool = True
    """LayerNorm after each hidden linear layer."""
    layer_norm_affine: bool = False
    """Learn LayerNorm's scale and shift (True), or keep them at 1 and 0
    (False, default), as the author's networks, which have none."""
    activation: Activation = "swish"
    """Hidden activation: ``"swish"`` (x*sigmoid(x)), ``"relu"`` or ``"tanh"``."""
    policy: PolicyKind = "student_t"
    """Policy distribution: diagonal ``"student_t"`` (paper) or ``"normal"``."""
    min_scale: float = 1e-3
    """Floor of the policy's scale, scale = softplus(raw) + min_scale, a finite number
    > 0 (the author's test bed: 1e-8)."""
    head_tensors: HeadTensors = "joint"
    """The policy's output layer for the optimiser's t-momentum, which weighs each
    parameter tensor by its own statistics: one weight and one bias (``"joint"``, default),
    or one of each per part of the output, location, scale and degrees of freedom
    (``"per_output"``, the author's test bed, whose head is three layers). The network
    computes the same either way."""
    engine: Engine = "fused"
    """Implementation of the step: one numba kernel per step over all the members
    (``"fused"``, default, pporpe.online.fused_engine: 3-14x faster than torch, compiled
    once and cached on disk) or batched torch operations (``"torch"``,
    pporpe.online.torch_engine, the reference the kernel is tested against). The two
    agree to float rounding, not bitwise, so this is part of a run's identity."""
    compile: bool = True
    """With ``engine="torch"``: compile its elementwise update (traces, td-AmsProp,
    t-soft) with ``torch.compile``, about 2x faster per step on this project's 2-core CPU
    after a compile of a few seconds per population shape. Compiled and eager updates
    agree to float rounding, not bitwise, so this is part of a run's identity. The fused
    engine ignores it."""

    def __post_init__(self) -> None:
        validate_surrogate_fields(self)
        for name in ("gamma", "lr", "opt_eps", "k_dof", "tau", "nu"):
            require(is_real(getattr(self, name)), name, getattr(self, name), "a number")
        require(0.0 <= self.gamma < 1.0, "gamma", self.gamma, "in [0, 1)")
        self._validate_optimiser()
        self._validate_target_traces_and_rewards()
        validate_network_fields(self)
        require(
            is_real(self.min_scale) and 0.0 < self.min_scale < math.inf,
            "min_scale",
            self.min_scale,
            "a finite number > 0",
        )
        for name in ("compile", "layer_norm_affine"):
            value = getattr(self, name)
            require(isinstance(value, bool), name, value, "True or False")
        for name, allowed in _CHOICE_FIELDS:
            value = getattr(self, name)
            require(value in allowed, name, value, f"one of {list(allowed)}")

    def _validate_optimiser(self) -> None:
        """lr, opt_betas, opt_eps, k_dof and amsgrad_decay are in their ranges."""
        require(0.0 < self.lr < math.inf, "lr", self.lr, "a finite number > 0")
        require(
            isinstance(self.opt_betas, tuple | list)
            and len(self.opt_betas) == 2
            and all(is_real(b) and 0.0 <= b < 1.0 for b in self.opt_betas),
            "opt_betas",
            self.opt_betas,
            "two numbers in [0, 1)",
        )
        require(self.opt_eps > 0.0, "opt_eps", self.opt_eps, "> 0")
        require(self.k_dof > 0.0, "k_dof", self.k_dof, "> 0 (inf allowed)")
        require(
            is_real(self.amsgrad_decay) and 0.0 <= self.amsgrad_decay <= 1.0,
            "amsgrad_decay",
            self.amsgrad_decay,
            "in [0, 1]",
        )

    def _validate_target_traces_and_rewards(self) -> None:
        """tau, nu, lambdas, kappa, the regulariser weights and reward_scale are in range."""
        require(0.0 < self.tau <= 1.0, "tau", self.tau, "in (0, 1]")
        require(self.nu > 0.0, "nu", self.nu, "> 0 (inf allowed)")
        require(
            isinstance(self.lambdas, tuple | list)
            and len(self.lambdas) == 2
            and all(is_real(x) and 0.0 <= x <= 1.0 for x in self.lambdas),
            "lambdas",
            self.lambdas,
            "two numbers in [0, 1]",
        )
        for name in ("kappa", "beta_td", "beta_de"):
            v = getattr(self, name)
            require(is_real(v) and 0.0 <= v < math.inf, name, v, "a finite number >= 0")
        require(
            self.reward_scale is None
            or (is_real(self.reward_scale) and 0.0 < self.reward_scale < math.inf),
            "reward_scale",
            self.reward_scale,
            "None or a finite number > 0",
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
    """Seed of the networks, the sampling and the environment, in [0, 2**32 - 1]
    (:data:`~pporpe.limits.MAX_SEED`)."""
    episodes: int | None = 200
    """Training length in episodes, in [1, 10**6] (:data:`~pporpe.limits.MAX_EPISODES`);
    ``None`` when ``steps`` sets it."""
    steps: int | None = None
    """Training length in environment steps, in [1, 10**9]
    (:data:`~pporpe.limits.MAX_STEPS`); ``None`` when ``episodes`` sets it."""
    checkpoint_every: int = 10
    """Episodes between two checkpoints (>= 1); also one at the end, and by time whatever
    the count (mid-episode): 30 s into training, 1 min later, then every 2 min."""
    eval_episodes: int = 50
    """Test episodes after training, in [0, 10**4] (the paper's score is the median of 50)."""
    learner: OnlineConfig = field(default_factory=OnlineConfig)
    """Settings of the online learner."""

    def __post_init__(self) -> None:
        require(isinstance(self.env, str) and bool(self.env), "env", self.env, "a task name")
        check_int_in("seed", self.seed, 0, MAX_SEED)
        require(
            (self.episodes is None) != (self.steps is None),
            "episodes/steps",
            (self.episodes, self.steps),
            "exactly one of the two set",
        )
        if self.episodes is not None:
            check_int_in("episodes", self.episodes, 1, MAX_EPISODES)
        if self.steps is not None:
            check_int_in("steps", self.steps, 1, MAX_STEPS)
        check_int_in("checkpoint_every", self.checkpoint_every, 1, MAX_STEPS)
        check_int_in("eval_episodes", self.eval_episodes, 0, MAX_EVAL_EPISODES)
        require(isinstance(self.learner, OnlineConfig), "learner", self.learner, "an OnlineConfig")
