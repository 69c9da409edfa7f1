"""The choices that make pporpe's online learner the author's test bed (``TESTBED``):
the score weighted by the clipped ratio, the time limit as a termination, the scale floor.
Each against a float64 reference written here, a hand-worked case or an identity."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from tiny import ACT, OBS
from tiny import population as pop
from tiny import small_config as cfg

from pporpe.nn.mlp import mlp
from pporpe.online import config as config_module
from pporpe.online.config import AUTHOR_CHOICES, TESTBED, TESTBED_WEIGHTS, OnlineConfig
from pporpe.online.population import ENGINES, PopulationLearner


def student_t_logp64(raw: torch.Tensor, u: torch.Tensor, min_scale: float) -> torch.Tensor:
    """log of the product of univariate student-t densities, written out in float64:
    raw = [loc, scale_raw, df_raw], scale = softplus + min_scale, df = softplus + 2."""
    d = u.shape[-1]
    loc, scale_raw, df_raw = raw[:d], raw[d : 2 * d], raw[2 * d]
    scale = torch.log1p(torch.exp(scale_raw)) + min_scale
    df = torch.log1p(torch.exp(df_raw)) + 2.0
    y = (u - loc) / scale
    per_dim = (
        torch.lgamma((df + 1) / 2)
        - torch.lgamma(df / 2)
        - 0.5 * torch.log(df * math.pi)
        - torch.log(scale)
        - (df + 1) / 2 * torch.log1p(y * y / df)
    )
    return per_dim.sum()


def grad_logp64(p: PopulationLearner, k: int, obs: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """d log pi(u|s) / d theta_policy of member k in float64, through torch.nn modules."""
    c = p.configs[k]
    net = mlp(OBS, p.head.raw_dim, c.layers, c.units, c.layer_norm, c.activation).double()
    n_pol = len(p.lay.real_index[0])
    torch.nn.utils.vector_to_parameters(p.member_theta(k)[:n_pol].double(), net.parameters())
    raw = net(obs.double().view(1, OBS))[0]
    logp = student_t_logp64(raw, u.double().view(ACT), c.min_scale)
    grads = torch.autograd.grad(logp, list(net.parameters()))
    return torch.cat([g.reshape(-1) for g in grads])


def clipped_weight64(ratio: float, adv: float, eps: float) -> float:
    """The test bed's weight sign(A) min(sign(A) rho, sign(A) clip(rho, 1 - eps, 1 + eps))."""
    s = 1.0 if adv > 0 else -1.0
    return s * min(s * ratio, s * min(max(ratio, 1.0 - eps), 1.0 + eps))


def one_step(p: PopulationLearner, log_ratio_shift: list[float]) -> tuple:
    """One transition for every member with the same state, action and reward; the
    behaviour log-density shifted per member so that rho = exp(shift) at the first step."""
    K = p.K
    u = torch.tensor([[0.4, -0.7]]).repeat(K, 1)
    obs0 = np.tile(np.array([[0.1, -0.2, 0.3]]), (K, 1))
    p.begin_episode(range(K), obs0, forced_u=u)
    p.state.pending.logp_b.sub_(torch.tensor(log_ratio_shift))  # test hook: rho = exp(shift)
    theta_before = [p.member_theta(k).clone() for k in range(K)]
    no = np.zeros(K, dtype=bool)
    stats, _ = p.step(np.full(K, 0.8), np.ones((K, OBS)), no, no, forced_u=u)
    return stats, theta_before, torch.as_tensor(obs0[0], dtype=torch.float32), u[0]


def policy_gradient_of(p: PopulationLearner, k: int) -> torch.Tensor:
    """This step's policy gradient per unit of A: the torch engine's ``grad`` buffer (the
    fused engine keeps it in scratch; tests/test_fused.py holds it to the torch engine)."""
    return p.state.grad[0, k].reshape(-1)[p.lay.real_index[0]].double()


@pytest.mark.parametrize("shift", [0.4, -0.4, 0.02])
def test_weighted_score_is_the_clipped_weight_times_the_score(shift: float) -> None:
    """g = -w grad log pi per unit of A, w the test bed's clipped weight (float64 reference)."""
    p = pop([cfg(method="ppo", policy_gradient="weighted_score", layer_norm_affine=True)], [3],
            engine="torch")  # fmt: skip
    stats, theta, obs, u = one_step(p, [shift])
    ratio, adv = float(stats.ratio[0]), float(stats.adv[0])
    assert ratio == pytest.approx(math.exp(shift), rel=1e-5)
    p_ref = pop([cfg(method="ppo", layer_norm_affine=True)], [3])
    p_ref.set_member_theta(0, theta[0])
    expected = -clipped_weight64(ratio, adv, 0.1) * grad_logp64(p_ref, 0, obs, u)
    torch.testing.assert_close(policy_gradient_of(p, 0), expected, rtol=2e-4, atol=1e-7)


def test_weighted_score_differs_from_the_surrogate_only_where_the_clip_acts() -> None:
    """Two members each with the same parameters and transition: where rho is inside the
    clip the two gradients are equal (grad rho = rho grad log pi); where it is clipped PPO's
    surrogate gives 0 and the weighted score w grad log pi with |w| = 1 +- eps."""
    shifts = [0.02, 0.4, -0.4]
    configs = [cfg(method="ppo", policy_gradient=pg) for pg in ("surrogate", "weighted_score")]
    p = pop([c for c in configs for _ in shifts], [5] * (2 * len(shifts)), engine="torch")
    stats, *_ = one_step(p, shifts * 2)
    clipped = 0
    for j, _shift in enumerate(shifts):
        sur, wsc = policy_gradient_of(p, j), policy_gradient_of(p, j + len(shifts))
        ratio, adv = float(stats.ratio[j]), float(stats.adv[j])
        w = clipped_weight64(ratio, adv, 0.1)
        if w == ratio:
            torch.testing.assert_close(sur, wsc, rtol=1e-4, atol=1e-8)
        else:
            clipped += 1
            assert torch.count_nonzero(sur) == 0
            assert abs(w) == pytest.approx(1.1 if ratio > 1 else 0.9)
            assert torch.count_nonzero(wsc) > 0
    assert clipped >= 1  # one of rho = exp(+-0.4) is clipped whatever the sign of A


def test_time_limit_terminal_drops_the_bootstrap_at_a_truncation_only() -> None:
    """Hand-worked: at a truncation delta differs by exactly gamma V_target(s_{t+1});
    at a termination and at an ordinary step the two choices are equal."""
    for term, trunc, equal in ((False, True, False), (True, False, True), (False, False, True)):
        p = pop([cfg(), cfg(time_limit="terminal")], [7, 7])
        u = torch.tensor([[0.2, 0.1]]).repeat(2, 1)
        p.begin_episode([0, 1], np.zeros((2, OBS)), forced_u=u)
        nxt = np.full((2, OBS), 0.5)
        v_next = float(p.value(nxt)[0])  # the target equals the online network at the start
        s, _ = p.step(np.full(2, 1.0), nxt, np.full(2, term), np.full(2, trunc), forced_u=u)
        gap = float(s.delta[0].double() - s.delta[1].double())
        if equal:
            assert gap == 0.0
        else:
            assert gap == pytest.approx(0.99 * v_next, rel=1e-5, abs=1e-8)


def test_min_scale_is_the_heads_floor() -> None:
    """scale = softplus(raw) + min_scale: at raw = -200 softplus underflows, scale is the floor."""
    raw = torch.zeros(2 * ACT + 1)
    raw[ACT : 2 * ACT] = -200.0
    for floor in (1e-3, 1e-8):
        p = pop([cfg(min_scale=floor)], [0])
        _, scale, _ = p.head.split(raw)  # type: ignore[misc]
        assert torch.all(scale == torch.tensor(floor, dtype=torch.float32))
    raw[ACT : 2 * ACT] = 0.5
    _, scale, _ = p.head.split(raw)  # type: ignore[misc]
    torch.testing.assert_close(scale, torch.full((ACT,), math.log1p(math.exp(0.5)) + 1e-8))


def test_members_must_share_the_scale_floor() -> None:
    with pytest.raises(ValueError, match="min_scale"):
        pop([cfg(), cfg(min_scale=1e-8)], [0, 1])


@pytest.mark.parametrize(
    ("field", "value"),
    [("policy_gradient", "score"), ("time_limit", "truncate"), ("min_scale", 0.0),
     ("min_scale", math.inf)],
)  # fmt: skip
def test_bad_testbed_choice_is_refused_by_name(field: str, value: object) -> None:
    with pytest.raises(ValueError, match=field):
        OnlineConfig(**{field: value})  # type: ignore[arg-type]


def test_testbed_preset_is_the_test_beds_learner() -> None:
    """Every field of TESTBED is a valid OnlineConfig field, documented in the preset's
    docstring; the values that follow from the test bed's constructor are right."""
    c = OnlineConfig(**TESTBED)  # type: ignore[arg-type]
    assert set(AUTHOR_CHOICES) | set(TESTBED_WEIGHTS) <= set(TESTBED)
    assert (c.method, c.eps, c.lr, c.layers, c.units) == ("ppo", 0.1, 1e-4, 5, 128)
    assert (c.lambdas, c.kappa, c.tau) == ((0.5, 0.9), 1.0, 1.0)
    # the test bed's reward scale (1 - gamma)(1 - w b) and 0.025 = w b b = w b (1 - b)
    w, b = 0.1, 0.5
    assert c.effective_reward_scale == pytest.approx((1 - c.gamma) * (1 - w * b))
    assert c.beta_td == pytest.approx(w * b * b) and c.beta_de == pytest.approx(w * b * (1 - b))
    source = Path(config_module.__file__ or "").read_text()
    preset_doc = source.split("TESTBED: Mapping")[1].split('"""')[1]
    for name in set(TESTBED) - set(AUTHOR_CHOICES) - set(TESTBED_WEIGHTS):
        assert f"``{name}=" in preset_doc, f"TESTBED's docstring does not explain {name}"


@pytest.mark.parametrize("engine", ENGINES)
def test_tau_one_keeps_the_target_equal_to_the_online_network(engine: str) -> None:
    """The test bed has no target network; t-soft with tau = 1 moves the target onto the
    online value network at every step (identity, bitwise)."""
    p = pop([cfg(tau=1.0)], [9], engine=engine)
    u = torch.tensor([[0.1, 0.3]])
    p.begin_episode([0], np.zeros((1, OBS)), forced_u=u)
    no = np.zeros(1, dtype=bool)
    rng = np.random.default_rng(0)
    for _ in range(5):
        p.step(np.array([rng.normal()]), rng.normal(size=(1, OBS)), no, no, forced_u=u)
        assert torch.equal(p.state.params[2, 0], p.state.params[1, 0])


def _segments64(lay: object, parts: tuple[int, ...]) -> list[tuple[list[int], int]]:
    """The test bed's parameter tensors of one policy network, written out here: every
    hidden tensor of the layout, then the output layer as one (weight, bias) per part;
    each as (flat positions in the padded layout, element count)."""
    units = lay.units  # type: ignore[attr-defined]
    segs = [(list(range(s.offset, s.offset + s.real[0])), s.real[0])
            for s in lay.slots[:-2]]  # type: ignore[attr-defined]  # fmt: skip
    w0, b0, first = lay.out_w.offset, lay.out_b.offset, 0  # type: ignore[attr-defined]
    weights, biases = [], []
    for n in parts:
        weights.append((list(range(w0 + first * units, w0 + (first + n) * units)), n * units))
        biases.append((list(range(b0 + first, b0 + first + n)), n))
        first += n
    return segs + weights + biases


def test_split_head_t_momentum_is_per_part_against_a_float64_reference() -> None:
    """One td-AmsProp step with the policy output as three tensors (location, scale, dof):
    the momentum of every element equals TLaProp's rule computed per tensor in float64,
    w = (n + k n) / (k n + |gv - m|^2) over that tensor's n elements, m += w/(W+w) (gv - m)."""
    from pporpe.nn.batched import NetLayout
    from pporpe.online.torch_engine.update import update_chunk

    parts = (2, 2, 1)
    lay = NetLayout(3, 5, 2, 8, True, head_parts=parts)
    R, U, S, K = lay.n_rows, lay.units, lay.n_seg, 1
    gen = torch.Generator().manual_seed(0)
    real = torch.zeros(2, K, R * U)
    real[0, 0, lay.real_index[0]] = 1.0
    real[1, 0, lay.real_index[1]] = 1.0
    real = real.view(2, K, R, U)
    G = torch.randn(2, K, R, U, generator=gen) * real
    m = torch.randn(2, K, R, U, generator=gen) * real * 0.5
    W = torch.rand(2, K, S, generator=gen) + 1.0
    k_dof = 1.0
    n = torch.tensor(lay.segments, dtype=torch.float32).T.reshape(2, 1, S)
    num, den = n * (1 + k_dof), torch.where(n > 0, n * k_dof, 1.0)
    beta2, eps = 0.999, 1e-8
    sqrt_bc2 = torch.tensor([math.sqrt(1 - beta2)])
    P = torch.zeros(3, K, R, U)
    z = torch.zeros(K)
    m0, W0 = m.clone().double(), W.clone().double()
    update_chunk(
        P, G, torch.zeros_like(G), torch.zeros_like(G), torch.zeros_like(G), torch.zeros_like(G),
        m, W, torch.ones(2, K), z, z, torch.full((K,), beta2), torch.full((K,), 1 - beta2),
        torch.ones(K), sqrt_bc2, torch.full((K,), eps), torch.zeros(K, dtype=torch.bool),
        torch.full((K,), 0.1), torch.full((K,), 1 - 1 / 0.9), num, den, torch.full((K,), 1e-3),
        torch.ones(K, dtype=torch.bool), lay.row_seg, lay.col_seg, lay.bias_row,
    )  # fmt: skip
    q = G[0, 0].double().reshape(-1)
    gv = q / (torch.sqrt((1 - beta2) * q * q) / math.sqrt(1 - beta2) + eps)
    d = gv - m0[0, 0].reshape(-1)
    expected = m0[0, 0].reshape(-1).clone()
    segs = _segments64(lay, parts)
    assert len(segs) == S
    for j, (idx, count) in enumerate(segs):
        w = (count + k_dof * count) / (k_dof * count + float((d[idx] ** 2).sum()))
        expected[idx] += w / (float(W0[0, 0, j]) + w) * d[idx]
    torch.testing.assert_close(m[0, 0].reshape(-1).double(), expected, rtol=1e-5, atol=1e-7)
    # the joint head pools the three parts' sums: the same buffers give other numbers there
    joint = NetLayout(3, 5, 2, 8, True)
    assert joint.n_seg == S - 4 and joint.col_seg is None


def test_split_head_changes_only_the_output_layer_at_first() -> None:
    """Joint and split heads on the same data: after the first update (t-momentum weight
    1 for any tensor) they differ by rounding in the output layer only; after the second
    the output layer differs by far more than rounding, and far more than the rest."""
    configs = [cfg(method="ppo", head_tensors=h) for h in ("joint", "per_output")]
    joint, split = pop(configs[:1], [11]), pop(configs[1:], [11])
    assert split.lay.n_seg == joint.lay.n_seg + 4
    u = torch.tensor([[0.3, -0.2]])
    no = np.zeros(1, dtype=bool)
    rng = np.random.default_rng(1)
    obs = [rng.normal(size=(1, OBS)) for _ in range(3)]
    for p in (joint, split):
        p.begin_episode([0], obs[0], forced_u=u)
    out = torch.zeros(joint.lay.n_rows, dtype=torch.bool)
    out[joint.lay.out_w.offset // joint.lay.units :] = True
    gaps = []
    for step in (1, 2):
        for p in (joint, split):
            p.step(np.array([0.5]), obs[step], no, no, forced_u=u)
        gap = (joint.state.params[0, 0] - split.state.params[0, 0]).abs()
        gaps.append((float(gap[out].max()), float(gap[~out].max())))
    (out1, rest1), (out2, rest2) = gaps
    assert rest1 == 0.0 and out1 < 1e-6
    assert out2 > 100 * max(out1, 1e-9) and out2 > 100 * max(rest2, 1e-9)
