"""Tests of the adaptive multiple time-scale eligibility traces (pporpe.traces)."""

from __future__ import annotations

import io
import math

import pytest
import torch

from pporpe.online.torch_engine.traces import AdaptiveTraces


def reference_traces(grads, divs, gamma, lam1, lam2, kappa):
    """Plain float64 transcription of NOTES.md section 3 (one element at a time)."""
    n = grads[0].numel()
    e = [0.0] * n
    r = [0.0] * n
    D = 0.0
    out = []
    for g, d in zip(grads, divs, strict=True):
        D = D + d
        decay = math.exp(-kappa * D)
        D = decay * D
        for i in range(n):
            e[i] = gamma * lam1 * decay * e[i] + float(g[i])
            r[i] = gamma * lam2 * decay * r[i]
            sign = (e[i] > 0) - (e[i] < 0)
            if (e[i] - r[i]) * sign >= 0:
                r[i] = e[i]
        out.append(
            (torch.tensor(e, dtype=torch.float64), torch.tensor(r, dtype=torch.float64), decay)
        )
    return out


def test_matches_reference_over_many_steps() -> None:
    gen = torch.Generator().manual_seed(0)
    n, steps = 16, 60
    grads = [torch.randn(n, generator=gen, dtype=torch.float64) for _ in range(steps)]
    # mostly small divergences, now and then a large one
    divs = [
        float(torch.rand(1, generator=gen)) * (0.5 if t % 9 == 0 else 0.01) for t in range(steps)
    ]
    ref = reference_traces(grads, divs, 0.99, 0.5, 0.95, 10.0)
    tr = AdaptiveTraces(n, 0.99, (0.5, 0.95), 10.0, dtype=torch.float64)
    for t, (g, d, (e, r, decay)) in enumerate(zip(grads, divs, ref, strict=True)):
        out = tr.step_(g, torch.tensor(d, dtype=torch.float64))
        assert out is tr.r
        torch.testing.assert_close(tr.e, e, rtol=1e-12, atol=1e-13, msg=f"e at step {t + 1}")
        torch.testing.assert_close(tr.r, r, rtol=1e-12, atol=1e-13, msg=f"r at step {t + 1}")
        assert float(tr.last_decay) == pytest.approx(decay, rel=1e-12)


def test_float32_matches_reference() -> None:
    gen = torch.Generator().manual_seed(1)
    grads = [torch.randn(8, generator=gen) for _ in range(30)]
    divs = [0.02 * (t % 3) for t in range(30)]
    ref = reference_traces(grads, divs, 0.99, 0.5, 0.95, 10.0)
    tr = AdaptiveTraces(8)
    for g, d in zip(grads, divs, strict=True):
        tr.step_(g, torch.tensor(d))
    assert tr.r.dtype == torch.float32
    torch.testing.assert_close(tr.e.double(), ref[-1][0], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(tr.r.double(), ref[-1][1], rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize(("kappa", "div"), [(0.0, 0.7), (10.0, 0.0)])
def test_no_divergence_or_kappa_zero_is_plain_accumulating_trace(kappa, div) -> None:
    gen = torch.Generator().manual_seed(2)
    n, steps, gamma, lam1 = 5, 25, 0.9, 0.8
    grads = [torch.randn(n, generator=gen, dtype=torch.float64) for _ in range(steps)]
    tr = AdaptiveTraces(n, gamma, (lam1, 0.95), kappa, dtype=torch.float64)
    for g in grads:
        tr.step_(g, torch.tensor(div, dtype=torch.float64))
    # e_T = sum_t (gamma lambda1)^(T - t) g_t
    closed = sum((gamma * lam1) ** (steps - 1 - t) * g for t, g in enumerate(grads))
    torch.testing.assert_close(tr.e, closed, rtol=1e-12, atol=1e-13)
    assert float(tr.last_decay) == 1.0


def test_large_divergence_cuts_the_traces() -> None:
    tr = AdaptiveTraces(4, dtype=torch.float64)
    gen = torch.Generator().manual_seed(3)
    for _ in range(10):
        tr.step_(torch.randn(4, generator=gen, dtype=torch.float64), torch.tensor(0.001))
    g = torch.tensor([1.0, -2.0, 0.5, 0.0], dtype=torch.float64)
    tr.step_(g, torch.tensor(100.0))  # exp(-1000) == 0: all memory is cut
    assert float(tr.last_decay) == 0.0
    assert torch.equal(tr.e, g)
    assert torch.equal(tr.r, g)
    assert float(tr.D) == 0.0
    tr.step_(g, torch.tensor(math.inf))  # even an infinite divergence gives no NaN
    assert torch.equal(tr.e, g) and torch.equal(tr.r, g)
    assert float(tr.D) == 0.0


def test_divergence_decays_gradually() -> None:
    tr = AdaptiveTraces(1, gamma=1.0, lambdas=(1.0, 1.0), kappa=2.0, dtype=torch.float64)
    tr.step_(torch.zeros(1, dtype=torch.float64), torch.tensor(0.1))
    # D = 0.1, decay = exp(-0.2), D <- 0.1 exp(-0.2)
    assert float(tr.last_decay) == pytest.approx(math.exp(-0.2))
    assert float(tr.D) == pytest.approx(0.1 * math.exp(-0.2))
    tr.step_(torch.zeros(1, dtype=torch.float64), 0.05)  # a float works too
    d = 0.1 * math.exp(-0.2) + 0.05
    assert float(tr.last_decay) == pytest.approx(math.exp(-2 * d))
    assert float(tr.D) == pytest.approx(d * math.exp(-2 * d))


def test_replacing_rule_hand_worked() -> None:
    # gamma = 1, lambdas = (0.5, 1), kappa = 0: e <- 0.5 e + g, r <- r, then
    # r takes e wherever (e - r) sign(e) >= 0.
    tr = AdaptiveTraces(3, gamma=1.0, lambdas=(0.5, 1.0), kappa=0.0, dtype=torch.float64)
    tr.step_(torch.tensor([4.0, -4.0, 2.0], dtype=torch.float64), torch.tensor(0.0))
    # e = [4, -4, 2]; r = 0: (e - 0) sign(e) = |e| >= 0 everywhere -> r = [4, -4, 2]
    assert tr.r.tolist() == [4.0, -4.0, 2.0]
    tr.step_(torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64), torch.tensor(0.0))
    # e = [2 - 1, -2 + 1, 1 + 1] = [1, -1, 2]; r = [4, -4, 2]
    # (e - r) sign(e) = [(1-4)(+1), (-1+4)(-1), (2-2)(+1)] = [-3, -3, 0] -> only the last replaced
    assert tr.e.tolist() == [1.0, -1.0, 2.0]
    assert tr.r.tolist() == [4.0, -4.0, 2.0]
    tr.step_(torch.tensor([9.5, 0.5, -3.0], dtype=torch.float64), torch.tensor(0.0))
    # e = [0.5 + 9.5, -0.5 + 0.5, 1 - 3] = [10, 0, -2]; r = [4, -4, 2]
    # (e - r) sign(e) = [6, 0 (sign 0), (-2 - 2)(-1) = 4] -> all replaced
    assert tr.e.tolist() == [10.0, 0.0, -2.0]
    assert tr.r.tolist() == [10.0, 0.0, -2.0]


def test_reset_zeroes() -> None:
    tr = AdaptiveTraces(6)
    r = tr.step_(torch.ones(6), torch.tensor(0.3))
    assert float(tr.D) > 0 and r.abs().sum() > 0
    tr.reset_()
    assert torch.equal(tr.e, torch.zeros(6)) and torch.equal(tr.r, torch.zeros(6))
    assert float(tr.D) == 0.0 and float(tr.last_decay) == 1.0
    assert r is tr.r  # buffers keep their identity


def test_state_round_trip() -> None:
    gen = torch.Generator().manual_seed(4)
    grads = [torch.randn(10, generator=gen) for _ in range(20)]
    divs = [torch.rand((), generator=gen) * 0.05 for _ in range(20)]
    a = AdaptiveTraces(10)
    for g, d in zip(grads[:10], divs[:10], strict=True):
        a.step_(g, d)
    buf = io.BytesIO()
    torch.save(a.state_dict(), buf)
    buf.seek(0)
    b = AdaptiveTraces(10)
    r_b = b.r
    b.load_state_dict(torch.load(buf, weights_only=True))
    assert b.r is r_b
    for g, d in zip(grads[10:], divs[10:], strict=True):
        assert torch.equal(a.step_(g, d), b.step_(g, d))
    assert torch.equal(a.e, b.e) and torch.equal(a.D, b.D)
    with pytest.raises(ValueError, match="shape"):
        AdaptiveTraces(11).load_state_dict(a.state_dict())


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"numel": 0}, "numel"),
        ({"numel": 2.5}, "numel"),
        ({"gamma": 1.1}, "gamma"),
        ({"gamma": -0.1}, "gamma"),
        ({"lambdas": (0.5, 1.2)}, "lambda2"),
        ({"lambdas": (-0.5, 0.9)}, "lambda1"),
        ({"lambdas": (0.5,)}, "lambdas"),
        ({"kappa": -1.0}, "kappa"),
        ({"kappa": math.inf}, "kappa"),
    ],
)
def test_invalid_arguments(kwargs, name) -> None:
    kwargs = {"numel": 3, **kwargs}
    with pytest.raises(ValueError, match=name):
        AdaptiveTraces(**kwargs)
