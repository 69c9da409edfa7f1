"""Tests of td-AmsProp (pporpe.optim.TDAmsProp) against independent references."""

from __future__ import annotations

import copy
import io
import math
from collections.abc import Sequence

import pytest
import torch

from pporpe.online.torch_engine.optim import TDAmsProp, _fused_works

FUSED_MODES = [None, False]  # fused kernel where usable / always eager


def reference_tdamsprop(
    p0: torch.Tensor,
    grads: Sequence[torch.Tensor],
    segments: Sequence[int],
    lr: float,
    beta1: float,
    beta2: float,
    eps: float,
    k_dof: float,
    decay: float,
) -> list[torch.Tensor]:
    """Plain per-segment float64 transcription of NOTES.md section 3; params after each step."""
    p = [s.clone().double() for s in p0.double().split(list(segments))]
    v = [torch.zeros_like(s) for s in p]
    vmax = [torch.zeros_like(s) for s in p]
    m = [torch.zeros_like(s) for s in p]
    W = [beta1 / (1 - beta1) for _ in p]
    out = []
    for t, g_full in enumerate(grads, start=1):
        for i, g in enumerate(g_full.double().split(list(segments))):
            n = g.numel()
            v[i] = beta2 * v[i] + (1 - beta2) * g * g
            v_hat = v[i] / (1 - beta2**t)
            vmax[i] = torch.maximum(decay * vmax[i], v_hat)
            gv = g / (vmax[i].sqrt() + eps)
            if beta1 == 0.0:
                m[i] = gv
            else:
                if math.isinf(k_dof):
                    w = 1.0
                else:
                    dof = k_dof * n
                    w = (n + dof) / (dof + float(((gv - m[i]) ** 2).sum()))
                b = W[i] / (W[i] + w)
                m[i] = b * m[i] + (1 - b) * gv
                W[i] = (2 - 1 / beta1) * W[i] + w
            p[i] = p[i] - lr / (1 - beta1**t) * m[i]
        out.append(torch.cat(p))
    return out


def reference_laprop(
    p0: torch.Tensor,
    grads: Sequence[torch.Tensor],
    lr: float,
    beta1: float,
    beta2: float,
    eps: float,
) -> list[torch.Tensor]:
    """Plain LaProp (Ziyin et al. 2020), float64."""
    p = p0.clone().double()
    v = torch.zeros_like(p)
    m = torch.zeros_like(p)
    out = []
    for t, g in enumerate(grads, start=1):
        g = g.double()
        v = beta2 * v + (1 - beta2) * g * g
        v_hat = v / (1 - beta2**t)
        m = beta1 * m + (1 - beta1) * g / (v_hat.sqrt() + eps)
        p = p - lr / (1 - beta1**t) * m
        out.append(p.clone())
    return out


def random_grads(n: int, steps: int, seed: int, dtype: torch.dtype = torch.float64) -> list:
    gen = torch.Generator().manual_seed(seed)
    # varying scale so that v_hat goes up and down and vmax matters
    return [
        torch.randn(n, generator=gen, dtype=dtype)
        * (0.1 + 2.0 * float(torch.rand(1, generator=gen)))
        for _ in range(steps)
    ]


def run(opt: TDAmsProp, p: torch.nn.Parameter, grads: Sequence[torch.Tensor]) -> list:
    out = []
    for g in grads:
        p.grad = g.to(p.dtype).clone()
        opt.step()
        out.append(p.detach().clone())
    return out


SEGMENTS = [7, 1, 30, 3, 12, 64, 2]


@pytest.mark.parametrize("fused", FUSED_MODES)
@pytest.mark.parametrize(
    ("k_dof", "decay", "betas"),
    [
        (1.0, 0.999, (0.9, 0.999)),
        (0.3, 1.0, (0.8, 0.99)),
        (5.0, 0.0, (0.95, 0.9)),
        (1.0, 0.5, (0.0, 0.99)),
        (math.inf, 0.999, (0.9, 0.999)),
    ],
)
def test_matches_reference_over_steps(fused, k_dof, decay, betas) -> None:
    n = sum(SEGMENTS)
    p0 = torch.randn(n, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    grads = random_grads(n, 20, seed=2)
    kw = dict(lr=0.01, betas=betas, eps=1e-6, k_dof=k_dof, amsgrad_decay=decay)
    ref = reference_tdamsprop(p0, grads, SEGMENTS, 0.01, *betas, 1e-6, k_dof, decay)
    p = torch.nn.Parameter(p0.clone())
    opt = TDAmsProp([p], segments=SEGMENTS, fused=fused, **kw)
    got = run(opt, p, grads)
    # the default mode really exercises the fused kernel where it is available
    assert opt._cache[p].fused_ok is (fused is None and _fused_works(torch.float64))
    for t, (a, b) in enumerate(zip(got, ref, strict=True)):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12, msg=f"step {t + 1}")


@pytest.mark.parametrize("fused", FUSED_MODES)
def test_float32_matches_reference(fused) -> None:
    n = sum(SEGMENTS)
    p0 = torch.randn(n, generator=torch.Generator().manual_seed(3))
    grads = random_grads(n, 20, seed=4, dtype=torch.float32)
    ref = reference_tdamsprop(p0, grads, SEGMENTS, 0.01, 0.9, 0.999, 1e-8, 1.0, 0.999)
    p = torch.nn.Parameter(p0.clone())
    got = run(TDAmsProp([p], lr=0.01, segments=SEGMENTS, fused=fused), p, grads)
    assert got[-1].dtype == torch.float32
    torch.testing.assert_close(got[-1].double(), ref[-1], rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("fused", FUSED_MODES)
def test_k_dof_inf_is_laprop(fused) -> None:
    n = 50
    p0 = torch.randn(n, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    grads = random_grads(n, 20, seed=6)
    ref = reference_laprop(p0, grads, lr=0.02, beta1=0.9, beta2=0.99, eps=1e-8)
    p = torch.nn.Parameter(p0.clone())
    opt = TDAmsProp(
        [p], lr=0.02, betas=(0.9, 0.99), eps=1e-8, k_dof=math.inf, amsgrad_decay=0.0, fused=fused
    )
    got = run(opt, p, grads)
    for a, b in zip(got, ref, strict=True):
        assert torch.isfinite(a).all()
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-14)
    # with segments too, and W stays at its fixed point beta1 / (1 - beta1)
    p2 = torch.nn.Parameter(p0.clone())
    opt2 = TDAmsProp([p2], 0.02, (0.9, 0.99), 1e-8, math.inf, 0.0, segments=[10, 40], fused=fused)
    torch.testing.assert_close(run(opt2, p2, grads)[-1], ref[-1], rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(opt2.state[p2]["W"], torch.full((2,), 9.0, dtype=torch.float64))


@pytest.mark.parametrize("fused", FUSED_MODES)
def test_amsgrad_decay_one_keeps_vmax_non_decreasing(fused) -> None:
    n = 20
    p = torch.nn.Parameter(torch.zeros(n, dtype=torch.float64))
    opt = TDAmsProp([p], betas=(0.9, 0.5), amsgrad_decay=1.0, fused=fused)
    gen = torch.Generator().manual_seed(7)
    prev = torch.zeros(n, dtype=torch.float64)
    for t in range(40):
        scale = 10.0 if t < 5 else 0.01  # large gradients first, then small: v_hat falls
        p.grad = torch.randn(n, generator=gen, dtype=torch.float64) * scale
        opt.step()
        vmax = opt.vmax(p)
        assert (vmax >= prev * (1 - 1e-12)).all()
        prev = vmax
    # whereas a decaying maximum does come down
    q = torch.nn.Parameter(torch.zeros(n, dtype=torch.float64))
    opt_d = TDAmsProp([q], betas=(0.9, 0.5), amsgrad_decay=0.9, fused=fused)
    gen = torch.Generator().manual_seed(7)
    for t in range(40):
        q.grad = torch.randn(n, generator=gen, dtype=torch.float64) * (10.0 if t < 5 else 0.01)
        opt_d.step()
    assert (opt_d.vmax(q) < 0.1 * opt.vmax(p)).all()


@pytest.mark.parametrize("fused", FUSED_MODES)
def test_hand_worked_first_step(fused) -> None:
    # p = [1, 2], g = [0.5, -1], lr = 0.1, betas = (0.9, 0.999), eps = 0.5, k_dof = 1 (one segment)
    # v = 0.001 g^2 = [0.00025, 0.001];  v_hat = g^2 = [0.25, 1];  vmax = v_hat
    # gv = g / (|g| + 0.5) = [0.5, -2/3];  ||gv - m||^2 = 0.25 + 4/9 = 25/36
    # n = 2, dof = 2: w = 4 / (2 + 25/36) = 144/97
    # W_0 = 0.9/0.1 = 9:  b = 9 / (9 + 144/97) = 873/1017,  m = (1 - b) gv = (144/1017) gv
    # W_1 = (2 - 1/0.9) 9 + 144/97 = 8 + 144/97
    # p <- p - lr/(1 - 0.9) m = p - m = [1 - 72/1017, 2 + 96/1017]
    p = torch.nn.Parameter(torch.tensor([1.0, 2.0], dtype=torch.float64))
    opt = TDAmsProp([p], lr=0.1, betas=(0.9, 0.999), eps=0.5, k_dof=1.0, fused=fused)
    p.grad = torch.tensor([0.5, -1.0], dtype=torch.float64)
    opt.step()
    exp = torch.tensor([1 - 72 / 1017, 2 + 96 / 1017], dtype=torch.float64)
    torch.testing.assert_close(p.detach(), exp, rtol=1e-13, atol=1e-15)
    st = opt.state[p]
    torch.testing.assert_close(st["v"], torch.tensor([0.00025, 0.001], dtype=torch.float64))
    torch.testing.assert_close(
        st["m"], torch.tensor([0.5, -2 / 3], dtype=torch.float64) * 144 / 1017
    )
    torch.testing.assert_close(float(st["W"][0]), 8 + 144 / 97, rtol=1e-13, atol=0)
    torch.testing.assert_close(opt.vmax(p), torch.tensor([0.25, 1.0], dtype=torch.float64))
    assert int(st["step"]) == 1


@pytest.mark.parametrize("fused", FUSED_MODES)
def test_outlier_moves_momentum_less_than_laprop(fused) -> None:
    n = 100
    gen = torch.Generator().manual_seed(8)
    grads = [torch.randn(n, generator=gen, dtype=torch.float64) for _ in range(30)]
    outlier = torch.full((n,), 1e3, dtype=torch.float64)
    moves = {}
    for k in (1.0, math.inf):
        p = torch.nn.Parameter(torch.zeros(n, dtype=torch.float64))
        opt = TDAmsProp([p], k_dof=k, fused=fused)
        run(opt, p, grads)
        m_before = opt.state[p]["m"].clone()
        run(opt, p, [outlier])
        moves[k] = float((opt.state[p]["m"] - m_before).norm())
    assert moves[1.0] < 0.1 * moves[math.inf]


@pytest.mark.parametrize("fused", FUSED_MODES)
def test_state_dict_round_trip_continues_identically(fused) -> None:
    n = sum(SEGMENTS)
    grads = random_grads(n, 20, seed=9, dtype=torch.float32)
    p = torch.nn.Parameter(torch.randn(n, generator=torch.Generator().manual_seed(10)))
    opt = TDAmsProp([p], lr=0.01, segments=SEGMENTS, fused=fused)
    run(opt, p, grads[:10])
    buf = io.BytesIO()
    torch.save(opt.state_dict(), buf)
    q = torch.nn.Parameter(p.detach().clone())
    opt2 = TDAmsProp([q], lr=0.5, segments=[n], fused=fused)  # options come from the checkpoint
    buf.seek(0)
    opt2.load_state_dict(torch.load(buf, weights_only=True))
    assert opt2.param_groups[0]["lr"] == 0.01
    assert set(opt2.state[q]) == {"step", "v", "vmax_scaled", "m", "W"}
    a = run(opt, p, grads[10:])
    b = run(opt2, q, grads[10:])
    for x, y in zip(a, b, strict=True):
        assert torch.equal(x, y)
    assert int(opt2.state[q]["step"]) == 20
    # a deep copy of a used optimizer continues identically too (and keeps `fused`)
    p4 = copy.deepcopy(p)
    opt3 = TDAmsProp([p4], lr=0.01, segments=SEGMENTS, fused=fused)
    opt3.load_state_dict(opt.state_dict())  # in-process load: no tensors shared with opt
    assert all(a is not b for a, b in zip(opt3.state[p4].values(), opt.state[p].values()))
    opt4 = copy.deepcopy(opt3)
    assert opt4._fused_allowed is (fused is not False)
    q4 = opt4.param_groups[0]["params"][0]
    c3, c4 = run(opt3, p4, grads[:5]), run(opt4, q4, grads[:5])
    for x, y in zip(c3, c4, strict=True):
        assert torch.equal(x, y)


def test_multi_tensor_params_equal_flat_segments() -> None:
    gen = torch.Generator().manual_seed(11)
    a0 = torch.randn(3, 4, generator=gen, dtype=torch.float64)
    b0 = torch.randn(4, generator=gen, dtype=torch.float64)
    a, b = torch.nn.Parameter(a0.clone()), torch.nn.Parameter(b0.clone())
    flat = torch.nn.Parameter(torch.cat([a0.view(-1), b0]))
    opt_multi = TDAmsProp([a, b], lr=0.01)
    opt_flat = TDAmsProp([flat], lr=0.01, segments=[12, 4])
    for g in random_grads(16, 15, seed=12):
        a.grad, b.grad = g[:12].view(3, 4).clone(), g[12:].clone()
        flat.grad = g.clone()
        opt_multi.step()
        opt_flat.step()
    torch.testing.assert_close(torch.cat([a.detach().view(-1), b.detach()]), flat.detach())


def test_non_contiguous_grad_and_missing_grad() -> None:
    gen = torch.Generator().manual_seed(13)
    p0 = torch.randn(4, 3, generator=gen, dtype=torch.float64)
    p, q = torch.nn.Parameter(p0.clone()), torch.nn.Parameter(p0.clone())
    unused = torch.nn.Parameter(torch.ones(2, dtype=torch.float64))
    opt_p, opt_q = TDAmsProp([p, unused], lr=0.01), TDAmsProp([q], lr=0.01)
    for _ in range(5):
        g = torch.randn(3, 4, generator=gen, dtype=torch.float64).t()  # non-contiguous
        assert not g.is_contiguous()
        p.grad, q.grad = g, g.contiguous()
        opt_p.step()
        opt_q.step()
    torch.testing.assert_close(p.detach(), q.detach(), rtol=1e-12, atol=1e-14)
    assert torch.equal(unused.detach(), torch.ones(2, dtype=torch.float64))
    assert len(opt_p.state[unused]) == 0


@pytest.mark.skipif(not _fused_works(torch.float32), reason="fused kernel unavailable")
def test_fused_and_eager_paths_agree_float32() -> None:
    n = sum(SEGMENTS)
    grads = random_grads(n, 30, seed=14, dtype=torch.float32)
    p0 = torch.randn(n, generator=torch.Generator().manual_seed(15))
    outs = []
    for fused in (True, False):
        p = torch.nn.Parameter(p0.clone())
        opt = TDAmsProp([p], lr=0.01, segments=SEGMENTS, fused=fused)
        assert opt._cache.get(p) is None
        outs.append(run(opt, p, grads)[-1])
        assert opt._cache[p].fused_ok is fused
    torch.testing.assert_close(outs[0], outs[1], rtol=1e-5, atol=1e-6)


def test_minimises_a_quadratic() -> None:
    gen = torch.Generator().manual_seed(16)
    scales = torch.rand(10, generator=gen) * 10 + 0.1
    target = torch.randn(10, generator=gen)
    x = torch.nn.Parameter(torch.zeros(10))
    opt = TDAmsProp([x], lr=0.05, segments=[4, 6])
    first = None
    for _ in range(600):
        opt.zero_grad()
        loss = 0.5 * (scales * (x - target) ** 2).sum()
        loss.backward()
        first = float(loss.detach()) if first is None else first
        opt.step()
    assert float(0.5 * (scales * (x.detach() - target) ** 2).sum()) < 1e-4 * first
    torch.testing.assert_close(x.detach(), target, atol=5e-3, rtol=0)


def test_closure_is_called() -> None:
    x = torch.nn.Parameter(torch.ones(3))
    opt = TDAmsProp([x])

    def closure() -> float:
        opt.zero_grad()
        loss = (x**2).sum()
        loss.backward()
        return float(loss.detach())

    assert opt.step(closure) == 3.0
    assert (x.detach() < 1).all()


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"lr": 0.0}, "lr"),
        ({"lr": -1e-3}, "lr"),
        ({"lr": float("nan")}, "lr"),
        ({"betas": (1.0, 0.999)}, "beta1"),
        ({"betas": (-0.1, 0.999)}, "beta1"),
        ({"betas": (0.9, 1.0)}, "beta2"),
        ({"betas": (0.9, -0.5)}, "beta2"),
        ({"betas": (0.9,)}, "betas"),
        ({"eps": 0.0}, "eps"),
        ({"eps": -1e-8}, "eps"),
        ({"k_dof": 0.0}, "k_dof"),
        ({"k_dof": -1.0}, "k_dof"),
        ({"k_dof": float("nan")}, "k_dof"),
        ({"amsgrad_decay": -0.1}, "amsgrad_decay"),
        ({"amsgrad_decay": 1.5}, "amsgrad_decay"),
        ({"segments": [5, 0, 5]}, "segments"),
        ({"segments": [5, 4]}, "segments"),
        ({"segments": [5, 5.0]}, "segments"),
        ({"segments": []}, "segments"),
        ({"fused": "yes"}, "fused"),
    ],
)
def test_invalid_arguments_raise_value_error(kwargs, name) -> None:
    p = torch.nn.Parameter(torch.zeros(10))
    with pytest.raises(ValueError, match=name):
        TDAmsProp([p], **kwargs)


def test_error_message_gives_value_and_range() -> None:
    with pytest.raises(ValueError, match=r"amsgrad_decay must be in \[0.0, 1.0\], got 1.5"):
        TDAmsProp([torch.nn.Parameter(torch.zeros(2))], amsgrad_decay=1.5)


def test_segments_need_one_flat_param() -> None:
    with pytest.raises(ValueError, match="segments"):
        TDAmsProp([torch.nn.Parameter(torch.zeros(2, 5))], segments=[5, 5])
    with pytest.raises(ValueError, match="segments"):
        TDAmsProp(
            [torch.nn.Parameter(torch.zeros(5)), torch.nn.Parameter(torch.zeros(5))],
            segments=[5, 5],
        )
    opt = TDAmsProp([torch.nn.Parameter(torch.zeros(3))])
    with pytest.raises(ValueError, match="lr"):  # groups added later are validated too
        opt.add_param_group({"params": [torch.nn.Parameter(torch.zeros(3))], "lr": -1.0})
    assert len(opt.param_groups) == 1


def test_inf_and_extremes_are_finite() -> None:
    p = torch.nn.Parameter(torch.zeros(6))
    opt = TDAmsProp([p], k_dof=math.inf, amsgrad_decay=1.0, segments=[3, 3])
    for _ in range(3):
        p.grad = torch.zeros(6)  # vmax == 0: gv = 0 / eps = 0, no NaN
        opt.step()
    assert torch.equal(p.detach(), torch.zeros(6))
    p.grad = torch.tensor([1e30, -1e30, 0.0, 1.0, -1.0, 0.5])
    opt.step()
    assert torch.isfinite(p.detach()).all()
