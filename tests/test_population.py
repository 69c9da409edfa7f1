"""PopulationLearner: hand backward, equivalence with the scalar reference, isolated members."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import scipy.stats
import torch
from reference_online import ReferenceLearner as OnlineLearner
from tiny import ACT, HIGH, LOW, OBS
from tiny import baseline_config as cfg
from tiny import population as pop

from pporpe.nn.batched import NetLayout, backward_row0, forward_chain
from pporpe.online.noise import NoiseBank, polar_student_t
from pporpe.online.population import ENGINES, PopulationLearner

torch.set_num_threads(1)


# pporpe 0.2's learner choices pinned: the reference learner implements them, and each
# choice's test compares it against them.
def data(n: int, seed: int = 1, episode: int = 100) -> list[tuple[float, np.ndarray, bool, bool]]:
    """Transitions; episode ends alternate between truncation and termination."""
    rng = np.random.default_rng(seed)
    out = []
    for t in range(n):
        end = t % episode == episode - 1
        term = end and (t // episode) % 2 == 1
        out.append((float(rng.normal()), rng.normal(size=OBS).astype(np.float32), term, end))
    return out


def run_pop(p: PopulationLearner, trans: list, obs0: np.ndarray, **kw: object) -> list:
    """Feed the same transitions to every member; restart episodes at their ends."""
    K = p.K
    stats, actions = [], [p.begin_episode(range(K), np.stack([obs0] * K))]
    for r, o, term, trunc in trans:
        s, a = p.step(np.full(K, r), np.stack([o] * K), np.full(K, term), np.full(K, trunc), **kw)
        stats.append(s)
        actions.append(a)
        if term or trunc:
            actions.append(p.begin_episode(range(K), np.stack([obs0] * K)))
    return stats, actions


# ------------------------------------------------------------------------------- (a)
@pytest.mark.parametrize("K", [1, 3])
@pytest.mark.parametrize("layer_norm", [True, False])
@pytest.mark.parametrize("activation", ["swish", "relu", "tanh"])
def test_hand_backward_equals_autograd(K: int, layer_norm: bool, activation: str) -> None:
    gen = torch.Generator().manual_seed(K)
    lay = NetLayout(5, 9, 3, 16, layer_norm)
    flat = torch.randn(3 * K, lay.n_pad, generator=gen) * 0.4
    x = torch.randn(3 * K, 2, 5, generator=gen)
    dout = torch.randn(2 * K, 9, generator=gen)
    out, cache = forward_chain(flat, x, lay, activation, keep=2 * K)
    assert cache is not None
    grad = torch.zeros(2 * K, lay.n_pad)
    backward_row0(flat, grad, dout, cache, lay, activation)
    leaf = flat.clone().requires_grad_(True)
    out2, _ = forward_chain(leaf, x, lay, activation)
    (out2[: 2 * K, 0] * dout).sum().backward()
    assert leaf.grad is not None
    torch.testing.assert_close(out, out2, rtol=0, atol=0)
    scale = leaf.grad.abs().max()
    assert (grad - leaf.grad[: 2 * K]).abs().max() <= 1e-6 * max(1.0, float(scale))


def test_layout_matches_mlp_module() -> None:
    """Forward of a packed member equals the torch module it was built from."""
    p = pop([cfg()], [4])
    torch.manual_seed(4)
    ref = OnlineLearner(OBS, LOW, HIGH, cfg())
    x = torch.randn(5, OBS)
    raw, _ = forward_chain(p.state.params[0].reshape(1, -1), x.unsqueeze(0), p.lay, "swish")
    torch.testing.assert_close(raw[0], ref.policy_raw(x), rtol=1e-6, atol=1e-6)
    assert torch.equal(p.member_theta(0), ref.theta.detach())
    assert torch.equal(p.member_target(0), ref.target)


# ------------------------------------------------------------------------------- (b)
@pytest.mark.parametrize("method", ["rpe", "spo"])
@pytest.mark.parametrize("engine", ENGINES)
def test_member_equals_reference_online_learner(engine: str, method: str) -> None:
    member = cfg(lr=1e-3, method=method)
    others = [cfg(method="ppo", lr=3e-3, kappa=0.0), cfg(method="rb", nu=float("inf"))]
    torch.manual_seed(5)
    ref = OnlineLearner(OBS, LOW, HIGH, member)
    p = pop([others[0], member, others[1]], [1, 5, 2], engine=engine)
    rng = np.random.default_rng(0)
    forced = {"u": torch.zeros(1, ACT)}

    def fake_sample(raw: torch.Tensor) -> torch.Tensor:
        forced["u"] = torch.tensor(rng.normal(size=(1, ACT)), dtype=torch.float32)
        return forced["u"].clone()

    ref.head.sample = fake_sample  # type: ignore[method-assign]
    obs0 = np.zeros(OBS, np.float32)
    ref.begin_episode(obs0)
    p.begin_episode([0, 1, 2], np.stack([obs0] * 3), forced_u=forced["u"].repeat(3, 1))
    drift = []
    for t, (r, o, term, trunc) in enumerate(data(300)):
        s, _ = ref.step(r, o, term, trunc)
        z = np.full(3, term), np.full(3, trunc)
        ps, _ = p.step(np.full(3, r), np.stack([o] * 3), *z, forced_u=forced["u"].repeat(3, 1))
        drift.append(float((p.member_theta(1) - ref.theta.detach()).abs().max()))
        if t == 0:
            assert drift[0] <= 1e-6
            for name in ("delta", "adv", "ratio", "divergence", "trace_decay"):
                torch.testing.assert_close(getattr(ps, name)[1], getattr(s, name))
        if term or trunc:
            ref.begin_episode(obs0)
            p.begin_episode([0, 1, 2], np.stack([obs0] * 3), forced_u=forced["u"].repeat(3, 1))
    # how far the parameters moved from their initial values, for scale
    total = float(
        (p.member_theta(1) - pop([member], [5], engine=engine).member_theta(0)).abs().max()
    )
    print(
        f"\nmax abs drift vs the scalar reference: step 1 {drift[0]:.2e}, "
        f"step 100 {drift[99]:.2e}, step 300 {drift[-1]:.2e}, max {max(drift):.2e}; "
        f"parameter change {total:.2e}"
    )
    assert max(drift) < 1e-3 * max(total, 1e-3)
    tgt = float((p.member_target(1) - ref.target).abs().max())
    assert tgt < 1e-3 * max(total, 1e-3)


# ------------------------------------------------------------------------------- (c)
def test_methods_differ_and_ratio_departs_from_one() -> None:
    configs = [cfg(method=m, lr=3e-2) for m in ("ppo", "rb", "rpe", "spo")]
    p = pop(configs, [0, 0, 0, 0])
    stats, _ = run_pop(p, data(30), np.zeros(OBS, np.float32))
    th = [p.member_theta(k) for k in range(4)]
    for i, j in itertools.combinations(range(4), 2):
        assert not torch.allclose(th[i], th[j]), (i, j)
    assert torch.allclose(stats[0].ratio, torch.ones(4), atol=1e-6)
    later = torch.stack([s.ratio for s in stats[1:]])
    assert torch.all((later - 1.0).abs() > 1e-6)


# ------------------------------------------------------------------------------- (d)
@pytest.mark.parametrize("engine", ENGINES)
def test_non_finite_member_is_isolated(engine: str) -> None:
    configs = [cfg(), cfg(method="ppo"), cfg(method="rb")]
    a, b = pop(configs, [0, 1, 2], engine=engine), pop(configs, [0, 1, 2], engine=engine)
    obs = np.zeros((3, OBS), np.float32)
    a.begin_episode([0, 1, 2], obs)
    b.begin_episode([0, 1, 2], obs)
    z = np.zeros(3, bool)
    for t, (r, o, _, _) in enumerate(data(12, episode=1000)):
        rew = np.full(3, r)
        b.step(rew, np.stack([o] * 3), z, z)
        if t == 4:
            rew[1] = np.nan
        a.step(rew, np.stack([o] * 3), z, z)
    assert a.finite().tolist() == [True, False, True]
    assert b.finite().all()
    for k in (0, 2):
        assert torch.equal(a.state.params[:, k], b.state.params[:, k])
        assert torch.equal(a.state.opt_m[:, k], b.state.opt_m[:, k])
        assert torch.equal(a.state.trace_e[:, k], b.state.trace_e[:, k])


# ------------------------------------------------------------------------------- (e)
@pytest.mark.parametrize("df", [2.1, 5.0, 50.0])
def test_student_t_sampler_matches_torch(df: float) -> None:
    bank = NoiseBank(1, 4, block=5000)
    bank.reset(0, 123)
    pts = bank.buf[0].reshape(-1, 2)
    ours = polar_student_t(pts, torch.tensor(df, dtype=torch.float64)).numpy()
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        ref = torch.distributions.StudentT(df).sample((20000,)).double().numpy()
    assert scipy.stats.ks_2samp(ours, ref).pvalue > 1e-3
    assert scipy.stats.kstest(ours, scipy.stats.t(df).cdf).pvalue > 1e-3
    qs = [0.01, 0.1, 0.5, 0.9, 0.99]
    ours_q = np.quantile(ours, qs)
    np.testing.assert_allclose(ours_q, scipy.stats.t(df).ppf(qs), rtol=0.1, atol=0.03)
    np.testing.assert_allclose(ours_q, np.quantile(ref, qs), rtol=0.1, atol=0.03)


def test_learner_samples_follow_its_head() -> None:
    """The population's sampler at a fixed state-dependent (loc, scale, df)."""
    p = pop([cfg()], [0], compile_update=False)
    bank = NoiseBank(1, ACT, block=20000)
    bank.reset(0, 7)
    raw = torch.tensor([[0.5, -1.0, 0.3, -0.2, 1.5]]).expand(20000, 5)  # df = softplus + 2
    u = p._sample(raw, bank.buf[0])
    loc, scale, df = p.head.split(raw[:1])
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        ref = torch.distributions.StudentT(df[0, 0], loc[0], scale[0]).sample((20000,))
    for d in range(ACT):
        assert scipy.stats.ks_2samp(u[:, d].numpy(), ref[:, d].numpy()).pvalue > 1e-3


# ------------------------------------------------------------------------------- (f)
@pytest.mark.parametrize("engine", ENGINES)
def test_member_does_not_depend_on_slot_or_K(engine: str) -> None:
    member = cfg(lr=3e-3)
    one = pop([member], [11], engine=engine)
    four = pop(
        [cfg(method="ppo"), cfg(lr=1e-2), member, cfg(method="rb")], [1, 2, 11, 3], engine=engine
    )
    assert torch.equal(one.noise.buf[0], four.noise.buf[2])
    trans = data(60, episode=25)
    _, a1 = run_pop(one, trans, np.zeros(OBS, np.float32))
    _, a4 = run_pop(four, trans, np.zeros(OBS, np.float32))
    acts1 = np.stack([a[0] for a in a1])
    acts4 = np.stack([a[2] for a in a4])
    np.testing.assert_allclose(acts1, acts4, rtol=0, atol=1e-5)
    assert one.noise.pos[0] == four.noise.pos[2]
    diff = float((one.member_theta(0) - four.member_theta(2)).abs().max())
    assert diff < 1e-5
    if engine == "fused":  # one member's loop, the same code in every slot: bitwise
        assert np.array_equal(acts1, acts4) and diff == 0.0


# ------------------------------------------------------------------------------- (g)
def _member_snapshot(p: PopulationLearner, k: int) -> list[torch.Tensor]:
    """Every tensor of member k's checkpoint (its slice of the state, its noise stream)
    and its noise position, flattened."""

    def leaves(x: object) -> list[torch.Tensor]:
        if isinstance(x, dict):
            return [t for v in x.values() for t in leaves(v)]
        return [] if x is None else [torch.as_tensor(x)]

    return [*leaves(p.member_state(k)), torch.tensor([int(p.noise.pos[k])])]


@pytest.mark.parametrize("engine", ENGINES)
def test_inactive_member_is_bitwise_unchanged(engine: str) -> None:
    p = pop([cfg(), cfg(method="ppo"), cfg(method="rb")], [0, 1, 2], engine=engine)
    p.begin_episode([0, 1, 2], np.zeros((3, OBS), np.float32))
    z = np.zeros(3, bool)
    for r, o, _, _ in data(3):
        p.step(np.full(3, r), np.stack([o] * 3), z, z)
    before = _member_snapshot(p, 1)
    active = np.array([True, False, True])
    for r, o, _, _ in data(5, seed=3):
        obs = np.stack([o] * 3)
        obs[1] = np.nan
        p.step(np.array([r, np.nan, r]), obs, z, z, active=active)
    after = _member_snapshot(p, 1)
    assert all(torch.equal(x, y) for x, y in zip(before, after, strict=True))
    assert p.finite().all()


@pytest.mark.parametrize("engine", ENGINES)
def test_member_state_round_trip_continues_bitwise(engine: str) -> None:
    configs = [cfg(), cfg(method="ppo", lr=1e-3), cfg(method="rb")]
    a = pop(configs, [0, 1, 2], engine=engine)
    obs0 = np.zeros(OBS, np.float32)
    run_pop(a, data(20, episode=20), obs0)  # ends at an episode boundary
    state = a.member_state(1)
    b = pop([cfg(method="rpe"), cfg(), cfg(lr=1e-2)], [7, 8, 9], engine=engine)
    b.load_member_state(1, configs[1], state)
    assert torch.equal(b.member_theta(1), a.member_theta(1))
    trans = data(30, seed=5, episode=15)
    _, acts_a = run_pop(a, trans, obs0)
    _, acts_b = run_pop(b, trans, obs0)
    assert np.array_equal(np.stack([x[1] for x in acts_a]), np.stack([x[1] for x in acts_b]))
    sa, sb = _member_snapshot(a, 1), _member_snapshot(b, 1)
    assert all(torch.equal(x, y) for x, y in zip(sa, sb, strict=True))


@pytest.mark.parametrize("engine", ENGINES)
def test_population_state_dict_round_trip_continues_bitwise(engine: str) -> None:
    """The whole population's state_dict, mid-episode, into a population built with the
    same configs and other seeds: both go on with the same numbers, bitwise."""
    configs = [cfg(), cfg(method="ppo", lr=1e-3), cfg(method="rb")]
    a = pop(configs, [0, 1, 2], engine=engine)
    obs0 = np.zeros(OBS, np.float32)
    K = a.K
    a.begin_episode(range(K), np.stack([obs0] * K))
    for r, o, _, _ in data(7, seed=2):  # mid-episode: a transition is pending
        a.step(np.full(K, r), np.stack([o] * K), np.zeros(K, bool), np.zeros(K, bool))
    saved = a.state_dict()
    assert "grad" not in saved["state"] and saved["state"]["pending.waiting"].all()
    b = pop(configs, [7, 8, 9], engine=engine)
    b.load_state_dict(saved)
    for r, o, term, trunc in data(12, seed=5, episode=6):
        step = (np.full(K, r), np.stack([o] * K), np.full(K, term), np.full(K, trunc))
        (sa, xa), (sb, xb) = a.step(*step), b.step(*step)
        assert np.array_equal(xa, xb) and torch.equal(sa.delta, sb.delta)
        if term or trunc:
            assert np.array_equal(a.begin_episode(range(K), np.stack([obs0] * K)),
                                  b.begin_episode(range(K), np.stack([obs0] * K)))  # fmt: skip
    after_a, after_b = a.state.state_dict(), b.state.state_dict()
    assert all(torch.equal(after_a[n], after_b[n]) for n in after_a)
    # the saved copy is a copy: the run went on without changing it
    assert not torch.equal(saved["state"]["params"], after_a["params"])


def test_population_state_dict_rejects_another_shape() -> None:
    a = pop([cfg(), cfg()], [0, 1])
    saved = a.state.state_dict()
    b = pop([cfg()], [0])
    with pytest.raises(ValueError, match=r"state_dict\['params'\] has shape"):
        b.state.load_state_dict(saved)
    with pytest.raises(ValueError, match="missing \\['decay'\\]"):
        a.state.load_state_dict({n: t for n, t in saved.items() if n != "decay"})
    with pytest.raises(ValueError, match="holds 2 members; this has 1"):
        b.load_state_dict(a.state_dict())


# ------------------------------------------------------------------------------- (h)
@pytest.mark.parametrize("engine", ENGINES)
def test_reset_member_equals_fresh_population(engine: str) -> None:
    p = pop([cfg(), cfg(method="ppo"), cfg(method="rb")], [0, 1, 2], engine=engine)
    run_pop(p, data(10), np.zeros(OBS, np.float32))
    new = cfg(method="rpe", lr=2e-3, kappa=0.0)
    p.reset_member(1, new, 42)
    fresh = pop([new], [42], engine=engine)
    s1, s0 = _member_snapshot(p, 1), _member_snapshot(fresh, 0)
    assert all(torch.equal(x, y) for x, y in zip(s1, s0, strict=True))
    assert torch.equal(p.noise.buf[1], fresh.noise.buf[0])
    assert torch.equal(p.noise.block_state[1], fresh.noise.block_state[0])
    trans = data(20, seed=9)
    _, ap = run_pop(p, trans, np.zeros(OBS, np.float32))
    _, af = run_pop(fresh, trans, np.zeros(OBS, np.float32))
    np.testing.assert_allclose(
        np.stack([x[1] for x in ap]), np.stack([x[0] for x in af]), rtol=0, atol=1e-5
    )
    assert float((p.member_theta(1) - fresh.member_theta(0)).abs().max()) < 1e-5


# ------------------------------------------------------------------------------- misc
def test_compiled_update_matches_eager() -> None:
    configs = [cfg(method=m, lr=1e-2) for m in ("ppo", "rpe")]
    e, c = pop(configs, [0, 1]), pop(configs, [0, 1], compile_update=True)
    trans = data(8)
    _, ae = run_pop(e, trans, np.zeros(OBS, np.float32))
    _, ac = run_pop(c, trans, np.zeros(OBS, np.float32))
    np.testing.assert_allclose(np.stack(ae), np.stack(ac), rtol=0, atol=1e-5)
    torch.testing.assert_close(c.state.params, e.state.params, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(c.state.opt_m, e.state.opt_m, rtol=1e-4, atol=1e-6)


def test_normal_head_and_no_layer_norm_run() -> None:
    p = pop(
        [cfg(policy="normal", layer_norm=False), cfg(policy="normal", layer_norm=False)], [0, 1]
    )
    torch.manual_seed(1)
    ref = OnlineLearner(OBS, LOW, HIGH, cfg(policy="normal", layer_norm=False))
    assert torch.equal(p.member_theta(1), ref.theta.detach())
    run_pop(p, data(10), np.zeros(OBS, np.float32))
    assert p.finite().all()
    assert p.act_deterministic(np.zeros((2, OBS), np.float32)).shape == (2, ACT)


def test_shape_mismatch_and_missing_begin_episode_raise() -> None:
    with pytest.raises(ValueError, match="units"):
        pop([cfg(), cfg(units=8)], [0, 1])
    with pytest.raises(ValueError, match="policy"):
        pop([cfg(), cfg(policy="normal")], [0, 1])
    p = pop([cfg(), cfg()], [0, 1])
    with pytest.raises(RuntimeError, match="begin_episode"):
        z = np.zeros(2, bool)
        p.step(np.zeros(2), np.zeros((2, OBS)), z, z)


def test_act_deterministic_matches_reference() -> None:
    p = pop([cfg(), cfg(method="ppo")], [3, 4])
    torch.manual_seed(4)
    ref = OnlineLearner(OBS, LOW, HIGH, cfg(method="ppo"))
    obs = np.random.default_rng(0).normal(size=(2, OBS)).astype(np.float32)
    np.testing.assert_allclose(
        p.act_deterministic(obs)[1], ref.act_deterministic(obs[1]), atol=1e-6
    )
