"""The learner choices where pporpe 0.2 and the author's test bed differ (issue: learning
fidelity): each formula against a float64 reference or a hand-worked case, and the
defaults unchanged (pporpe 0.2's numbers)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from tiny import ACT, OBS
from tiny import baseline_config as cfg
from tiny import population as pop
from torch.distributions import Normal, kl_divergence

from pporpe.advantages import regularized_advantage, td_error
from pporpe.nn.batched import forward_chain
from pporpe.nn.policies import NormalHead, StudentTHead
from pporpe.online.config import BASELINE_CHOICES, TESTBED_WEIGHTS, OnlineConfig
from pporpe.online.population import PopulationLearner
from pporpe.surrogates import surrogate_objective


# pporpe 0.2's learner choices pinned: the reference learner implements them, and each
# choice's test compares it against them.
def drive(p: PopulationLearner, steps: int, seed: int = 0, forced: bool = True) -> list:
    """The same transitions (and, with ``forced``, the same actions) for every member."""
    rng = np.random.default_rng(seed)
    K = p.K
    u0 = torch.as_tensor(rng.normal(size=(1, ACT)), dtype=torch.float32).repeat(K, 1)
    p.begin_episode(range(K), np.zeros((K, OBS)), forced_u=u0 if forced else None)
    out = []
    for _ in range(steps):
        obs = np.repeat(rng.normal(size=(1, OBS)), K, 0)
        u = torch.as_tensor(rng.normal(size=(1, ACT)), dtype=torch.float32).repeat(K, 1)
        no = np.zeros(K, dtype=bool)
        stats, _ = p.step(np.full(K, rng.normal()), obs, no, no, forced_u=u if forced else None)
        out.append(stats)
    return out


def test_td_units_hand_worked() -> None:
    delta, logp = (
        torch.tensor([0.02], dtype=torch.float64),
        torch.tensor([-1.2], dtype=torch.float64),
    )
    scaled = regularized_advantage(delta, logp, 0.01, 0.01, 0.01)
    unscaled = regularized_advantage(delta, logp, 0.01, 0.01, 0.01, td_scale=1.0 / 0.01)
    # 0.02 - 0.01 (0.01 * 0.02^2 + 0.01 * -1.2) and 0.02 - 0.01 (0.01 * 2^2 + 0.01 * -1.2)
    assert float(scaled) == pytest.approx(0.02011996, abs=1e-12)
    assert float(unscaled) == pytest.approx(0.01972, abs=1e-12)


def test_testbed_weights_give_the_test_beds_regularised_td_error() -> None:
    """The test bed's signal, written here in float64 from its description: one weight
    w = 0.1 and balance b = 0.5; delta = (1 - g)(1 - w b) r + g V' - V, then
    delta += (1 - g) w b (-(b (delta / (1 - g))^2 + (1 - b) log pi)). pporpe's
    td_error and regularized_advantage with TESTBED_WEIGHTS and the unscaled TD units
    give the same numbers."""
    rng = np.random.default_rng(3)
    r, v, v_next, logp = (rng.normal(size=64) for _ in range(4))
    g, w, b = 0.99, 0.1, 0.5
    raw = (1 - g) * (1 - w * b) * r + g * v_next - v
    expected = raw + (1 - g) * w * b * (-(b * (raw / (1 - g)) ** 2 + (1 - b) * logp))
    t = {k: torch.as_tensor(x, dtype=torch.float64) for k, x in zip("rvnl", (r, v, v_next, logp))}
    config = OnlineConfig(**TESTBED_WEIGHTS)
    discount = torch.tensor(g, dtype=torch.float64)
    delta = td_error(t["r"] * config.effective_reward_scale, t["n"], t["v"], discount)
    adv = regularized_advantage(
        delta, t["l"], 1 - g, config.beta_td, config.beta_de, td_scale=1 / (1 - g)
    )
    np.testing.assert_allclose(adv.numpy(), expected, rtol=1e-12, atol=1e-15)
    assert config.td_units == "unscaled"  # the defaults' units, which the formula needs


def test_testbed_weights_in_the_learner() -> None:
    """Two members with the same parameters and transition, the paper's weights and the
    test bed's: the first step's delta differs by the reward scale alone, and A by the
    weights, with log pi recovered from the first member's A (float64)."""
    paper, testbed = cfg(td_units="unscaled"), cfg(td_units="unscaled", **TESTBED_WEIGHTS)
    p = pop([paper, testbed], [0, 0])
    u = torch.tensor([[0.3, -1.1]])
    p.begin_episode([0, 1], np.zeros((2, OBS)), forced_u=u.repeat(2, 1))
    no = np.zeros(2, dtype=bool)
    reward = 0.7
    s, _ = p.step(np.full(2, reward), np.ones((2, OBS)), no, no, forced_u=u.repeat(2, 1))
    (d0, d1), (a0, a1), c = s.delta.double(), s.adv.double(), 0.01  # c = 1 - gamma
    assert float(d1 - d0) == pytest.approx(reward * (0.0095 - 0.01), rel=1e-4)
    log_pi = ((d0 - a0) / c - 0.01 * (d0 / c) ** 2) / 0.01
    expected = d1 - c * (0.025 * (d1 / c) ** 2 + 0.025 * log_pi)
    assert float(a1) == pytest.approx(float(expected), rel=1e-4, abs=1e-7)


def test_td_units_in_the_learner() -> None:
    """At the first step both members have the same parameters and delta: A differs by
    exactly the TD penalty's units, (1 - gamma) beta_TD delta^2 (1/(1-gamma)^2 - 1)."""
    p = pop([cfg(), cfg(td_units="unscaled")], [0, 0])
    (s, *_) = drive(p, 1)
    d = s.delta.double()
    assert torch.equal(s.delta[0], s.delta[1])
    expected = 0.01 * 0.01 * d[0] ** 2 * (1.0 / 0.01**2 - 1.0)
    assert float(s.adv[0] - s.adv[1]) == pytest.approx(float(expected), rel=1e-4, abs=1e-9)


def test_entropy_density_in_the_learner() -> None:
    """The pre-squash density drops the map's Jacobian: A differs by (1 - gamma) beta_DE
    log|da/du| at the same step."""
    p = pop([cfg(), cfg(entropy_density="pre_squash")], [0, 0])
    u = torch.tensor([[0.3, -1.1]])
    p.begin_episode([0, 1], np.zeros((2, OBS)), forced_u=u.repeat(2, 1))
    jac = p.action_map.log_abs_det_jacobian(u.double())[0]
    no = np.zeros(2, dtype=bool)
    s, _ = p.step(np.zeros(2), np.ones((2, OBS)), no, no, forced_u=u.repeat(2, 1))
    # A_action = ... - (1-g) b (logp - jac); A_pre = ... - (1-g) b logp
    expected = -0.01 * 0.01 * float(jac)
    assert float(s.adv[1] - s.adv[0]) == pytest.approx(expected, rel=1e-4)


def student_kl_reference(p: tuple, q: tuple) -> float:
    """Float64 normal-gamma KL of two diagonal student-t (loc, scale, df), written anew."""
    (mp, sp, dp), (mq, sq, dq) = p, q
    total = 0.0
    for a, b, c, d in zip(mp, sp, mq, sq):
        v = (b / d) ** 2
        total += 0.5 * (v + ((a - c) / d) ** 2 - 1.0 - math.log(v))
    ddf = dq * (math.log(dp) - math.log(dq)) - 2 * (math.lgamma(dp / 2) - math.lgamma(dq / 2))
    ddf += (dp - dq) * (float(torch.digamma(torch.tensor(dp / 2, dtype=torch.float64))) - 1.0)
    return total + 0.5 * ddf


def raw_student(loc: list[float], scale: list[float], df: float) -> torch.Tensor:
    inv_sp = [s - 1e-3 + math.log(-math.expm1(-(s - 1e-3))) for s in scale]
    d = df - 2.0
    return torch.tensor([*loc, *inv_sp, d + math.log(-math.expm1(-d))], dtype=torch.float64)


def test_student_t_kl_against_reference_and_limits() -> None:
    head = StudentTHead(2)
    p = ([0.1, -0.4], [0.7, 1.3], 4.0)
    q = ([-0.2, 0.5], [1.1, 0.6], 9.0)
    got = float(head.kl(raw_student(*p), raw_student(*q)))
    assert got == pytest.approx(student_kl_reference(p, q), rel=1e-9)
    assert float(head.kl(raw_student(*p), raw_student(*p))) == pytest.approx(0.0, abs=1e-12)
    # large df on both sides: the Gaussian KL
    big_p, big_q = (p[0], p[1], 1e6), (q[0], q[1], 1e6)
    gauss = kl_divergence(
        Normal(torch.tensor(p[0]), torch.tensor(p[1])),
        Normal(torch.tensor(q[0]), torch.tensor(q[1])),
    ).sum()
    assert float(head.kl(raw_student(*big_p), raw_student(*big_q))) == pytest.approx(
        float(gauss), rel=1e-5
    )


def test_normal_kl_equals_torch() -> None:
    head = NormalHead(2)
    raw_p = torch.tensor([0.1, -0.4, 0.3, -0.2], dtype=torch.float64)
    raw_q = torch.tensor([-0.2, 0.5, -0.7, 0.4], dtype=torch.float64)
    lp, sp = head.split(raw_p)
    lq, sq = head.split(raw_q)
    ref = kl_divergence(Normal(lp, sp), Normal(lq, sq)).sum()
    assert float(head.kl(raw_p, raw_q)) == pytest.approx(float(ref), rel=1e-12)


def test_analytic_trace_divergence_in_the_learner() -> None:
    """At step 2 the divergence is relu(KL(pi_theta1 || pi_theta0)) at s_1 plus half the
    squared value change, from the stored baseline and the current parameters."""
    p = pop([cfg(trace_divergence="analytic", lr=1e-2)], [3])
    drive(p, 1)
    raw_b, value_b, obs = (
        p.state.pending.raw_b.clone(),
        p.state.pending.value_b.clone(),
        p.state.pending.obs.clone(),
    )
    out, _ = forward_chain(p._flat(2), obs.view(1, 1, OBS).repeat(2, 1, 1), p.lay, "swish")
    raw_now, v_now = out[0, 0].double(), out[1, 0, 0].double()
    kl = max(float(p.head.kl(raw_now, raw_b[0].double())), 0.0)
    expected = kl + 0.5 * float(v_now - value_b[0].double()) ** 2
    no = np.zeros(1, dtype=bool)
    s, _ = p.step(np.zeros(1), np.ones((1, OBS)), no, no)
    assert float(s.divergence[0]) == pytest.approx(expected, rel=1e-4, abs=1e-9)
    assert expected > 0.0


def test_a_checkpoint_without_raw_b_is_refused_by_the_analytic_divergence() -> None:
    """Without pi_b's raw output the first KL after resuming would be against a made-up
    policy: refused, with the way out; the sample divergence does not need it."""
    p = pop([cfg(trace_divergence="analytic")], [3])
    drive(p, 1)
    state = p.member_state(0)
    del state["pending"]["raw_b"]
    with pytest.raises(ValueError, match=r"no raw_b.*trace_divergence='sample'"):
        pop([cfg(trace_divergence="analytic")], [3]).load_member_state(
            0, cfg(trace_divergence="analytic"), state
        )
    pop([cfg()], [3]).load_member_state(0, cfg(), state)  # the 0.2 divergence: fine


def test_amsgrad_maximum_raw_or_bias_corrected() -> None:
    """With decay 1 the maximum is the running max of the raw second moment ("raw") or,
    stored scaled by the bias correction, bc2_t times the running max of v_t / bc2_t."""
    p = pop([cfg(amsgrad_decay=1.0, amsgrad_max="raw"), cfg(amsgrad_decay=1.0)], [1, 1])
    beta2 = 0.999
    rng = np.random.default_rng(5)
    p.begin_episode([0, 1], np.zeros((2, OBS)))
    best_raw = best_hat = None
    no = np.zeros(2, dtype=bool)
    for t in range(1, 8):
        p.step(np.full(2, rng.normal()), np.repeat(rng.normal(size=(1, OBS)), 2, 0), no, no)
        v_raw, v_cor = p.state.opt_v[:, 0].double(), p.state.opt_v[:, 1].double()
        best_raw = v_raw if best_raw is None else torch.maximum(best_raw, v_raw)
        bc2 = 1 - beta2**t
        best_hat = v_cor / bc2 if best_hat is None else torch.maximum(best_hat, v_cor / bc2)
        torch.testing.assert_close(p.state.opt_vmax[:, 0].double(), best_raw, rtol=1e-6, atol=1e-12)
        torch.testing.assert_close(
            p.state.opt_vmax[:, 1].double(), bc2 * best_hat, rtol=1e-5, atol=1e-12
        )


def test_critic_signal_actor_is_the_gradient_of_the_authors_critic_loss() -> None:
    """With lambda = 0, the value block receives grad[-A rho_dagger V(s_t)] (rho_dagger
    detached); the TD choice receives grad[delta^2 / 2]-style delta * grad[-V]."""
    p = pop([cfg(critic_signal="actor", lambdas=(0.0, 0.0), method="ppo", lr=1e-2)], [2],
            engine="torch")  # the torch engine's grad buffer; test_fused.py: fused = torch
    drive(p, 1)
    obs = p.state.pending.obs.clone()
    flat = p.state.params[1, 0].reshape(1, -1).clone().requires_grad_(True)
    out, _ = forward_chain(flat, obs.view(1, 1, OBS), p.lay, "swish")
    v = out[0, 0, 0]
    (grad_v,) = torch.autograd.grad(v, flat)
    no = np.zeros(1, dtype=bool)
    s, _ = p.step(np.zeros(1), np.ones((1, OBS)), no, no)
    adv = s.adv[:1].double()
    rho_dagger = float(surrogate_objective("ppo", s.ratio[:1].double(), adv) / adv)
    assert rho_dagger != 1.0
    received = s.adv[0] * p.state.grad[1, 0].reshape(-1)
    expected = -float(s.adv[0]) * rho_dagger * grad_v[0]
    torch.testing.assert_close(received, expected, rtol=1e-4, atol=1e-7)


def test_frozen_layer_norm_keeps_scale_and_shift() -> None:
    p = pop([cfg(layer_norm_affine=False), cfg()], [4, 4])
    rows = p.lay.norm_rows
    before = p.state.params[:2, :, rows].clone()
    drive(p, 5)
    assert torch.equal(p.state.params[:2, 0, rows], before[:, 0])
    assert not torch.equal(p.state.params[:2, 1, rows], before[:, 1])
    assert torch.all(p.state.params[:2, 0, rows[0::2]] == 1.0) and torch.all(
        p.state.params[:2, 0, rows[1::2]] == 0.0
    )


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("td_units", "raw"),
        ("entropy_density", "bounded"),
        ("critic_signal", "value"),
        ("trace_divergence", "exact"),
        ("amsgrad_max", "max"),
        ("layer_norm_affine", 1),
    ],
)
def test_bad_choice_is_refused_by_name(field: str, value: object) -> None:
    with pytest.raises(ValueError, match=field):
        OnlineConfig(**{field: value})  # type: ignore[arg-type]


def test_defaults_are_the_authors_choices_but_the_two_the_ablation_rejected() -> None:
    """pporpe 0.4's defaults are the author's test-bed choices except the critic signal
    and the entropy density (DEFAULT_CHOICES); AUTHOR_CHOICES is pporpe 0.3's learner and
    BASELINE_CHOICES pporpe 0.2's, each differing from the defaults where it should."""
    from pporpe.online.config import AUTHOR_CHOICES, DEFAULT_CHOICES

    assert set(AUTHOR_CHOICES) == set(BASELINE_CHOICES) == set(DEFAULT_CHOICES)
    default = OnlineConfig()
    assert {k: getattr(default, k) for k in DEFAULT_CHOICES} == dict(DEFAULT_CHOICES)
    assert (default.critic_signal, default.entropy_density) == ("td", "action")
    author = OnlineConfig(**AUTHOR_CHOICES)  # type: ignore[arg-type]
    differs = {k for k in AUTHOR_CHOICES if getattr(author, k) != getattr(default, k)}
    assert differs == {"critic_signal", "entropy_density"}
    old = OnlineConfig(**BASELINE_CHOICES)  # type: ignore[arg-type]
    differs = {k for k in BASELINE_CHOICES if getattr(old, k) != getattr(default, k)}
    assert differs == set(BASELINE_CHOICES) - {"critic_signal", "entropy_density"}


def test_run_folders_written_before_the_choices_existed_keep_what_they_ran_with(
    tmp_path: Path,
) -> None:
    """A config.json without the choice fields (pporpe 0.1.0, early 0.2) is read with the
    values that run used, not with today's defaults; a complete one is read as written."""
    import json

    from pporpe.runs.folder import read_config

    fixture = Path(__file__).parent / "fixtures" / "run_v0_1_online" / "config.json"
    data = json.loads(fixture.read_text())
    # The fixture predates the six choice fields (amsgrad_decay existed: 0.999).
    assert set(BASELINE_CHOICES) & set(data["learner"]) == {"amsgrad_decay"}
    assert data["learner"]["amsgrad_decay"] == 0.999
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "config.json").write_text(json.dumps(data))
    _, cfg = read_config(tmp_path / "old")
    assert {k: getattr(cfg.learner, k) for k in BASELINE_CHOICES} == dict(BASELINE_CHOICES)
    data["learner"]["critic_signal"] = "actor"  # written explicitly: kept
    (tmp_path / "old" / "config.json").write_text(json.dumps(data))
    _, cfg = read_config(tmp_path / "old")
    assert cfg.learner.critic_signal == "actor" and cfg.learner.td_units == "scaled"
