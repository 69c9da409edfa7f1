r"""Advantage signals, pure tensor functions, with termination and truncation kept apart.

* :func:`compute_gae`: GAE(lambda) over ``[T, n_envs]`` rollouts (the batch learner).
* :func:`td_error` and :func:`regularized_advantage`: the online learner's one-step TD
  error and the advantage it feeds to the surrogate, with the TD and entropy regularisers
  folded in.

In every function a *termination* (a true end of the task) is not bootstrapped and a
*truncation* (a time limit) is, from the value of the state it reached.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["compute_gae", "regularized_advantage", "td_error"]


def compute_gae(
    rewards: Tensor,
    values: Tensor,
    next_values: Tensor,
    terminated: Tensor,
    truncated: Tensor,
    gamma: float,
    gae_lambda: float,
    bootstrap_truncated: bool = True,
) -> tuple[Tensor, Tensor]:
    r"""GAE(lambda) advantages and lambda-returns of ``[T, n_envs]`` rollouts.

    For step t of one sub-environment, with ``next_values[t]`` the value of the state
    reached by that step (the final observation when the episode ended there):

    .. math:: \delta_t = r_t + \gamma\,(1 - \mathrm{term}_t)\,V'_t - V_t, \qquad
              A_t = \delta_t + \gamma\lambda\,(1 - \mathrm{term}_t)(1 - \mathrm{trunc}_t)\,A_{t+1}

    with A_T = 0: a termination is not bootstrapped, a truncation is (by V of the final
    observation), and either ends the lambda chain. With ``bootstrap_truncated=False`` a
    truncation is treated like a termination. Returns ``(advantages, advantages + values)``.
    """
    term = terminated.to(values.dtype)
    trunc = truncated.to(values.dtype)
    stop = term if bootstrap_truncated else torch.clamp(term + trunc, max=1.0)
    delta = rewards + gamma * (1.0 - stop) * next_values - values
    carry = gamma * gae_lambda * (1.0 - term) * (1.0 - trunc)
    adv = torch.empty_like(delta)
    last = torch.zeros_like(delta[0])
    for t in range(delta.shape[0] - 1, -1, -1):
        last = torch.addcmul(delta[t], carry[t], last, out=adv[t])
    return adv, adv + values


def td_error(reward: Tensor, next_value: Tensor, value: Tensor, discount: Tensor) -> Tensor:
    r"""One-step TD error :math:`\delta = r + d\,V(s_{t+1}) - V(s_t)`.

    ``discount`` is gamma after a non-terminal step (a time-limit truncation included) and
    0 after a termination; ``reward`` is already scaled (the online learner multiplies
    rewards by 1 - gamma).
    """
    return reward + discount * next_value - value


def regularized_advantage(
    delta: Tensor,
    log_prob: Tensor,
    one_minus_gamma: float | Tensor,
    beta_td: float | Tensor,
    beta_de: float | Tensor,
    td_scale: float | Tensor = 1.0,
) -> Tensor:
    r"""The online learner's advantage with TD and entropy regularisation folded in.

    .. math:: A = \delta - (1 - \gamma)\,(\beta_{TD}\,(c\,\delta)^2
              + \beta_{DE}\,\log\pi(a|s))

    ``td_scale`` c sets the units of the TD error in the penalty: 1 squares delta as it is
    (in scaled-reward units), 1 / (1 - gamma) squares the unscaled TD error (the author's
    test bed).

    The entropy term (weight ``beta_de``, SAC-style) rewards unlikely actions; the TD term
    (weight ``beta_td``, after Parisi et al. 2019) penalises large TD errors. ``log_prob``
    is the log-density of the action taken. ``one_minus_gamma`` is 1 - gamma, passed as
    such (computed in float64 where gamma is a Python float); the weights may be
    per-member ``[K]`` tensors.
    """
    td = delta * td_scale
    return delta - one_minus_gamma * (beta_td * td * td + beta_de * log_prob)
