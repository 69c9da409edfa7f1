r"""Surrogate objectives of PPO, PPO-RB, PPO-RPE and SPO as pure tensor functions.

Every function here works on tensors of any batch shape, in float32 or float64,
does no reduction unless it says so, never calls ``.item()`` and never touches
global state. Equation numbers are those printed in the paper, T. Kobayashi, "Proximal
Policy Optimization with Relative Pearson Divergence" (arXiv:2010.03290); the label in
parentheses is the equation's name, listed with all others in ``docs/glossary.md``:

* eq. (5) (``ratio_ppo``), Sec. II-B: surrogate density ratio of PPO (eta = 0) and
  PPO-RB (eta > 0); eq. (6) (``loss_ppo``) is their loss
* eq. (9) (``div_rpe``), Sec. II-C: relative Pearson divergence PE_beta
* eq. (11) (``loss_rpe``), Sec. III-B: PPO-RPE objective
  rho*A - C*(1-beta+beta*rho)*(rho_beta-1)^2
* eq. (12) (``grad_rpe``), Sec. III-C: its derivative with respect to rho, the
  surrogate advantage A~
* eqs. (13)-(14) (``thr_rb``, ``thr_r``), Sec. III-D: thresholds on rho_beta and on
  the raw ratio rho
* eq. (15) (``mag_rpe``), Sec. III-D: threshold-based gain C
* eq. (16) (``grad_rpe_thre``), Sec. III-D, and Algorithm 1: A~ with that gain
  substituted, as printed (see ``docs/erratum.md``)

SPO, the fourth surrogate, is not in that paper: it is the objective
rho*A - |A|/(2 eps)*(rho-1)^2 of Z. Xie et al., "Simple Policy Optimization" (ICML 2025,
arXiv:2401.16025), whose maximiser over rho is 1 + sigma*eps (``docs/spo.md``).

Conventions shared by all functions:

* ``ratio`` is rho = pi(a|s) / pi_b(a|s) for actions sampled from the baseline
  policy pi_b; ``adv`` is the advantage A of the same samples, broadcastable
  against ``ratio``.
* sigma = sign(A).
* The advantage and the gain C are constants for autograd: no gradient flows into
  them (C depends on A through eq. (15); see ``docs/erratum.md``).
* Objectives are to be *maximised*; a loss is their negative mean.

See ``docs/erratum.md`` for why :func:`rpe_surrogate_advantage` implements the
derived form of eq. (12) (``grad_rpe``) with the gain of eq. (15) (``mag_rpe``) rather
than the printed eq. (16) (``grad_rpe_thre``), Sec. III-D.
"""

from __future__ import annotations

import math
from typing import Literal, NamedTuple, get_args

import torch
from torch import Tensor

__all__ = [
    "METHODS",
    "Method",
    "RPEForm",
    "Regularization",
    "check_surrogate_params",
    "ratio_thresholds",
    "regularization_amount",
    "relative_ratio",
    "rpe_divergence",
    "rpe_gain",
    "rpe_surrogate_advantage",
    "spo_surrogate_advantage",
    "surrogate_loss",
    "surrogate_objective",
]

Method = Literal["ppo", "rb", "rpe", "spo"]
"""Name of a surrogate: ``"ppo"`` (clip), ``"rb"`` (rollback), ``"rpe"`` (relative Pearson),
``"spo"`` (Simple Policy Optimization's quadratic penalty)."""

METHODS: tuple[Method, ...] = get_args(Method)

RPEForm = Literal["derived", "printed"]
"""Which A~ of PPO-RPE: the exact derivative (default) or the paper's printed eq. (16)."""

_RPE_FORMS: tuple[RPEForm, ...] = get_args(RPEForm)


# ----------------------------------------------------------------------------------------
# Parameter validation
# ----------------------------------------------------------------------------------------
def _check_eps(eps: float) -> None:
    if not (isinstance(eps, int | float) and 0.0 < eps < 1.0):
        raise ValueError(f"eps must be a number in the open interval (0, 1); got eps={eps!r}")


def _check_beta(beta: float) -> None:
    if not (isinstance(beta, int | float) and 0.0 <= beta <= 1.0):
        raise ValueError(f"beta must be a number in the closed interval [0, 1]; got beta={beta!r}")


def _check_eps_beta(eps: float, beta: float) -> None:
    _check_eps(eps)
    _check_beta(beta)
    if beta * (1.0 + eps) >= 1.0:
        raise ValueError(
            "beta*(1+eps) must be < 1 so that the PPO-RPE threshold on rho exists; "
            f"got beta={beta!r}, eps={eps!r} (beta*(1+eps)={beta * (1.0 + eps):.6g}); "
            f"with eps={eps!r} beta must be < {1.0 / (1.0 + eps):.6g}"
        )


def _check_eta(eta: float) -> None:
    if not (isinstance(eta, int | float) and 0.0 <= eta < math.inf):
        raise ValueError(f"eta must be a finite number >= 0; got eta={eta!r}")


def _check_method(method: str) -> None:
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(map(repr, METHODS))}; got {method!r}")


def check_surrogate_params(
    method: str, eps: float = 0.1, beta: float = 0.5, eta: float = 0.3
) -> None:
    """Validate the parameters of a surrogate, raising ``ValueError`` naming the bad one.

    Only the parameters that ``method`` uses are checked beyond ``eps``: ``beta`` for
    ``"rpe"``, ``eta`` for ``"rb"`` (``"ppo"`` and ``"spo"`` take eps alone). Learners call
    this in their config's ``__post_init__`` so that bad input fails before any work starts.
    """
    _check_method(method)
    _check_eps(eps)
    if method == "rpe":
        _check_eps_beta(eps, beta)
    elif method == "rb":
        _check_eta(eta)


def _sign(adv: Tensor) -> Tensor:
    """sigma = sign(A) with sign(0) := +1 (only used where the value at A = 0 is irrelevant)."""
    return torch.where(adv >= 0, 1.0, -1.0).to(adv.dtype)


# ----------------------------------------------------------------------------------------
# Relative density ratio and the RPE divergence
# ----------------------------------------------------------------------------------------
def relative_ratio(ratio: Tensor, beta: float) -> Tensor:
    r"""Relative density ratio (text below eq. (9) (``div_rpe``), Sec. II-C; Fig. 1).

    .. math:: \rho_\beta = \frac{\pi}{\beta\pi + (1-\beta)\pi_b}
                         = \frac{\rho}{1 - \beta + \beta\rho} \in [0, 1/\beta)

    Args:
        ratio: rho >= 0, any shape.
        beta: mixture ratio in [0, 1]; beta = 0 gives rho itself.
    """
    _check_beta(beta)
    return ratio / (1.0 - beta + beta * ratio)


def rpe_divergence(ratio: Tensor, beta: float, dim: int | tuple[int, ...] | None = None) -> Tensor:
    r"""Monte-Carlo estimate of the relative Pearson divergence (eq. (9) (``div_rpe``), Sec. II-C).

    The mixture policy pi_beta is that of eq. (8) (``pi_beta``); at ``beta = 0`` this is
    the Pearson divergence of eq. (7) (``div_pe``).

    .. math:: \mathrm{PE}_\beta(\pi, \pi_b)
              = \mathbb{E}_{a\sim\pi_\beta}\big[\tfrac12(\rho_\beta(a) - 1)^2\big]
              = \mathbb{E}_{a\sim\pi_b}\big[(1-\beta+\beta\rho)\,\tfrac12(\rho_\beta - 1)^2\big]

    The second form (importance weight pi_beta/pi_b = 1 - beta + beta*rho) lets the
    estimate use ratios of actions sampled from the baseline policy.

    Args:
        ratio: rho of actions sampled from pi_b.
        beta: mixture ratio in [0, 1].
        dim: dimension(s) over which samples are averaged; ``None`` averages all.
    """
    _check_beta(beta)
    weight = 1.0 - beta + beta * ratio
    per_sample = 0.5 * weight * (ratio / weight - 1.0) ** 2
    return per_sample.mean() if dim is None else per_sample.mean(dim=dim)


# ----------------------------------------------------------------------------------------
# PPO-RPE: thresholds, gain and surrogate advantage
# ----------------------------------------------------------------------------------------
def ratio_thresholds(eps: float = 0.1, beta: float = 0.5) -> tuple[float, float]:
    r"""Thresholds of PPO-RPE on rho (eq. (14) (``thr_r``), Sec. III-D), for A < 0 and A > 0.

    .. math:: \rho^\epsilon = 1 + \frac{\sigma\epsilon}{1 - \beta(1 + \sigma\epsilon)}

    They are the images of the symmetric thresholds 1 -/+ eps on rho_beta (eq. (13) (``thr_rb``)).
    With beta = 0.5, eps = 0.1: (0.8182, 1.2222). With beta = 0 they are PPO's 1 -/+ eps.

    Returns:
        ``(low, high)``: the threshold for sigma = -1 and for sigma = +1.
    """
    _check_eps_beta(eps, beta)
    low = 1.0 - eps / (1.0 - beta * (1.0 - eps))
    high = 1.0 + eps / (1.0 - beta * (1.0 + eps))
    return low, high


def rpe_gain(adv: Tensor, eps: float = 0.1, beta: float = 0.5) -> Tensor:
    r"""Threshold-based gain C of the RPE regulariser (eq. (15) (``mag_rpe``), Sec. III-D).

    .. math:: \frac{C}{A} = \frac{1}{\sigma\epsilon\,[\beta\sigma\epsilon
              + 2\{1 - \beta(1+\sigma\epsilon)\}]}
              \quad\Longrightarrow\quad
              C = \frac{|A|}{\epsilon\,[2(1-\beta) - \beta\sigma\epsilon]} \ge 0

    The right form is algebraically equal (sigma^2 = 1, A*sigma = |A|) and never
    divides by A, so C = 0 at A = 0. The result carries no gradient.
    """
    _check_eps_beta(eps, beta)
    adv = adv.detach()
    sigma = _sign(adv)
    return adv.abs() / (eps * (2.0 * (1.0 - beta) - beta * sigma * eps))


def rpe_surrogate_advantage(
    ratio: Tensor,
    adv: Tensor,
    eps: float = 0.1,
    beta: float = 0.5,
    form: RPEForm = "derived",
) -> Tensor:
    r"""Surrogate advantage A~ of PPO-RPE with the threshold gain (eqs. (12) + (15)).

    ``form="derived"`` (default) is eq. (12) (``grad_rpe``, Sec. III-C), the exact
    derivative of the objective of eq. (11) (``loss_rpe``, Sec. III-B) with respect to
    rho (C held constant), with the gain C of eq. (15) (``mag_rpe``, Sec. III-D); the
    derivation and the erratum are in ``docs/erratum.md``:

    .. math:: \tilde A = A - C(\rho_\beta - 1)\Big\{\beta(\rho_\beta - 1)
              + \frac{2(1-\beta)}{1-\beta+\beta\rho}\Big\}

    with C from :func:`rpe_gain`. A~ = A at rho = 1, A~ = 0 exactly at the thresholds
    of :func:`ratio_thresholds`, and A~ has the opposite sign of A beyond them.

    ``form="printed"`` is eq. (16) (``grad_rpe_thre``, Sec. III-D) as printed in the
    paper (and in Algorithm 1), with both inner ``+`` signs turned to ``-``. It also
    vanishes at the threshold but is not the derivative of the RPE objective; it is
    offered only to reproduce that text.
    Its denominator vanishes at beta = 2/(2+3*eps), where it raises ``ValueError``.

    The policy gradient of Algorithm 1 (and eq. (3), ``grad_reg``) is then
    ``-ratio * A~ * grad log pi``.
    """
    if form not in _RPE_FORMS:
        raise ValueError(f"form must be one of {', '.join(map(repr, _RPE_FORMS))}; got {form!r}")
    _check_eps_beta(eps, beta)
    adv = adv.detach()
    mix = 1.0 - beta + beta * ratio
    dev = ratio / mix - 1.0  # rho_beta - 1
    if form == "derived":
        gain = rpe_gain(adv, eps, beta)
        return adv - gain * dev * (beta * dev + 2.0 * (1.0 - beta) / mix)
    sigma = _sign(adv)
    denom_pos = eps * (beta * eps - 2.0 * (1.0 - beta * (1.0 + eps)))
    if abs(denom_pos) < 1e-12:
        raise ValueError(
            "the printed form of eq. (16) (grad_rpe_thre) divides by zero for A > 0 at "
            f"beta=2/(2+3*eps); got beta={beta!r}, eps={eps!r}"
        )
    denom = sigma * eps * (beta * sigma * eps - 2.0 * (1.0 - beta * (1.0 + sigma * eps)))
    return adv - adv * dev * (beta * dev - 2.0 * (1.0 - beta) / mix) / denom


# ----------------------------------------------------------------------------------------
# SPO: surrogate advantage
# ----------------------------------------------------------------------------------------
def spo_surrogate_advantage(ratio: Tensor, adv: Tensor, eps: float = 0.1) -> Tensor:
    r"""Surrogate advantage of SPO: the derivative in rho of its objective (Xie et al. 2025).

    .. math:: \tilde A^{SPO} = \frac{\partial}{\partial\rho}
              \Big[\rho A - \frac{|A|}{2\epsilon}(\rho - 1)^2\Big]
              = A - \frac{|A|}{\epsilon}(\rho - 1)

    It equals A at rho = 1 (as PPO's does), vanishes at rho = 1 + sigma*eps, the maximiser of
    each sample's objective, and has the opposite sign of A beyond it. Unlike PPO-RPE's gain
    C (eq. (15)), the penalty's weight |A|/(2 eps) is the same on both sides of rho = 1,
    so SPO's thresholds 1 -/+ eps are symmetric on rho itself; PPO-RPE at beta = 0 (gain
    |A|/(2 eps), penalty on rho) is SPO. The result is linear in ``ratio``; no gradient
    flows into ``adv``.
    """
    _check_eps(eps)
    adv = adv.detach()
    return adv - adv.abs() * (ratio - 1.0) / eps


# ----------------------------------------------------------------------------------------
# Objectives
# ----------------------------------------------------------------------------------------
def _ppo_ratio(ratio: Tensor, adv: Tensor, eps: float, eta: float) -> Tensor:
    r"""rho_PPO of eq. (5) (``ratio_ppo``), Sec. II-B (clip when eta = 0, rollback if eta > 0)."""
    sigma = torch.sign(adv)
    past = sigma * (ratio - 1.0) >= eps
    rolled = -eta * ratio + (1.0 + eta) * (1.0 + sigma * eps)
    return torch.where(past, rolled, ratio)


def surrogate_objective(
    method: Method,
    ratio: Tensor,
    adv: Tensor,
    eps: float = 0.1,
    beta: float = 0.5,
    eta: float = 0.3,
    rpe_form: RPEForm = "derived",
) -> Tensor:
    r"""Per-sample objective rho * A^dagger to *maximise*.

    Its negative (mean) is the loss of eq. (6) (``loss_ppo``, Sec. II-B) for PPO and
    PPO-RB, and of eq. (11) (``loss_rpe``, Sec. III-B) for PPO-RPE; both are instances
    of eq. (2) (``loss_reg``, Sec. II-A).

    * ``"ppo"`` (eq. (5) (``ratio_ppo``), eta = 0; ``eta`` is ignored):
      :math:`\rho^{PPO} A` with :math:`\rho^{PPO} = 1+\sigma\epsilon` where
      :math:`\sigma(\rho-1)\ge\epsilon`, else rho. Equal to
      ``min(rho*A, clip(rho, 1-eps, 1+eps)*A)``.
    * ``"rb"`` (eq. (5), eta > 0): :math:`\rho^{PPO} = -\eta\rho + (1+\eta)(1+\sigma\epsilon)`
      past the threshold (rollback), else rho.
    * ``"rpe"`` (eq. (11) (``loss_rpe``)):
      :math:`\rho A - C(1-\beta+\beta\rho)(\rho_\beta-1)^2` with C of eq. (15)
      (``mag_rpe``) held constant; the subtracted term is rho times the regulariser
      Omega^RPE of eq. (10) (``reg_rpe``).
    * ``"spo"`` (Simple Policy Optimization, Xie et al., ICML 2025, arXiv:2401.16025):
      :math:`\rho A - \frac{|A|}{2\epsilon}(\rho - 1)^2`, a quadratic penalty on rho
      itself whose per-sample maximiser is :math:`\rho^* = 1 + \sigma\epsilon`
      (``beta``, ``eta`` and ``rpe_form`` are ignored).

    The derivative with respect to ``ratio`` is the weight of the paper's policy
    gradient: for ``"rpe"`` exactly :func:`rpe_surrogate_advantage` (derived form), for
    ``"spo"`` :func:`spo_surrogate_advantage`. With
    ``rpe_form="printed"`` the RPE objective is replaced by the integral-free surrogate
    ``rho * stopgrad(A~_printed)``, whose ratio-gradient is the printed A~ at each sample.

    ``adv`` is treated as a constant (detached).
    """
    check_surrogate_params(method, eps, beta, eta)
    adv = adv.detach()
    if method == "ppo":
        return _ppo_ratio(ratio, adv, eps, 0.0) * adv
    if method == "rb":
        return _ppo_ratio(ratio, adv, eps, eta) * adv
    if method == "spo":
        return ratio * adv - adv.abs() / (2.0 * eps) * (ratio - 1.0) ** 2
    if rpe_form == "printed":
        weight = rpe_surrogate_advantage(ratio.detach(), adv, eps, beta, form="printed")
        return ratio * weight
    if rpe_form != "derived":
        raise ValueError(
            f"rpe_form must be one of {', '.join(map(repr, _RPE_FORMS))}; got {rpe_form!r}"
        )
    gain = rpe_gain(adv, eps, beta)
    mix = 1.0 - beta + beta * ratio
    return ratio * adv - gain * mix * (ratio / mix - 1.0) ** 2


def surrogate_loss(
    method: Method,
    ratio: Tensor,
    adv: Tensor,
    eps: float = 0.1,
    beta: float = 0.5,
    eta: float = 0.3,
    rpe_form: RPEForm = "derived",
) -> Tensor:
    """Mean negative :func:`surrogate_objective`: the scalar policy loss to minimise."""
    return -surrogate_objective(method, ratio, adv, eps, beta, eta, rpe_form).mean()


# ----------------------------------------------------------------------------------------
# Diagnostics
# ----------------------------------------------------------------------------------------
class Regularization(NamedTuple):
    """Per-sample amount of regularisation (the paper's Fig. 5) and the past-threshold mask."""

    amount: Tensor
    """sigma * (rho - rho_dagger), with rho_dagger = objective / A; 0 where A = 0."""
    past_threshold: Tensor
    """Boolean: sigma*(rho - 1) >= eps (PPO, PPO-RB; for SPO: rho at or past its maximiser
    1 + sigma*eps, where its gradient turns against A) or sigma*(rho_beta - 1) >= eps (PPO-RPE);
    False where A = 0."""

    @property
    def fraction_past_threshold(self) -> Tensor:
        """Fraction of samples past the threshold, as a 0-dim float tensor."""
        return self.past_threshold.to(self.amount.dtype).mean()


def regularization_amount(
    method: Method,
    ratio: Tensor,
    adv: Tensor,
    eps: float = 0.1,
    beta: float = 0.5,
    eta: float = 0.3,
) -> Regularization:
    r"""The amount of regularisation the paper plots (Fig. 5, Sec. IV-B) and where it acts.

    .. math:: \sigma(\rho - \rho^\dagger), \qquad \rho^\dagger = \rho A^\dagger / A

    i.e. how far the objective pulls rho*A back, in units of |A|. It is computed
    without dividing by A:

    * PPO / PPO-RB: :math:`\sigma(\rho - \rho^{PPO})`, zero inside the threshold.
    * PPO-RPE: :math:`(C/|A|)(1-\beta+\beta\rho)(\rho_\beta-1)^2 \ge 0`, zero only at rho = 1.
    * SPO: :math:`(\rho - 1)^2 / (2\epsilon) \ge 0`, zero only at rho = 1.

    Where A = 0, rho_dagger is undefined and the amount is reported as 0.
    """
    check_surrogate_params(method, eps, beta, eta)
    adv = adv.detach()
    ratio = ratio.detach()
    ratio, adv = torch.broadcast_tensors(ratio, adv)
    nonzero = adv != 0
    sigma = torch.sign(adv)
    if method in ("ppo", "rb"):
        rho_ppo = _ppo_ratio(ratio, adv, eps, 0.0 if method == "ppo" else eta)
        amount = sigma * (ratio - rho_ppo)
        past = sigma * (ratio - 1.0) >= eps
    elif method == "spo":
        amount = torch.where(nonzero, (ratio - 1.0) ** 2 / (2.0 * eps), 0.0)
        past = (sigma * (ratio - 1.0) >= eps) & nonzero
    else:
        mix = 1.0 - beta + beta * ratio
        dev = ratio / mix - 1.0
        gain_per_abs_adv = 1.0 / (eps * (2.0 * (1.0 - beta) - beta * _sign(adv) * eps))
        amount = torch.where(nonzero, gain_per_abs_adv * mix * dev**2, 0.0)
        past = (sigma * dev >= eps) & nonzero
    return Regularization(amount=amount, past_threshold=past)
