r"""The surrogates in closed form, for the fused kernel: the objective of PPO, PPO-RB,
PPO-RPE or SPO at ``A = sigma`` and its derivative in rho.

At ``A = sigma`` (the learner's per-unit-signal objective obj(rho, sigma);
``mix = 1 - beta + beta rho``, ``dev = rho / mix - 1``)::

    PPO, PPO-RB: obj = sigma rho_PPO; past = sigma (rho - 1) >= eps:
                 rho_PPO = -eta rho + (1+eta)(1 + sigma eps), d obj/d rho = -eta sigma
                 else rho_PPO = rho, d obj/d rho = sigma          (PPO: eta = 0)
    RPE derived: C = 1 / (eps (2(1-beta) - beta sigma eps))
                 obj = sigma rho - C mix dev^2
                 d obj/d rho = sigma - C dev (beta dev + 2(1-beta)/mix)
    RPE printed: obj = rho A~_printed(rho) with A~ held constant: d obj/d rho = A~_printed
    SPO:         obj = sigma rho - (rho - 1)^2 / (2 eps)   (|A| = 1)
                 d obj/d rho = sigma - (rho - 1) / eps

and the head's signal ``d(-sigma obj)/d raw = -sigma obj'(rho) rho d log pi/d raw``
(``policy_gradient="weighted_score"``: ``-rho_dagger d log pi/d raw``,
``rho_dagger = sigma obj``), formed in :mod:`.step`. The torch engine evaluates
:func:`pporpe.surrogates.surrogate_objective` and differentiates it with autograd.
"""

from __future__ import annotations

from .jit import scalar_jit

__all__ = ["surrogate_closed"]


@scalar_jit
def surrogate_closed(
    method: int, rho: float, sigma: float, eps: float, beta: float, eta: float
) -> tuple[float, float]:
    """``(obj(rho, sigma), d obj / d rho)`` of the surrogate ``method`` (module docstring).

    ``obj`` is the per-sample objective of eq. (2) (``loss_reg``), whose negative is the
    loss of eq. (6) (``loss_ppo``) for PPO and PPO-RB (rho_PPO of eq. (5),
    ``ratio_ppo``) and of eq. (11) (``loss_rpe``) for PPO-RPE (the regulariser of
    eq. (10), ``reg_rpe``, with C of eq. (15), ``mag_rpe``). ``d obj / d rho`` is, for
    PPO-RPE, A~ of eq. (12) (``grad_rpe``) or, printed, of eq. (16) (``grad_rpe_thre``).
    Code 4 is SPO (Xie et al. 2025), whose derivative is its surrogate advantage.
    """
    if method <= 1:
        slope = 0.0 if method == 0 else eta
        if sigma * (rho - 1.0) >= eps:
            return (-slope * rho + (1.0 + slope) * (1.0 + sigma * eps)) * sigma, -slope * sigma
        return rho * sigma, sigma
    if method == 4:
        dev = rho - 1.0
        return rho * sigma - dev * dev / (2.0 * eps), sigma - dev / eps
    mix = 1.0 - beta + beta * rho
    dev = rho / mix - 1.0
    if method == 2:
        gain = 1.0 / (eps * (2.0 * (1.0 - beta) - beta * sigma * eps))
        obj = rho * sigma - gain * mix * dev * dev
        return obj, sigma - gain * dev * (beta * dev + 2.0 * (1.0 - beta) / mix)
    denom = sigma * eps * (beta * sigma * eps - 2.0 * (1.0 - beta * (1.0 + sigma * eps)))
    w = sigma - sigma * dev * (beta * dev - 2.0 * (1.0 - beta) / mix) / denom
    return rho * w, w
