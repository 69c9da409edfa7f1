"""Numerics of pporpe.surrogates, tested three ways: by hand, against an independent
float64 reference written here, and through identities."""

from __future__ import annotations

import math
import re

import pytest
import torch

from pporpe import surrogates as S

PARAMS = [(0.1, 0.5), (0.2, 0.5), (0.1, 0.0), (0.3, 0.25), (0.05, 0.9), (0.2, 0.8)]


# ------------------------------------------------------------------------------------
# Independent float64 reference, written from the paper's equations with plain floats.
# ------------------------------------------------------------------------------------
def ref_rho_beta(rho: float, beta: float) -> float:
    return rho / (beta * rho + (1 - beta))


def ref_gain(a: float, eps: float, beta: float) -> float:
    """C = A * C/A with C/A of eq. mag_rpe, as printed (sigma kept explicit)."""
    if a == 0:
        return 0.0
    s = 1.0 if a > 0 else -1.0
    c_over_a = 1.0 / (s * eps * (beta * s * eps + 2 * (1 - beta * (1 + s * eps))))
    return a * c_over_a


def ref_objective_rpe(rho: float, a: float, eps: float, beta: float) -> float:
    c = ref_gain(a, eps, beta)
    return rho * a - c * (1 - beta + beta * rho) * (ref_rho_beta(rho, beta) - 1) ** 2


def ref_atilde(rho: float, a: float, eps: float, beta: float) -> float:
    """A~ of eq. grad_rpe, built as A - C*beta*(rb-1)^2 - 2C(1-b+b*rho)(rb-1)*d rb/d rho."""
    c = ref_gain(a, eps, beta)
    rb = ref_rho_beta(rho, beta)
    mix = 1 - beta + beta * rho
    drb = (1 - beta) / mix**2
    return a - c * beta * (rb - 1) ** 2 - 2 * c * mix * (rb - 1) * drb


def ref_atilde_printed(rho: float, a: float, eps: float, beta: float) -> float:
    s = 1.0 if a >= 0 else -1.0
    rb = ref_rho_beta(rho, beta)
    mix = 1 - beta + beta * rho
    numer = a * (rb - 1) * (beta * (rb - 1) - 2 * (1 - beta) / mix)
    denom = s * eps * (beta * s * eps - 2 * (1 - beta * (1 + s * eps)))
    return a - numer / denom


def ref_objective_ppo(rho: float, a: float, eps: float, eta: float) -> float:
    s = (a > 0) - (a < 0)
    if s * (rho - 1) >= eps:
        rho_ppo = -eta * rho + (1 + eta) * (1 + s * eps)
    else:
        rho_ppo = rho
    return rho_ppo * a


def t64(x: list[float] | float) -> torch.Tensor:
    return torch.tensor(x, dtype=torch.float64)


# ------------------------------------------------------------------------------------
# Hand-worked values
# ------------------------------------------------------------------------------------
def test_thresholds_hand_worked() -> None:
    low, high = S.ratio_thresholds(eps=0.1, beta=0.5)
    # 1 - 0.1 / (1 - 0.5*0.9) = 1 - 0.1/0.55 ; 1 + 0.1 / (1 - 0.5*1.1) = 1 + 0.1/0.45
    assert low == pytest.approx(0.8182, abs=5e-5)
    assert high == pytest.approx(1.2222, abs=5e-5)
    # beta = 0: no relativity, PPO's symmetric thresholds
    assert S.ratio_thresholds(0.2, 0.0) == pytest.approx((0.8, 1.2))


def test_thresholds_map_to_symmetric_relative_thresholds() -> None:
    for eps, beta in PARAMS:
        low, high = S.ratio_thresholds(eps, beta)
        rb = S.relative_ratio(t64([low, high]), beta)
        torch.testing.assert_close(rb, t64([1 - eps, 1 + eps]), rtol=0, atol=1e-12)


def test_gain_hand_worked() -> None:
    # beta=0.5, eps=0.1, A=+1: C = 1 / (0.1 * (0.05 + 2*0.45)) = 1/0.095
    c = S.rpe_gain(t64([1.0, -1.0, 0.0, 2.5]), eps=0.1, beta=0.5)
    # A=-1: C/A = 1/(-0.1 * (-0.05 + 2*0.55)) = -1/0.105 -> C = 1/0.105
    torch.testing.assert_close(c, t64([1 / 0.095, 1 / 0.105, 0.0, 2.5 / 0.095]))


def test_atilde_hand_worked_erratum_example() -> None:
    """NOTES.md section 1: beta=0.5, eps=0.1, A=+1, rho=3: derived -2.947, printed -0.471."""
    rho, a = t64([3.0]), t64([1.0])
    derived = S.rpe_surrogate_advantage(rho, a, eps=0.1, beta=0.5)
    printed = S.rpe_surrogate_advantage(rho, a, eps=0.1, beta=0.5, form="printed")
    # by hand: rho_b = 3/2 = 1.5, mix = 2, C = 1/0.095
    # derived: 1 - C*0.5*(0.5*0.5 + 2*0.5/2) = 1 - 0.375/0.095
    assert derived.item() == pytest.approx(1 - 0.375 / 0.095, abs=1e-12)
    assert derived.item() == pytest.approx(-2.947, abs=5e-4)
    assert printed.item() == pytest.approx(-0.471, abs=5e-4)


@pytest.mark.parametrize(("eps", "beta"), PARAMS)
@pytest.mark.parametrize("form", ["derived", "printed"])
def test_atilde_is_adv_at_one_and_zero_at_thresholds(eps: float, beta: float, form: str) -> None:
    low, high = S.ratio_thresholds(eps, beta)
    adv = t64([3.0, -2.0, 0.7, -0.01])
    at_one = S.rpe_surrogate_advantage(torch.ones(4, dtype=torch.float64), adv, eps, beta, form)
    torch.testing.assert_close(at_one, adv)
    # A > 0 vanishes at the high threshold, A < 0 at the low one
    thr = torch.where(adv > 0, t64(high), t64(low))
    at_thr = S.rpe_surrogate_advantage(thr, adv, eps, beta, form)
    torch.testing.assert_close(at_thr, torch.zeros(4, dtype=torch.float64), rtol=0, atol=1e-12)


@pytest.mark.parametrize(("eps", "beta"), PARAMS)
def test_atilde_changes_sign_past_the_threshold(eps: float, beta: float) -> None:
    low, high = S.ratio_thresholds(eps, beta)
    adv = t64([1.0, -1.0])
    inside = S.rpe_surrogate_advantage(t64([high - 1e-3, low + 1e-3]), adv, eps, beta)
    beyond = S.rpe_surrogate_advantage(t64([high + 1e-3, low - 1e-3]), adv, eps, beta)
    assert torch.all(torch.sign(inside) == torch.sign(adv))
    assert torch.all(torch.sign(beyond) == -torch.sign(adv))


def test_ppo_hand_worked() -> None:
    eps = 0.2
    rho = t64([0.5, 1.1, 1.5, 0.5, 0.9, 1.5])
    adv = t64([1.0, 1.0, 1.0, -1.0, -1.0, -1.0])
    ppo = S.surrogate_objective("ppo", rho, adv, eps=eps)
    torch.testing.assert_close(ppo, t64([0.5, 1.1, 1.2, -0.8, -0.9, -1.5]))
    # PPO-RB with eta=0.5, past the threshold: -0.5*rho + 1.5*(1 + sigma*eps)
    rb = S.surrogate_objective("rb", rho, adv, eps=eps, eta=0.5)
    torch.testing.assert_close(rb, t64([0.5, 1.1, -0.75 + 1.8, -(-0.25 + 1.2), -0.9, -1.5]))


# ------------------------------------------------------------------------------------
# Independent float64 reference at random points
# ------------------------------------------------------------------------------------
@pytest.mark.parametrize(("eps", "beta"), PARAMS)
def test_against_float64_reference(eps: float, beta: float) -> None:
    g = torch.Generator().manual_seed(0)
    rho = torch.exp(torch.randn(300, generator=g, dtype=torch.float64))
    adv = 3.0 * torch.randn(300, generator=g, dtype=torch.float64)
    eta = 0.3
    exp_rpe = t64([ref_objective_rpe(r, a, eps, beta) for r, a in zip(rho.tolist(), adv.tolist())])
    exp_at = t64([ref_atilde(r, a, eps, beta) for r, a in zip(rho.tolist(), adv.tolist())])
    exp_pr = t64([ref_atilde_printed(r, a, eps, beta) for r, a in zip(rho.tolist(), adv.tolist())])
    exp_ppo = t64([ref_objective_ppo(r, a, eps, 0.0) for r, a in zip(rho.tolist(), adv.tolist())])
    exp_rb = t64([ref_objective_ppo(r, a, eps, eta) for r, a in zip(rho.tolist(), adv.tolist())])
    exp_c = t64([ref_gain(a, eps, beta) for a in adv.tolist()])
    exp_rb_ratio = t64([ref_rho_beta(r, beta) for r in rho.tolist()])

    torch.testing.assert_close(S.surrogate_objective("rpe", rho, adv, eps, beta), exp_rpe)
    torch.testing.assert_close(S.rpe_surrogate_advantage(rho, adv, eps, beta), exp_at)
    torch.testing.assert_close(
        S.rpe_surrogate_advantage(rho, adv, eps, beta, form="printed"), exp_pr
    )
    torch.testing.assert_close(S.surrogate_objective("ppo", rho, adv, eps), exp_ppo)
    torch.testing.assert_close(S.surrogate_objective("rb", rho, adv, eps, eta=eta), exp_rb)
    torch.testing.assert_close(S.rpe_gain(adv, eps, beta), exp_c)
    torch.testing.assert_close(S.relative_ratio(rho, beta), exp_rb_ratio)


def test_float32_matches_float64() -> None:
    g = torch.Generator().manual_seed(1)
    rho = torch.exp(0.3 * torch.randn(64, generator=g, dtype=torch.float64))
    adv = torch.randn(64, generator=g, dtype=torch.float64)
    for method in S.METHODS:
        out64 = S.surrogate_objective(method, rho, adv)
        out32 = S.surrogate_objective(method, rho.float(), adv.float())
        assert out32.dtype == torch.float32
        torch.testing.assert_close(out32.double(), out64, rtol=1e-5, atol=1e-5)


def test_any_batch_shape_and_broadcasting() -> None:
    rho = torch.rand(2, 3, 4) + 0.5
    adv = torch.randn(2, 3, 1)
    for method in S.METHODS:
        assert S.surrogate_objective(method, rho, adv).shape == (2, 3, 4)
        assert S.regularization_amount(method, rho, adv).amount.shape == (2, 3, 4)
    assert S.rpe_surrogate_advantage(rho, adv).shape == (2, 3, 4)
    assert S.rpe_divergence(rho, 0.5, dim=-1).shape == (2, 3)
    assert S.rpe_divergence(rho, 0.5).shape == ()


# ------------------------------------------------------------------------------------
# Identities
# ------------------------------------------------------------------------------------
@pytest.mark.parametrize(("eps", "beta"), PARAMS)
def test_autograd_of_rpe_objective_is_atilde(eps: float, beta: float) -> None:
    g = torch.Generator().manual_seed(2)
    rho = torch.exp(torch.randn(200, generator=g, dtype=torch.float64)).requires_grad_(True)
    adv = torch.randn(200, generator=g, dtype=torch.float64)
    (grad,) = torch.autograd.grad(S.surrogate_objective("rpe", rho, adv, eps, beta).sum(), rho)
    torch.testing.assert_close(grad, S.rpe_surrogate_advantage(rho.detach(), adv, eps, beta))


def test_autograd_through_log_ratio_gives_alg1_gradient() -> None:
    """d/dtheta objective = rho * A~ * d log pi / dtheta (Alg. 1's g, up to sign)."""
    logp_old = torch.tensor([-1.0, -0.5, -2.0], dtype=torch.float64)
    logp = torch.tensor([-0.8, -0.7, -2.1], dtype=torch.float64, requires_grad=True)
    adv = torch.tensor([1.0, -0.5, 2.0], dtype=torch.float64)
    rho = torch.exp(logp - logp_old)
    (grad,) = torch.autograd.grad(S.surrogate_objective("rpe", rho, adv).sum(), logp)
    expected = rho.detach() * S.rpe_surrogate_advantage(rho.detach(), adv)
    torch.testing.assert_close(grad, expected)


def test_printed_objective_gradient_is_printed_atilde() -> None:
    rho = torch.tensor([0.7, 1.0, 1.4, 3.0], dtype=torch.float64, requires_grad=True)
    adv = torch.tensor([1.0, -1.0, 2.0, 1.0], dtype=torch.float64)
    obj = S.surrogate_objective("rpe", rho, adv, rpe_form="printed")
    (grad,) = torch.autograd.grad(obj.sum(), rho)
    expected = S.rpe_surrogate_advantage(rho.detach(), adv, form="printed")
    torch.testing.assert_close(grad, expected)


@pytest.mark.parametrize("eps", [0.05, 0.1, 0.2, 0.3])
def test_rb_with_eta_zero_is_ppo_min_clip(eps: float) -> None:
    g = torch.Generator().manual_seed(3)
    rho = torch.exp(0.5 * torch.randn(500, generator=g, dtype=torch.float64))
    adv = torch.randn(500, generator=g, dtype=torch.float64)
    min_clip = torch.minimum(rho * adv, torch.clamp(rho, 1 - eps, 1 + eps) * adv)
    torch.testing.assert_close(S.surrogate_objective("rb", rho, adv, eps, eta=0.0), min_clip)
    torch.testing.assert_close(S.surrogate_objective("ppo", rho, adv, eps), min_clip)


def test_ppo_ignores_eta() -> None:
    rho = t64([0.5, 1.5])
    adv = t64([-1.0, 1.0])
    torch.testing.assert_close(
        S.surrogate_objective("ppo", rho, adv, eta=0.9), S.surrogate_objective("ppo", rho, adv)
    )


def test_rpe_with_beta_zero_has_symmetric_thresholds_and_pearson_divergence() -> None:
    rho = t64([0.5, 1.0, 2.0])
    assert S.ratio_thresholds(0.1, 0.0) == pytest.approx((0.9, 1.1))
    torch.testing.assert_close(S.relative_ratio(rho, 0.0), rho)
    # PE(pi, pi_b) = E_b[0.5 (rho - 1)^2]
    torch.testing.assert_close(S.rpe_divergence(rho, 0.0), ((rho - 1) ** 2 / 2).mean())


def test_relative_ratio_is_bounded_by_one_over_beta() -> None:
    rho = torch.logspace(-6, 6, 200, dtype=torch.float64)
    for beta in (0.25, 0.5, 0.9):
        rb = S.relative_ratio(rho, beta)
        assert torch.all(rb >= 0) and torch.all(rb < 1 / beta)


def test_rpe_divergence_zero_at_one_and_grows_with_spread() -> None:
    ones = torch.ones(1000)
    assert S.rpe_divergence(ones, 0.5).item() == 0.0
    g = torch.Generator().manual_seed(4)
    z = torch.randn(10000, generator=g, dtype=torch.float64)
    values = [S.rpe_divergence(torch.exp(s * z), 0.5).item() for s in (0.01, 0.1, 0.3, 1.0)]
    assert values[0] < 1e-3
    assert all(a < b for a, b in zip(values, values[1:]))


def test_rpe_divergence_estimate_matches_quadrature() -> None:
    """Monte-Carlo estimate from baseline samples vs. the integral of eq. div_rpe."""
    beta = 0.5
    pi = torch.distributions.Normal(torch.tensor(0.4, dtype=torch.float64), 1.2)
    pi_b = torch.distributions.Normal(torch.tensor(0.0, dtype=torch.float64), 1.0)
    x = torch.linspace(-14, 14, 200001, dtype=torch.float64)
    p, pb = pi.log_prob(x).exp(), pi_b.log_prob(x).exp()
    p_mix = beta * p + (1 - beta) * pb
    exact = torch.trapezoid(p_mix * 0.5 * (p / p_mix - 1) ** 2, x)
    torch.manual_seed(0)
    a = pi_b.sample((400000,))
    estimate = S.rpe_divergence(torch.exp(pi.log_prob(a) - pi_b.log_prob(a)), beta)
    assert estimate.item() == pytest.approx(exact.item(), rel=0.02)


def test_objectives_equal_rho_times_adv_at_ratio_one() -> None:
    adv = t64([2.0, -3.0, 0.5])
    for method in S.METHODS:
        torch.testing.assert_close(S.surrogate_objective(method, torch.ones(3).double(), adv), adv)


def test_objectives_are_positively_homogeneous_in_adv() -> None:
    """Scaling A by k > 0 scales each objective by k (PPO-RPE's gain adapts to A's scale)."""
    g = torch.Generator().manual_seed(5)
    rho = torch.exp(0.4 * torch.randn(100, generator=g, dtype=torch.float64))
    adv = torch.randn(100, generator=g, dtype=torch.float64)
    for method in S.METHODS:
        torch.testing.assert_close(
            S.surrogate_objective(method, rho, 7.0 * adv),
            7.0 * S.surrogate_objective(method, rho, adv),
        )


def test_objectives_do_not_propagate_gradient_into_adv() -> None:
    rho = torch.tensor([1.3, 0.7], requires_grad=True)
    adv = torch.tensor([1.0, -1.0], requires_grad=True)
    for method in S.METHODS:
        obj = S.surrogate_objective(method, rho, adv).sum()
        g_rho, g_adv = torch.autograd.grad(obj, [rho, adv], allow_unused=True)
        assert g_adv is None
        assert g_rho is not None


def test_surrogate_loss_is_negative_mean() -> None:
    rho = t64([0.9, 1.2, 1.05])
    adv = t64([1.0, -0.3, 0.2])
    for method in S.METHODS:
        expected = -S.surrogate_objective(method, rho, adv).mean()
        torch.testing.assert_close(S.surrogate_loss(method, rho, adv), expected)


# ------------------------------------------------------------------------------------
# Regularisation diagnostics
# ------------------------------------------------------------------------------------
def test_regularization_amount_matches_definition() -> None:
    g = torch.Generator().manual_seed(6)
    rho = torch.exp(0.5 * torch.randn(200, generator=g, dtype=torch.float64))
    adv = torch.randn(200, generator=g, dtype=torch.float64)
    for method in S.METHODS:
        obj = S.surrogate_objective(method, rho, adv)
        rho_dagger = obj / adv
        expected = torch.sign(adv) * (rho - rho_dagger)
        reg = S.regularization_amount(method, rho, adv)
        torch.testing.assert_close(reg.amount, expected)
        assert torch.all(reg.amount >= -1e-12)


def test_regularization_fraction_past_threshold() -> None:
    low, high = S.ratio_thresholds(0.1, 0.5)
    rho = t64([1.0, high + 0.01, low - 0.01, 1.15, 0.85])
    adv = t64([1.0, 1.0, -1.0, 1.0, -1.0])
    rpe = S.regularization_amount("rpe", rho, adv, eps=0.1, beta=0.5)
    assert rpe.past_threshold.tolist() == [False, True, True, False, False]
    assert rpe.fraction_past_threshold.item() == pytest.approx(0.4)
    ppo = S.regularization_amount("ppo", rho, adv, eps=0.1)
    assert ppo.past_threshold.tolist() == [False, True, True, True, True]
    # PPO does not regularise inside its threshold, PPO-RPE does everywhere but rho = 1
    inside = S.regularization_amount("ppo", t64([1.05, 0.3]), t64([1.0, 1.0]))
    assert inside.amount.tolist() == [0.0, 0.0]
    assert torch.all(rpe.amount[1:] > 0) and rpe.amount[0].item() == 0.0


def test_regularization_amount_zero_where_adv_zero() -> None:
    for method in S.METHODS:
        reg = S.regularization_amount(method, t64([1.5, 0.5]), t64([0.0, 0.0]))
        assert reg.amount.tolist() == [0.0, 0.0]
        assert reg.past_threshold.tolist() == [False, False]


# ------------------------------------------------------------------------------------
# Robustness
# ------------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_finite_values_and_gradients_over_extreme_ratios(dtype: torch.dtype) -> None:
    rho = torch.logspace(-6, 6, 121, dtype=dtype).repeat(3).requires_grad_(True)
    adv = torch.tensor([1.0, -1.0, 0.0], dtype=dtype).repeat_interleave(121)
    for method in S.METHODS:
        for eps, beta in PARAMS:
            obj = S.surrogate_objective(method, rho, adv, eps, beta)
            (grad,) = torch.autograd.grad(obj.sum(), rho)
            assert torch.isfinite(obj).all() and torch.isfinite(grad).all()
            reg = S.regularization_amount(method, rho, adv, eps, beta)
            assert torch.isfinite(reg.amount).all()
    for eps, beta in PARAMS:
        assert torch.isfinite(S.rpe_surrogate_advantage(rho.detach(), adv, eps, beta)).all()
        assert torch.isfinite(S.rpe_divergence(rho.detach(), beta)).all()
        assert torch.isfinite(S.rpe_gain(adv, eps, beta)).all()


def test_zero_advantage_gives_zero_gain_and_zero_atilde() -> None:
    adv = torch.zeros(3)
    assert S.rpe_gain(adv).tolist() == [0.0, 0.0, 0.0]
    out = S.rpe_surrogate_advantage(torch.tensor([0.5, 1.0, 2.0]), adv)
    assert out.tolist() == [0.0, 0.0, 0.0]


BAD = [
    ({"eps": 0.0}, "eps"),
    ({"eps": 1.0}, "eps"),
    ({"eps": -0.1}, "eps"),
    ({"eps": math.nan}, "eps"),
    ({"beta": -0.01}, "beta"),
    ({"beta": 1.5}, "beta"),
    ({"beta": 0.95, "eps": 0.1}, "beta*(1+eps)"),
    ({"eta": -0.1}, "eta"),
    ({"eta": math.inf}, "eta"),
]


@pytest.mark.parametrize(("kwargs", "name"), BAD)
def test_invalid_parameters_raise_naming_the_parameter(kwargs: dict, name: str) -> None:
    method = "rb" if "eta" in kwargs else "rpe"
    with pytest.raises(ValueError, match=re.escape(name)) as info:
        S.surrogate_objective(method, torch.ones(2), torch.ones(2), **kwargs)
    value = next(iter(kwargs.values()))
    assert repr(value) in str(info.value)


def test_invalid_method_and_form_raise() -> None:
    with pytest.raises(
        ValueError, match=r"method must be one of 'ppo', 'rb', 'rpe', 'spo'; got 'trpo'"
    ):
        S.surrogate_objective("trpo", torch.ones(1), torch.ones(1))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="form"):
        S.rpe_surrogate_advantage(torch.ones(1), torch.ones(1), form="typo")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="rpe_form"):
        S.surrogate_objective("rpe", torch.ones(1), torch.ones(1), rpe_form="x")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="beta"):
        S.relative_ratio(torch.ones(1), 2.0)
    with pytest.raises(ValueError, match="beta"):
        S.rpe_divergence(torch.ones(1), -1.0)
    with pytest.raises(ValueError, match="eps"):
        S.ratio_thresholds(eps=2.0)


def test_printed_form_singularity_raises() -> None:
    eps = 0.1
    beta = 2 / (2 + 3 * eps)
    with pytest.raises(ValueError, match="printed"):
        S.rpe_surrogate_advantage(torch.ones(1), torch.ones(1), eps, beta, form="printed")


# ------------------------------------------------------------------------------------
# SPO (Xie et al., ICML 2025): rho*A - |A|/(2 eps)*(rho - 1)^2
# ------------------------------------------------------------------------------------
SPO_EPS = [0.05, 0.1, 0.2, 0.3, 0.5, 0.9]


def ref_objective_spo(rho: float, a: float, eps: float) -> float:
    """SPO's per-sample objective, written from its paper with plain floats."""
    return rho * a - abs(a) / (2.0 * eps) * (rho - 1.0) ** 2


def ref_atilde_spo(rho: float, a: float, eps: float) -> float:
    """Its derivative in rho, by hand: A - 2*|A|/(2 eps)*(rho - 1)."""
    return a - abs(a) * (rho - 1.0) / eps


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_spo_hand_worked(dtype: torch.dtype) -> None:
    eps = 0.2
    rho = torch.tensor([1.0, 1.1, 1.2, 1.5, 0.8, 0.5, 1.3], dtype=dtype)
    adv = torch.tensor([2.0, 1.0, 1.0, 1.0, -1.0, -2.0, 0.0], dtype=dtype)
    # 1.1 - 0.01/0.4; 1.2 - 0.04/0.4 (the maximum, 1 + eps/2); 1.5 - 0.25/0.4;
    # -0.8 - 0.04/0.4; -1.0 - 2*0.25/0.4; A = 0 gives 0
    expected = torch.tensor([2.0, 1.075, 1.1, 0.875, -0.9, -2.25, 0.0], dtype=dtype)
    obj = S.surrogate_objective("spo", rho, adv, eps=eps)
    assert obj.dtype == dtype
    torch.testing.assert_close(obj, expected)
    # A - |A|(rho - 1)/eps: 2; 1 - 0.5; 1 - 1; 1 - 2.5; -1 + 1; -2 + 5; 0
    grad = S.spo_surrogate_advantage(rho, adv, eps=eps)
    torch.testing.assert_close(
        grad, torch.tensor([2.0, 0.5, 0.0, -1.5, 0.0, 3.0, 0.0], dtype=dtype)
    )
    torch.testing.assert_close(S.surrogate_loss("spo", rho, adv, eps=eps), -expected.mean())
    # where PPO clips (rho = 1.5, A = 1: 1.2), SPO pulls further back (0.875)
    assert S.surrogate_objective("ppo", rho, adv, eps=eps)[3].item() == pytest.approx(1.2)


@pytest.mark.parametrize("eps", SPO_EPS)
def test_spo_against_float64_reference(eps: float) -> None:
    g = torch.Generator().manual_seed(7)
    rho = torch.exp(torch.randn(300, generator=g, dtype=torch.float64))
    adv = 3.0 * torch.randn(300, generator=g, dtype=torch.float64)
    pairs = list(zip(rho.tolist(), adv.tolist()))
    exp_obj = t64([ref_objective_spo(r, a, eps) for r, a in pairs])
    exp_at = t64([ref_atilde_spo(r, a, eps) for r, a in pairs])
    torch.testing.assert_close(S.surrogate_objective("spo", rho, adv, eps), exp_obj)
    torch.testing.assert_close(S.spo_surrogate_advantage(rho, adv, eps), exp_at)
    # float32 agrees with the float64 reference to float32's resolution
    out32 = S.surrogate_objective("spo", rho.float(), adv.float(), eps)
    assert out32.dtype == torch.float32
    torch.testing.assert_close(out32.double(), exp_obj, rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize("eps", SPO_EPS)
def test_spo_per_sample_maximiser_is_one_plus_sigma_eps(eps: float) -> None:
    """Over a fine grid of rho, each sample's objective peaks at rho* = 1 + sign(A)*eps,
    where it is A + |A|*eps/2; autograd's derivative vanishes there and only there."""
    rho = torch.linspace(0.0, 3.0, 300001, dtype=torch.float64)
    for a in (2.5, 1.0, 0.3, -0.3, -1.0, -4.0):
        obj = S.surrogate_objective("spo", rho, torch.full_like(rho, a), eps)
        best = rho[int(torch.argmax(obj))].item()
        assert best == pytest.approx(1.0 + math.copysign(eps, a), abs=1e-5)
        assert obj.max().item() == pytest.approx(a + abs(a) * eps / 2, rel=1e-9)
    at = torch.tensor([1.0 + eps, 1.0 - eps], dtype=torch.float64, requires_grad=True)
    adv = t64([1.7, -0.4])
    (grad,) = torch.autograd.grad(S.surrogate_objective("spo", at, adv, eps).sum(), at)
    torch.testing.assert_close(grad, torch.zeros(2, dtype=torch.float64), rtol=0, atol=1e-12)
    # the objective is concave in rho: its second derivative is -|A|/eps
    x = torch.tensor([0.7, 1.4], dtype=torch.float64, requires_grad=True)
    (g1,) = torch.autograd.grad(
        S.surrogate_objective("spo", x, adv, eps).sum(), x, create_graph=True
    )
    (g2,) = torch.autograd.grad(g1.sum(), x)
    torch.testing.assert_close(g2, -adv.abs() / eps)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("eps", SPO_EPS)
def test_spo_gradient_is_its_surrogate_advantage_and_ppos_at_ratio_one(
    eps: float, dtype: torch.dtype
) -> None:
    g = torch.Generator().manual_seed(8)
    rho = torch.exp(0.5 * torch.randn(200, generator=g, dtype=dtype)).requires_grad_(True)
    adv = torch.randn(200, generator=g, dtype=dtype)
    (grad,) = torch.autograd.grad(S.surrogate_objective("spo", rho, adv, eps).sum(), rho)
    torch.testing.assert_close(grad, S.spo_surrogate_advantage(rho.detach(), adv, eps))
    ones = torch.ones(200, dtype=dtype, requires_grad=True)
    grads = {}
    for method in ("spo", "ppo"):
        (grads[method],) = torch.autograd.grad(
            S.surrogate_objective(method, ones, adv, eps).sum(), ones
        )
    torch.testing.assert_close(grads["spo"], adv, rtol=0, atol=0)
    torch.testing.assert_close(grads["ppo"], adv, rtol=0, atol=0)


@pytest.mark.parametrize("eps", SPO_EPS)
def test_spo_surrogate_advantage_turns_at_one_plus_sigma_eps(eps: float) -> None:
    adv = t64([1.0, -1.0])
    inside = S.spo_surrogate_advantage(t64([1 + eps - 1e-3, 1 - eps + 1e-3]), adv, eps)
    beyond = S.spo_surrogate_advantage(t64([1 + eps + 1e-3, 1 - eps - 1e-3]), adv, eps)
    assert torch.all(torch.sign(inside) == torch.sign(adv))
    assert torch.all(torch.sign(beyond) == -torch.sign(adv))


@pytest.mark.parametrize("eps", [0.1, 0.2, 0.3])
def test_spo_is_ppo_rpe_with_beta_zero_and_differs_from_it_with_beta(eps: float) -> None:
    """At beta = 0 PPO-RPE's gain is C = |A|/(2 eps) on both sides (eq. (15)) and its
    penalty is on rho itself: SPO's objective. With beta > 0 the penalty is on rho_beta
    with a gain that differs with the sign of A, and the two part."""
    g = torch.Generator().manual_seed(9)
    rho = torch.exp(0.4 * torch.randn(100, generator=g, dtype=torch.float64))
    adv = torch.randn(100, generator=g, dtype=torch.float64)
    spo = S.surrogate_objective("spo", rho, adv, eps)
    torch.testing.assert_close(spo, S.surrogate_objective("rpe", rho, adv, eps, beta=0.0))
    torch.testing.assert_close(S.rpe_gain(adv, eps, 0.0), adv.abs() / (2 * eps))
    rpe = S.surrogate_objective("rpe", rho, adv, eps, beta=0.5)
    assert float((spo - rpe).abs().max()) > 1e-3
    # PPO-RPE's thresholds on rho move (asymmetric); SPO's maximiser stays at 1 -/+ eps
    low, high = S.ratio_thresholds(eps, 0.5)
    assert high - 1 > eps and 1 - low > eps


def test_spo_regularization_amount_and_past_threshold() -> None:
    eps = 0.2
    rho = t64([1.0, 1.1, 1.25, 1.5, 0.9, 0.7, 1.3, 1.5])
    adv = t64([1.0, 1.0, 1.0, 1.0, -1.0, -2.0, -1.0, 0.0])
    reg = S.regularization_amount("spo", rho, adv, eps=eps)
    # (rho - 1)^2 / (2 eps), 0 where A = 0
    torch.testing.assert_close(
        reg.amount, t64([0.0, 0.025, 0.15625, 0.625, 0.025, 0.225, 0.225, 0.0])
    )
    # past: sigma*(rho - 1) >= eps, the ratio at or past its maximiser 1 + sigma eps;
    # rho = 1.3 with A < 0 is on the other side (no past), A = 0 is never past
    assert reg.past_threshold.tolist() == [False, False, True, True, False, True, False, False]
    assert reg.fraction_past_threshold.item() == pytest.approx(3 / 8)


@pytest.mark.parametrize("method", S.METHODS)
@pytest.mark.parametrize("eps", [0.0, 1.0, -0.1, 1.5, math.nan, math.inf])
def test_bad_eps_refused_alike_by_every_method(method: str, eps: float) -> None:
    expected = f"eps must be a number in the open interval (0, 1); got eps={eps!r}"
    with pytest.raises(ValueError) as info:
        S.surrogate_objective(method, torch.ones(2), torch.ones(2), eps=eps)  # type: ignore[arg-type]
    assert str(info.value) == expected
    with pytest.raises(ValueError) as info:
        S.check_surrogate_params(method, eps=eps)
    assert str(info.value) == expected
    if method == "spo":
        with pytest.raises(ValueError, match=re.escape(expected)):
            S.spo_surrogate_advantage(torch.ones(2), torch.ones(2), eps=eps)


def test_spo_takes_no_beta_or_eta() -> None:
    """beta and eta are not SPO's: a beta that PPO-RPE refuses and any eta leave it as is."""
    rho, adv = t64([0.5, 1.4]), t64([-1.0, 2.0])
    S.check_surrogate_params("spo", eps=0.1, beta=0.95)
    torch.testing.assert_close(
        S.surrogate_objective("spo", rho, adv, eps=0.1, beta=0.95, eta=5.0, rpe_form="printed"),
        S.surrogate_objective("spo", rho, adv, eps=0.1),
    )
