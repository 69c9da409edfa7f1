"""PPO-RPE, PPO-RB and SPO inside Stable-Baselines3: ``from pporpe.sb3 import PPO``.

:class:`PPO` is ``stable_baselines3.PPO`` with three more arguments, so that an SB3 (or
rl-zoo3) script switches surrogate with one word::

    from pporpe.sb3 import PPO            # instead of: from stable_baselines3 import PPO

    model = PPO("MlpPolicy", "Pendulum-v1", surrogate="rpe", seed=0)
    model.learn(10_000)
    model.save("ppo_rpe_pendulum")
    model = PPO.load("ppo_rpe_pendulum")

* ``surrogate``: ``"ppo"`` (clip, SB3's own loss), ``"rb"`` (rollback), ``"rpe"``
  (relative Pearson divergence) or ``"spo"`` (Simple Policy Optimization, Xie et al. 2025),
  computed by :func:`pporpe.surrogates.surrogate_objective`;
* ``eta``: PPO-RB's rollback slope (eq. (5) of arXiv 2010.03290), used by ``"rb"``;
* ``rpe_beta``: PPO-RPE's mixture ratio beta (eq. (8)), used by ``"rpe"``.

SB3's ``clip_range`` is the paper's eps for all four (a float, a schedule or rl-zoo3's
``"lin_<x>"`` string; a schedule that reaches 0, like ``lin_0.2`` at the last update, is
floored at 1e-8). The three arguments and ``clip_range`` are checked at construction and
again by ``load`` (after ``custom_objects``), each error naming the argument. Every
other argument, the rollout collection, the value loss, advantage normalisation, gradient
clipping, ``target_kl`` early stopping, ``save``/``load`` and the logger are SB3's. With
``surrogate="ppo"`` training is bit-identical to ``stable_baselines3.PPO`` for the same
seed (tested). Besides SB3's ``train/*`` keys the logger gets
``train/rpe_divergence`` (eq. (9), Monte-Carlo over the minibatch, with ``rpe_beta``),
``train/regularization`` (the mean of sigma*(rho - rho_dagger), the paper's Fig. 5) and
``train/past_threshold_fraction``.

Needs the optional extra: ``pip install "pporpe[sb3]"``.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from torch.nn import functional as F

from .config import is_real
from .surrogates import METHODS, regularization_amount, rpe_divergence, surrogate_objective
from .zoo_literal import read_zoo_literal

try:
    from gymnasium import spaces
    from stable_baselines3 import PPO as _SB3PPO
    from stable_baselines3.common.utils import explained_variance
except ImportError as exc:  # pragma: no cover - exercised only without the extra
    raise ImportError(
        'pporpe.sb3 needs Stable-Baselines3: pip install "pporpe[sb3]" '
        "(or pip install stable-baselines3)"
    ) from exc

__all__ = [
    "EPS_FLOOR",
    "PPO",
    "SCHEDULE_KEYS",
    "SCHEDULE_POINTS",
    "ZOO_NON_ARGS",
    "ZooLinearSchedule",
    "zoo_kwargs",
    "zoo_model",
]

EPS_FLOOR = 1e-8
"""Smallest eps passed to the surrogates (they need eps > 0; a clip schedule may reach 0)."""


def _check_args(surrogate: Any, eta: Any, rpe_beta: Any, clip_range: Any) -> None:
    """Validate the three pporpe arguments and ``clip_range`` (a number, a schedule or an
    rl-zoo3 ``lin_<x>`` string) before any work, each error naming the argument."""
    if surrogate not in METHODS:
        raise ValueError(
            f"`surrogate` must be one of {', '.join(map(repr, METHODS))}; got {surrogate!r}"
        )
    if not (is_real(eta) and 0.0 <= eta < math.inf):
        raise ValueError(f"`eta` must be a finite number >= 0 (PPO-RB's slope); got {eta!r}")
    if not (is_real(rpe_beta) and 0.0 <= rpe_beta <= 1.0):
        raise ValueError(f"`rpe_beta` must be a number in [0, 1]; got {rpe_beta!r}")
    if isinstance(clip_range, str):
        clip_range = _schedule("clip_range", clip_range)
        if isinstance(clip_range, str):
            raise ValueError(
                f"`clip_range` (the paper's eps) must be in (0, 1) for pporpe's surrogates, "
                f"a schedule or an rl-zoo3 'lin_<x>' string; got {clip_range!r}"
            )
    _check_rpe_threshold(surrogate, rpe_beta, _largest_eps(clip_range), _shown(clip_range))


def _check_rpe_threshold(surrogate: Any, rpe_beta: float, eps: float, shown: str) -> None:
    """PPO-RPE's threshold exists: ``rpe_beta * (1 + eps) < 1`` (``shown``: the clip_range)."""
    if surrogate == "rpe" and rpe_beta * (1.0 + eps) >= 1.0:
        raise ValueError(
            f"`rpe_beta` * (1 + `clip_range`) must be < 1 for PPO-RPE's threshold to "
            f"exist; got rpe_beta={rpe_beta!r}, clip_range={shown}: with this "
            f"clip_range rpe_beta must be < {1.0 / (1.0 + eps):.6g}"
        )


SCHEDULE_POINTS = 11
"""A ``clip_range`` schedule is checked at this many evenly spaced ``progress_remaining``
values from 1 (the first update) to 0 (the last), and again at every update."""


def _shown(clip_range: Any) -> str:
    """``clip_range`` as an error message shows it (``0.2``, ``lin_0.2``)."""
    return repr(clip_range) if is_real(clip_range) else str(clip_range)


def _largest_eps(clip_range: Any) -> float:
    """The largest eps ``clip_range`` gives: a number in (0, 1), or a schedule whose values
    are in [0, 1) (0 is floored at :data:`EPS_FLOOR`), else a ``ValueError`` naming it."""
    schedule = getattr(clip_range, "value_schedule", clip_range)  # SB3's FloatSchedule
    if isinstance(schedule, ZooLinearSchedule):
        if not (is_real(schedule.start) and 0.0 < schedule.start < 1.0):
            raise ValueError(
                f"`clip_range` (the paper's eps) {schedule} goes from {schedule.start!r} "
                f"to 0; its start must be in (0, 1) for pporpe's surrogates"
            )
        return float(schedule.start)
    if not callable(schedule):
        if not (is_real(schedule) and 0.0 < schedule < 1.0):
            raise ValueError(
                f"`clip_range` (the paper's eps) must be in (0, 1) for pporpe's surrogates; "
                f"got {clip_range!r}"
            )
        return float(schedule)
    values = [
        _scheduled_eps(schedule, 1.0 - i / (SCHEDULE_POINTS - 1)) for i in range(SCHEDULE_POINTS)
    ]
    return max(values)


def _scheduled_eps(schedule: Callable[[float], Any], progress: float) -> float:
    """The schedule's eps at ``progress`` remaining, in [0, 1), else a ``ValueError``."""
    try:
        value = schedule(progress)
    except Exception as exc:
        raise ValueError(
            f"`clip_range` (a schedule) failed at progress_remaining={progress:g}: {exc}"
        ) from None
    if isinstance(value, np.floating | np.integer):
        value = value.item()
    if not (is_real(value) and 0.0 <= value < 1.0):
        raise ValueError(
            f"`clip_range` (a schedule, the paper's eps) must give values in [0, 1) for "
            f"pporpe's surrogates; got {value!r} at progress_remaining={progress:g}"
        )
    return float(value)


class PPO(_SB3PPO):
    """``stable_baselines3.PPO`` whose policy loss is PPO's, PPO-RB's, PPO-RPE's or SPO's.

    Args:
        policy, env: as for ``stable_baselines3.PPO``.
        surrogate: ``"ppo"`` (default, SB3's clipped loss), ``"rb"``, ``"rpe"`` or ``"spo"``.
        eta: PPO-RB's rollback slope, a finite number >= 0 (default 0.3; ``"rb"`` only).
        rpe_beta: PPO-RPE's mixture ratio beta in [0, 1] with
            ``rpe_beta * (1 + clip_range) < 1`` (default 0.5; ``"rpe"`` only).
        *args, **kwargs: every other ``stable_baselines3.PPO`` argument, unchanged
            (``clip_range`` is eps), except that ``learning_rate``, ``clip_range`` and
            ``clip_range_vf`` also take rl-zoo3's ``"lin_<x>"`` strings.

    Raises:
        ValueError: a bad ``surrogate``, ``eta``, ``rpe_beta`` or ``clip_range``, naming it,
            before any environment or network is built; by ``load`` too, before the policy
            is built, with the saved values and ``custom_objects`` applied.
    """

    def __init__(
        self,
        policy: Any,
        env: Any,
        *args: Any,
        surrogate: str = "ppo",
        eta: float = 0.3,
        rpe_beta: float = 0.5,
        **kwargs: Any,
    ) -> None:
        for key in SCHEDULE_KEYS:  # rl-zoo3's lin_<x> strings
            if key in kwargs:
                kwargs[key] = _schedule(key, kwargs[key])
        bound = inspect.signature(_SB3PPO.__init__).bind_partial(None, policy, env, *args, **kwargs)
        _check_args(surrogate, eta, rpe_beta, bound.arguments.get("clip_range", 0.2))
        self.surrogate = surrogate
        self.eta = float(eta)
        self.rpe_beta = float(rpe_beta)
        super().__init__(policy, env, *args, **kwargs)

    def _setup_model(self) -> None:
        """SB3's, after checking the pporpe arguments again: ``load`` reaches here with the
        saved values, ``custom_objects`` and its keyword arguments applied, before it builds
        the policy."""
        _check_args(self.surrogate, self.eta, self.rpe_beta, self.clip_range)
        self.clip_range = _schedule("clip_range", self.clip_range)
        self.eta, self.rpe_beta = float(self.eta), float(self.rpe_beta)
        super()._setup_model()

    # -- one update ---------------------------------------------------------------------
    def _minibatch(
        self, data: Any, eps: float, clip_vf: float | None
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The loss of one minibatch and its (detached) diagnostics; no ``.item()`` here."""
        actions = data.actions
        if isinstance(self.action_space, spaces.Discrete):
            actions = actions.long().flatten()
        values, log_prob, entropy = self.policy.evaluate_actions(data.observations, actions)
        values = values.flatten()
        adv = data.advantages
        if self.normalize_advantage and len(adv) > 1:
            adv = (adv - adv.mean()) / (adv.std() + 1e-8)
        log_ratio = log_prob - data.old_log_prob
        ratio = torch.exp(log_ratio)
        params: dict[str, Any] = {"eps": eps, "beta": self.rpe_beta, "eta": self.eta}
        method: Any = self.surrogate
        policy_loss = -surrogate_objective(method, ratio, adv, **params).mean()
        if clip_vf is not None:  # the value moves at most clip_vf from the rollout's value
            values = data.old_values + torch.clamp(values - data.old_values, -clip_vf, clip_vf)
        value_loss = F.mse_loss(data.returns, values)
        entropy_loss = -torch.mean(-log_prob) if entropy is None else -torch.mean(entropy)
        loss = policy_loss + self.ent_coef * entropy_loss + self.vf_coef * value_loss
        with torch.no_grad():
            reg = regularization_amount(method, ratio, adv, **params)
            metrics = {
                "policy_gradient_loss": policy_loss.detach(),
                "value_loss": value_loss.detach(),
                "entropy_loss": entropy_loss.detach(),
                "clip_fraction": ((ratio - 1.0).abs() > eps).float().mean(),
                "approx_kl": ((ratio - 1.0) - log_ratio).mean(),
                "rpe_divergence": rpe_divergence(ratio, self.rpe_beta),
                "regularization": reg.amount.mean(),
                "past_threshold_fraction": reg.fraction_past_threshold,
            }
        return loss, metrics

    def train(self) -> None:
        """n_epochs passes over the rollout buffer in minibatches, with pporpe's surrogate."""
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.optimizer)
        progress = self._current_progress_remaining
        clip_range = _scheduled_eps(self.clip_range, progress)  # type: ignore[arg-type]
        eps = max(clip_range, EPS_FLOOR)
        shown = f"{eps!r} at progress_remaining={progress:g}"
        _check_rpe_threshold(self.surrogate, self.rpe_beta, eps, shown)
        vf_schedule = self.clip_range_vf
        clip_vf = None if vf_schedule is None else float(vf_schedule(progress))  # type: ignore[operator]
        history: dict[str, list[float]] = {}
        loss = torch.zeros(())
        stop = False
        for epoch in range(self.n_epochs):
            kls: list[float] = []
            for data in self.rollout_buffer.get(self.batch_size):
                loss, metrics = self._minibatch(data, eps, clip_vf)
                values = {k: float(v) for k, v in metrics.items()}
                kls.append(values.pop("approx_kl"))
                for key, value in values.items():
                    history.setdefault(key, []).append(value)
                if self.target_kl is not None and kls[-1] > 1.5 * self.target_kl:
                    stop = True
                    if self.verbose >= 1:
                        print(f"Early stopping at epoch {epoch}: approx_kl {kls[-1]:.2f}")
                    break
                self.policy.optimizer.zero_grad()
                loss.backward()
                torch.nn.utils.clip_grad_norm_(self.policy.parameters(), self.max_grad_norm)
                self.policy.optimizer.step()
            history["approx_kl"] = kls
            self._n_updates += 1
            if stop:
                break
        self._log_update(history, loss, clip_range, clip_vf)

    def _log_update(
        self,
        history: dict[str, list[float]],
        loss: torch.Tensor,
        clip_range: float,
        clip_vf: float | None,
    ) -> None:
        """SB3's ``train/*`` keys, plus pporpe's regularisation diagnostics."""
        record: Callable[..., None] = self.logger.record
        for key, values in history.items():
            record(f"train/{key}", float(np.mean(values)) if values else float("nan"))
        buf = self.rollout_buffer
        record(
            "train/explained_variance",
            explained_variance(buf.values.flatten(), buf.returns.flatten()),
        )
        record("train/loss", float(loss.detach()))
        if hasattr(self.policy, "log_std"):
            record("train/std", float(torch.exp(self.policy.log_std.detach()).mean()))
        record("train/n_updates", self._n_updates, exclude="tensorboard")
        record("train/clip_range", clip_range)
        if clip_vf is not None:
            record("train/clip_range_vf", clip_vf)
        record("train/surrogate", self.surrogate, exclude=("tensorboard", "csv"))


ZOO_NON_ARGS = ("n_envs", "n_timesteps", "normalize", "policy", "env_wrapper", "frame_stack")
"""Keys of an rl-zoo3 hyperparameter entry that describe the experiment, not PPO's arguments
(only ``n_envs``, ``n_timesteps``, ``normalize`` and ``policy`` are acted on by
:func:`zoo_model`; a wrapper or frame stack is refused there)."""


class ZooLinearSchedule:
    """rl-zoo3's ``lin_<start>``: ``start * progress_remaining``, from ``start`` at the first
    update to 0 at the end (a class rather than a closure, so that a check can read
    ``start``)."""

    def __init__(self, start: float) -> None:
        self.start = start

    def __call__(self, progress_remaining: float) -> float:
        return progress_remaining * self.start

    def __repr__(self) -> str:
        return f"lin_{self.start!r}"


SCHEDULE_KEYS = ("learning_rate", "clip_range", "clip_range_vf")
"""The arguments that take an rl-zoo3 ``lin_<x>`` string (a :class:`ZooLinearSchedule`)."""


def _schedule(key: str, value: Any) -> Any:
    """``value``, or the :class:`ZooLinearSchedule` of a ``lin_<x>`` string."""
    if isinstance(value, str) and value.startswith("lin_"):
        try:
            start = float(value[4:])
        except ValueError:
            start = math.nan
        if not math.isfinite(start):
            raise ValueError(f"`{key}`: a schedule is 'lin_<number>'; got {value!r}")
        return ZooLinearSchedule(start)
    return value


def zoo_kwargs(hyperparams: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """Split an rl-zoo3 hyperparameter entry into ``(PPO keyword arguments, experiment)``.

    ``lin_<x>`` strings for ``learning_rate``, ``clip_range`` and ``clip_range_vf`` become
    linear schedules (:class:`ZooLinearSchedule`), and a ``policy_kwargs`` string (rl-zoo3
    writes e.g. ``"dict(net_arch=[64, 64], activation_fn=nn.Tanh)"``) is read as data by
    :func:`pporpe.zoo_literal.read_zoo_literal`, never evaluated: ``dict(...)`` and
    ``{...}``, lists, tuples, numbers, strings, ``True``/``False``/``None`` and a fixed set
    of ``nn.<activation>`` names; anything else raises ``ValueError`` naming
    ``policy_kwargs``. ``surrogate``, ``eta`` and ``rpe_beta`` may be in the entry like any
    other argument. The experiment part holds :data:`ZOO_NON_ARGS` that were present.
    """
    kwargs = {k: v for k, v in hyperparams.items() if k not in ZOO_NON_ARGS}
    experiment = {k: hyperparams[k] for k in ZOO_NON_ARGS if k in hyperparams}
    for key in SCHEDULE_KEYS:
        if key in kwargs:
            kwargs[key] = _schedule(key, kwargs[key])
    pk = kwargs.get("policy_kwargs")
    if isinstance(pk, str):
        kwargs["policy_kwargs"] = read_zoo_literal(pk, "policy_kwargs")
        if not isinstance(kwargs["policy_kwargs"], dict):
            raise ValueError(f"`policy_kwargs` must be a dict(...) of keywords; got {pk!r}")
    return kwargs, experiment


def zoo_model(
    env_id: str, hyperparams: dict[str, Any], seed: int | None = None, **overrides: Any
) -> tuple[PPO, int | None]:
    """A :class:`PPO` built from an rl-zoo3 hyperparameter entry, and its ``n_timesteps``.

    ``n_envs`` sub-environments (default 1) in a ``DummyVecEnv``, wrapped in
    ``VecNormalize`` when ``normalize`` is true (or a dict of its arguments), as rl-zoo3
    does; ``overrides`` win over the entry (e.g. ``surrogate="rpe"``)::

        model, steps = zoo_model("Pendulum-v1", {"n_envs": 4, "n_timesteps": 1e5,
                                                 "n_steps": 1024, "gamma": 0.9},
                                 seed=0, surrogate="rpe")
        model.learn(steps)
    """
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecNormalize

    kwargs, experiment = zoo_kwargs({**hyperparams, **overrides})
    for key in ("env_wrapper", "frame_stack"):
        if experiment.get(key):
            raise ValueError(f"`{key}` is not supported by zoo_model; wrap the env yourself")
    n_envs = experiment.get("n_envs", 1)
    if not (isinstance(n_envs, int) and n_envs >= 1):
        raise ValueError(f"`n_envs` must be an int >= 1; got {n_envs!r}")
    # Validate PPO's own arguments before any environment is built.
    _check_args(
        kwargs.get("surrogate", "ppo"),
        kwargs.get("eta", 0.3),
        kwargs.get("rpe_beta", 0.5),
        kwargs.get("clip_range", 0.2),
    )
    env: Any = make_vec_env(env_id, n_envs=n_envs, seed=seed)
    normalize = experiment.get("normalize", False)
    if normalize:
        env = VecNormalize(env, **(normalize if isinstance(normalize, dict) else {}))
    steps = experiment.get("n_timesteps")
    model = PPO(experiment.get("policy", "MlpPolicy"), env, seed=seed, **kwargs)
    return model, None if steps is None else int(steps)
