"""Tests of the t-soft target update (pporpe.tsoft.TSoftUpdate)."""

from __future__ import annotations

import io
import math

import pytest
import torch

from pporpe.online.torch_engine.tsoft import TSoftUpdate


def reference_tsoft(
    target: torch.Tensor,
    onlines: list[torch.Tensor],
    tau: float,
    nu: float,
    sigma2: float,
) -> tuple[list[torch.Tensor], float, float]:
    """Plain float64 transcription of NOTES.md section 3 (t-soft update)."""
    tb = target.double().clone()
    W = (1 - tau) / tau
    out = []
    for th in onlines:
        th = th.double()
        D2 = float(((th - tb) ** 2).mean())
        w = (nu + 1) / (nu + D2 / sigma2)
        tau_i = w / (W + w)
        tb = (1 - tau_i) * tb + tau_i * th
        tau_s = tau * w * nu / (nu + 1)
        sigma2 = (1 - tau_s) * sigma2 + tau_s * D2
        W = (1 - tau) * (W + w)
        out.append(tb.clone())
    return out, W, sigma2


def walk(n: int, steps: int, seed: int, dtype: torch.dtype = torch.float64) -> list[torch.Tensor]:
    """Online parameters drifting like a learner's, with varying step sizes."""
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(n, generator=gen, dtype=dtype)
    out = []
    for t in range(steps):
        x = x + torch.randn(n, generator=gen, dtype=dtype) * (0.01 if t % 7 else 0.3)
        out.append(x.clone())
    return out


@pytest.mark.parametrize(("tau", "nu"), [(0.3, 1.0), (0.05, 5.0), (1.0, 0.5), (0.7, 1e6)])
def test_matches_reference(tau, nu) -> None:
    n = 40
    target = torch.randn(n, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    onlines = walk(n, 25, seed=1)
    ref, W, sigma2 = reference_tsoft(target, onlines, tau, nu, 1e-2)
    upd = TSoftUpdate(tau=tau, nu=nu, sigma2_init=1e-2)
    tb = target.clone()
    for t, (th, exp) in enumerate(zip(onlines, ref, strict=True)):
        upd.update_(tb, th)
        torch.testing.assert_close(tb, exp, rtol=1e-12, atol=1e-13, msg=f"step {t + 1}")
    assert math.isclose(float(upd.W), W, rel_tol=1e-12, abs_tol=1e-15)
    assert math.isclose(float(upd.sigma2), sigma2, rel_tol=1e-12)


def test_float32_target() -> None:
    n = 1000
    target = torch.randn(n, generator=torch.Generator().manual_seed(2))
    onlines = walk(n, 20, seed=3, dtype=torch.float32)
    ref, _, _ = reference_tsoft(target, onlines, 0.3, 1.0, 1e-2)
    upd = TSoftUpdate()
    tb = target.clone()
    for th in onlines:
        upd.update_(tb, th)
    assert tb.dtype == torch.float32
    torch.testing.assert_close(tb.double(), ref[-1], rtol=1e-5, atol=1e-5)


def test_nu_inf_is_exactly_polyak() -> None:
    n = 30
    target = torch.randn(n, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    upd = TSoftUpdate(tau=0.3, nu=math.inf)
    tb, ref = target.clone(), target.clone()
    for th in walk(n, 20, seed=5):
        upd.update_(tb, th)
        ref = (1 - 0.3) * ref + 0.3 * th
        assert torch.isfinite(tb).all()
        torch.testing.assert_close(tb, ref, rtol=1e-14, atol=1e-15)
    # the adaptive scalars are untouched (they do not enter the update)
    assert float(upd.W) == pytest.approx(0.7 / 0.3)
    assert float(upd.sigma2) == 1e-2


def test_outlier_moves_target_less_than_polyak() -> None:
    n = 200
    gen = torch.Generator().manual_seed(6)
    base = torch.randn(n, generator=gen, dtype=torch.float64)
    tsoft, polyak = TSoftUpdate(0.3, 1.0), TSoftUpdate(0.3, math.inf)
    tb_t, tb_p = base.clone(), base.clone()
    for _ in range(30):  # small, regular changes: sigma2 adapts to them
        th = base + 0.01 * torch.randn(n, generator=gen, dtype=torch.float64)
        tsoft.update_(tb_t, th)
        polyak.update_(tb_p, th)
    outlier = base + 10.0 * torch.randn(n, generator=gen, dtype=torch.float64)
    before_t, before_p = tb_t.clone(), tb_p.clone()
    tsoft.update_(tb_t, outlier)
    polyak.update_(tb_p, outlier)
    move_t = float((tb_t - before_t).norm())
    move_p = float((tb_p - before_p).norm())
    assert move_t < 0.01 * move_p
    # ... while an ordinary step moves it at a rate comparable to tau
    th = tb_t + 0.01 * torch.randn(n, generator=gen, dtype=torch.float64)
    before = tb_t.clone()
    tsoft.update_(tb_t, th)
    assert float((tb_t - before).norm()) > 0.05 * float((th - before).norm())


def test_identical_vectors_leave_target_unchanged() -> None:
    x = torch.randn(50, generator=torch.Generator().manual_seed(7))
    tb = x.clone()
    upd = TSoftUpdate()
    for _ in range(3000):  # long enough for sigma2 to reach its floor
        upd.update_(tb, x)
    assert torch.equal(tb, x)
    assert float(upd.sigma2) == pytest.approx(1e-12)
    assert math.isfinite(float(upd.W))
    # and it still reacts (no NaN, no frozen target) when the online vector moves
    y = x + 1e-3
    for _ in range(200):
        upd.update_(tb, y)
    assert torch.isfinite(tb).all()
    torch.testing.assert_close(tb, y, rtol=0, atol=1e-5)


def test_tau_one_copies() -> None:
    upd = TSoftUpdate(tau=1.0, nu=2.0)
    tb = torch.zeros(5)
    th = torch.arange(5.0)
    upd.update_(tb, th)
    assert torch.equal(tb, th)


def test_state_round_trip() -> None:
    n = 20
    onlines = walk(n, 30, seed=8)
    a = TSoftUpdate(0.2, 3.0)
    tb = torch.zeros(n, dtype=torch.float64)
    for th in onlines[:15]:
        a.update_(tb, th)
    buf = io.BytesIO()
    torch.save(a.state_dict(), buf)
    buf.seek(0)
    b = TSoftUpdate(0.2, 3.0)
    b.load_state_dict(torch.load(buf, weights_only=True))
    tb2 = tb.clone()
    for th in onlines[15:]:
        a.update_(tb, th)
        b.update_(tb2, th)
    assert torch.equal(tb, tb2)
    assert torch.equal(a.W, b.W) and torch.equal(a.sigma2, b.sigma2)
    with pytest.raises(ValueError, match="nu"):
        TSoftUpdate(0.2, 1.0).load_state_dict(a.state_dict())


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"tau": 0.0}, "tau"),
        ({"tau": 1.5}, "tau"),
        ({"tau": float("nan")}, "tau"),
        ({"nu": 0.0}, "nu"),
        ({"nu": -1.0}, "nu"),
        ({"sigma2_init": 0.0}, "sigma2_init"),
        ({"sigma2_init": math.inf}, "sigma2_init"),
        ({"sigma2_min": -1.0}, "sigma2_min"),
        ({"sigma2_min": 1.0}, "sigma2_min"),
    ],
)
def test_invalid_arguments(kwargs, name) -> None:
    with pytest.raises(ValueError, match=name):
        TSoftUpdate(**kwargs)
