"""Tests of pporpe.policies: heads, the bounded action map and their densities."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch.distributions import AffineTransform, SigmoidTransform, TransformedDistribution

from pporpe.nn.policies import (
    HEAD_KINDS,
    ActionMap,
    NormalHead,
    PolicyHead,
    StudentTHead,
    make_head,
)

F64 = torch.float64


def _softplus(x: float) -> float:
    return max(x, 0.0) + math.log1p(math.exp(-abs(x)))


def _student_t_reference(raw: np.ndarray, u: np.ndarray, act_dim: int, min_scale: float) -> float:
    """Log-density of the diagonal Student-t written out element by element."""
    loc = raw[:act_dim]
    scale = [_softplus(float(x)) + min_scale for x in raw[act_dim : 2 * act_dim]]
    df = _softplus(float(raw[2 * act_dim])) + 2.0
    total = 0.0
    for i in range(act_dim):
        z = (float(u[i]) - float(loc[i])) / scale[i]
        total += (
            math.lgamma((df + 1.0) / 2.0)
            - math.lgamma(df / 2.0)
            - 0.5 * math.log(df * math.pi)
            - math.log(scale[i])
            - (df + 1.0) / 2.0 * math.log1p(z * z / df)
        )
    return total


def _normal_reference(raw: np.ndarray, u: np.ndarray, act_dim: int, min_scale: float) -> float:
    """Log-density of the diagonal Gaussian written out element by element."""
    total = 0.0
    for i in range(act_dim):
        scale = _softplus(float(raw[act_dim + i])) + min_scale
        z = (float(u[i]) - float(raw[i])) / scale
        total += -0.5 * z * z - math.log(scale) - 0.5 * math.log(2.0 * math.pi)
    return total


REFERENCES = {"student_t": _student_t_reference, "normal": _normal_reference}


@pytest.mark.parametrize("kind", HEAD_KINDS)
@pytest.mark.parametrize("act_dim", [1, 3, 6])
def test_log_prob_matches_reference_formula(kind: str, act_dim: int) -> None:
    gen = torch.Generator().manual_seed(act_dim)
    head = make_head(kind, act_dim)
    raw = 2.0 * torch.randn(4, 5, head.raw_dim, generator=gen, dtype=F64)
    u = 3.0 * torch.randn(4, 5, act_dim, generator=gen, dtype=F64)
    dist_lp = head.distribution(raw).log_prob(u)
    fast_lp = head.log_prob(raw, u)
    assert dist_lp.shape == fast_lp.shape == (4, 5)
    expected = torch.tensor(
        [
            [REFERENCES[kind](raw[i, j].numpy(), u[i, j].numpy(), act_dim, 1e-3) for j in range(5)]
            for i in range(4)
        ],
        dtype=F64,
    )
    torch.testing.assert_close(dist_lp, expected, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(fast_lp, expected, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("kind", HEAD_KINDS)
def test_closed_form_log_prob_float32_and_broadcasting(kind: str) -> None:
    gen = torch.Generator().manual_seed(0)
    head = make_head(kind, 6)
    raw = torch.randn(2, head.raw_dim, generator=gen)
    dist = head.distribution(raw)
    u = dist.sample((7,))  # [7, 2, 6] against raw [2, raw_dim]
    torch.testing.assert_close(head.log_prob(raw, u), dist.log_prob(u), rtol=1e-5, atol=1e-5)
    # Gradients agree too.
    raw_a = raw.clone().requires_grad_(True)
    raw_b = raw.clone().requires_grad_(True)
    head.log_prob(raw_a, u).sum().backward()
    head.distribution(raw_b).log_prob(u).sum().backward()
    assert raw_a.grad is not None and raw_b.grad is not None
    torch.testing.assert_close(raw_a.grad, raw_b.grad, rtol=1e-4, atol=1e-5)


def test_student_t_parameters_and_shared_df() -> None:
    head = StudentTHead(3, min_scale=0.01)
    assert head.raw_dim == 7
    raw = torch.tensor([[0.5, -1.0, 2.0, 0.0, -30.0, 3.0, 1.0]], dtype=F64)
    loc, scale, df = head.split(raw)
    torch.testing.assert_close(loc, raw[:, :3])
    torch.testing.assert_close(scale, torch.nn.functional.softplus(raw[:, 3:6]) + 0.01)
    assert df.shape == (1, 1)
    torch.testing.assert_close(df, torch.nn.functional.softplus(raw[:, 6:]) + 2.0)
    base = head.distribution(raw).base_dist  # type: ignore[attr-defined]
    torch.testing.assert_close(base.df, df.expand(1, 3))
    assert head.distribution(raw).event_shape == (3,)
    torch.testing.assert_close(head.location(raw), loc)
    assert NormalHead(3).raw_dim == 6


def test_log_prob_action_matches_transformed_distribution() -> None:
    gen = torch.Generator().manual_seed(1)
    low = torch.tensor([-1.0, 0.0, -3.0], dtype=F64)
    high = torch.tensor([1.0, 0.5, 5.0], dtype=F64)
    amap = ActionMap(low, high)
    for kind in HEAD_KINDS:
        head = make_head(kind, 3)
        raw = torch.randn(10, head.raw_dim, generator=gen, dtype=F64)
        base = head.distribution(raw)
        u = 4.0 * torch.rand(10, 3, generator=gen, dtype=F64) - 2.0  # interior points
        a = amap.to_action(u)
        reference = TransformedDistribution(
            base, [SigmoidTransform(), AffineTransform(low, high - low)], validate_args=False
        )
        # torch inverts a back to u (logit), which costs a few ulps of u; hence 1e-7.
        torch.testing.assert_close(
            amap.log_prob_action(base, u), reference.log_prob(a), rtol=1e-7, atol=1e-7
        )
        # The Jacobian cancels in ratios: a-space and u-space ratios agree.
        other = head.distribution(raw + 0.1)
        ratio_u = other.log_prob(u) - base.log_prob(u)
        ratio_a = amap.log_prob_action(other, u) - amap.log_prob_action(base, u)
        torch.testing.assert_close(ratio_u, ratio_a)


def test_log_abs_det_jacobian_is_stable_at_large_u() -> None:
    amap = ActionMap([-2.0], [2.0])
    u = torch.tensor([[-200.0], [0.0], [200.0]])
    ladj = amap.log_abs_det_jacobian(u)
    expected = torch.tensor([-200.0 + math.log(4.0), math.log(4.0) - 2 * math.log(2.0), -200.0])
    expected[2] += math.log(4.0)
    torch.testing.assert_close(ladj, expected)
    assert torch.all(torch.isfinite(ladj))


@pytest.mark.parametrize(
    ("kind", "raw_values"),
    [
        ("student_t", [0.3, -0.4, 0.5]),  # scale ~ 0.51, df ~ 2.97
        ("student_t", [-1.0, 0.5, -1.5]),  # off-centre, df ~ 2.2 (heavy tails)
        ("normal", [0.7, 0.2]),
        ("normal", [-2.0, -3.0]),  # narrow, near the low bound
    ],
)
def test_bounded_density_integrates_to_one(kind: str, raw_values: list[float]) -> None:
    low, high = -0.5, 2.5
    amap = ActionMap([low], [high])
    head = make_head(kind, 1)
    dist = head.distribution(torch.tensor(raw_values, dtype=F64))
    u = torch.linspace(-300.0, 300.0, 600_001, dtype=F64).unsqueeze(-1)
    a = amap.to_action(u).squeeze(-1)
    density = torch.exp(amap.log_prob_action(dist, u))
    assert torch.all(torch.isfinite(density))
    assert a.min() >= low and a.max() <= high
    mass = torch.trapezoid(density, a).item()
    assert mass == pytest.approx(1.0, abs=1e-3)  # float64 sigmoid saturates past u ~ 37


@pytest.mark.parametrize("kind", HEAD_KINDS)
def test_sampled_actions_lie_in_bounds_and_location_is_median(kind: str) -> None:
    torch.manual_seed(0)
    low = torch.tensor([-1.0, 0.0, 10.0])
    high = torch.tensor([1.0, 0.1, 30.0])
    amap = ActionMap(low, high)
    head = make_head(kind, 3)
    raw = torch.zeros(head.raw_dim)
    raw[:3] = torch.tensor([0.5, -1.0, 2.0])
    raw[3:6] = torch.tensor([3.0, 0.0, -2.0])
    dist = head.distribution(raw)
    a = amap.to_action(dist.sample((20_000,)))
    assert a.shape == (20_000, 3)
    assert torch.all(a >= low) and torch.all(a <= high)
    # Extreme raw values still give in-bound actions.
    wild = amap.to_action(head.distribution(torch.full((head.raw_dim,), 1e4)).sample((100,)))
    assert torch.all(wild >= low) and torch.all(wild <= high)
    # The test-time action maps the location; it is the median of the action (monotone map).
    test_action = amap.to_action(head.location(raw))
    torch.testing.assert_close(test_action, low + (high - low) * torch.sigmoid(raw[:3]))
    assert torch.all((a.median(0).values - test_action).abs() <= 0.05 * (high - low))


@pytest.mark.parametrize("kind", HEAD_KINDS)
def test_rsample_is_reparameterised(kind: str) -> None:
    torch.manual_seed(0)
    head = make_head(kind, 2)
    raw = torch.randn(8, head.raw_dim, requires_grad=True)
    dist = head.distribution(raw)
    assert dist.has_rsample
    amap = ActionMap([-1.0, -2.0], [1.0, 2.0])
    a = amap.to_action(dist.rsample())
    (a**2).sum().backward()
    assert raw.grad is not None
    assert torch.all(torch.isfinite(raw.grad))
    assert raw.grad[:, :2].abs().sum() > 0  # loc
    assert raw.grad[:, 2:4].abs().sum() > 0  # scale
    if kind == "student_t":
        assert raw.grad[:, 4].abs().sum() > 0  # degrees of freedom


@pytest.mark.parametrize("kind", HEAD_KINDS)
def test_extreme_raw_values_stay_valid(kind: str) -> None:
    head = make_head(kind, 3)
    amap = ActionMap([-1.0] * 3, [1.0] * 3)
    for value in (-1e4, 1e4):
        raw = torch.full((2, head.raw_dim), value, requires_grad=True)
        params = head.split(raw)
        scale = params[1]
        assert torch.all(scale > 0) and torch.all(torch.isfinite(scale))
        if kind == "student_t":
            df = params[2]
            assert torch.all(df >= 2.0) and torch.all(torch.isfinite(df))
        dist = head.distribution(raw)
        for u in (torch.zeros(2, 3), torch.full((2, 3), 50.0), dist.sample()):
            lp = head.log_prob(raw, u)
            assert torch.all(torch.isfinite(lp))
            assert torch.all(torch.isfinite(dist.log_prob(u)))
            assert torch.all(torch.isfinite(amap.log_prob_action(dist, u)))
        head.log_prob(raw, torch.zeros(2, 3)).sum().backward()
        assert raw.grad is not None and torch.all(torch.isfinite(raw.grad))
    if kind == "student_t":
        df = head.split(torch.full((1, head.raw_dim), -10.0))[2]
        assert torch.all(df > 2.0)  # strictly above 2 until softplus underflows


def test_make_head_kinds_and_errors() -> None:
    assert isinstance(make_head("student_t", 2), StudentTHead)
    assert isinstance(make_head("normal", 2), NormalHead)
    assert isinstance(make_head("student_t", 2, min_df=3.0), PolicyHead)
    with pytest.raises(ValueError, match="student_t"):
        make_head("gaussian", 2)
    with pytest.raises(ValueError, match="act_dim"):
        make_head("normal", 0)
    with pytest.raises(ValueError, match="min_scale"):
        StudentTHead(2, min_scale=0.0)
    with pytest.raises(ValueError, match="last dimension 5"):
        StudentTHead(2).distribution(torch.zeros(3, 4))


def test_action_map_validation_and_from_space() -> None:
    with pytest.raises(ValueError):
        ActionMap([1.0], [1.0])
    with pytest.raises(ValueError):
        ActionMap([0.0, 0.0], [1.0])
    with pytest.raises(ValueError):
        ActionMap([-math.inf], [1.0])
    box = type(
        "Box", (), {"low": np.array([-2.0], np.float32), "high": np.array([2.0], np.float32)}
    )
    amap = ActionMap.from_space(box())
    assert amap.act_dim == 1
    torch.testing.assert_close(amap.to_action(torch.zeros(1)), torch.zeros(1))
    assert amap.state_dict() == {}
    # Awkward float32 bounds: saturated actions never leave the box.
    odd = ActionMap([-0.1, 0.3, -7.7], [0.3, 0.7000001, 1e-3])
    u = torch.tensor([[-1e4] * 3, [-40.0] * 3, [40.0] * 3, [1e4] * 3])
    a = odd.to_action(u)
    assert torch.all(a >= odd.low) and torch.all(a <= odd.high)
    torch.testing.assert_close(a[0], odd.low, rtol=0, atol=1e-6)
    torch.testing.assert_close(a[-1], odd.high, rtol=0, atol=1e-6)
    # float64 inputs are computed in float64.
    assert amap.to_action(torch.zeros(1, dtype=F64)).dtype == F64


@pytest.mark.parametrize("kind", ["student_t", "normal"])
def test_fast_sample_equals_torch_distributions_sample(kind: str) -> None:
    """head.sample draws the same numbers as distribution(raw).sample() from the same RNG."""
    head = make_head(kind, 3)
    raw = torch.randn(4, head.raw_dim) * 2.0
    torch.manual_seed(123)
    expected = head.distribution(raw).sample()
    after_expected = torch.rand(1)
    torch.manual_seed(123)
    got = head.sample(raw)
    after_got = torch.rand(1)
    torch.testing.assert_close(got, expected, rtol=0, atol=0)
    assert torch.equal(after_got, after_expected)  # same amount of RNG consumed
    assert not got.requires_grad
