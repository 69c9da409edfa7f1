"""The fused engine (one numba kernel per step): its closed forms against torch autograd in
float64, and the engine against the torch engine, buffer by buffer."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import kernels_once
import numpy as np
import pytest
import torch
from tiny import small_config as cfg

from pporpe.nn.batched import NetLayout
from pporpe.nn.policies import NormalHead, StudentTHead
from pporpe.online.config import AUTHOR_CHOICES, BASELINE_CHOICES, TESTBED, OnlineConfig
from pporpe.online.fused_engine import segment_ranges
from pporpe.online.fused_engine.kernels.head import digamma, head_grad_closed, kl_closed
from pporpe.online.fused_engine.kernels.inputs import HEADS, METHOD_CODES
from pporpe.online.fused_engine.kernels.surrogates import surrogate_closed
from pporpe.online.population import PopulationLearner
from pporpe.surrogates import rpe_surrogate_advantage, spo_surrogate_advantage, surrogate_objective

torch.set_num_threads(1)
OBS, ACT = 3, 2
LOW, HIGH = -np.ones(ACT), np.ones(ACT) * 2.0


# ------------------------------------------------------------------------ closed forms
def test_digamma_hand_worked_and_against_torch() -> None:
    euler = 0.5772156649015329
    assert digamma(1.0) == pytest.approx(-euler, abs=1e-13)
    assert digamma(0.5) == pytest.approx(-euler - 2.0 * math.log(2.0), abs=1e-13)
    # the recurrence psi(x + 1) = psi(x) + 1/x, across the switch to the series at 6
    for x in (1.3, 9.5, 9.999, 10.0, 17.2):
        assert digamma(x + 1.0) - digamma(x) == pytest.approx(1.0 / x, abs=1e-13)
    xs = np.linspace(1.0, 60.0, 97)
    ref = torch.digamma(torch.tensor(xs, dtype=torch.float64)).numpy()
    np.testing.assert_allclose([digamma(float(x)) for x in xs], ref, rtol=0, atol=1e-12)


def _raw_u(head: str, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """float32 raw outputs (scale and df from the softplus' linear tail to its saturation)
    and pre-map actions."""
    rng = np.random.default_rng(seed)
    raw_dim = 2 * ACT + (1 if head == "student_t" else 0)
    raw = rng.normal(size=(n, raw_dim)) * 2.0
    raw[:4, ACT:] = [-30.0, 25.0, 0.0, 19.9][: raw_dim - ACT][0]  # softplus' branches
    u = raw[:, :ACT] + rng.standard_t(3, size=(n, ACT))
    return raw.astype(np.float32), u.astype(np.float32)


@pytest.mark.parametrize("kind", ["student_t", "normal"])
def test_head_log_density_and_gradient_match_autograd(kind: str) -> None:
    head = StudentTHead(ACT, min_scale=1e-3) if kind == "student_t" else NormalHead(ACT, 1e-3)
    code = HEADS[kind]
    raw, u = _raw_u(kind, 40, seed=3)
    for i in range(raw.shape[0]):
        r64 = torch.tensor(raw[i], dtype=torch.float64, requires_grad=True)
        u64 = torch.tensor(u[i], dtype=torch.float64)
        ref = head.distribution(r64).log_prob(u64)  # torch.distributions, float64
        (grad_ref,) = torch.autograd.grad(ref, r64)
        grad = np.zeros(raw.shape[1])
        logp = head_grad_closed(raw[i], u[i], code, ACT, 1e-3, grad)
        assert logp == pytest.approx(float(ref), rel=1e-12, abs=1e-12)
        np.testing.assert_allclose(grad, grad_ref.numpy(), rtol=1e-10, atol=1e-12)


def test_student_t_gradient_hand_worked() -> None:
    """At u = loc the location gradient is 0 and the scale's is -sigmoid(raw_s)/scale."""
    raw = np.array([0.5, -0.2, 0.3, 0.1, 1.0], np.float32)
    u = raw[:ACT].copy()
    grad = np.zeros(5)
    head_grad_closed(raw, u, 0, ACT, 1e-3, grad)
    raw_s = raw[2:4].astype(np.float64)
    scale = np.log1p(np.exp(raw_s)) + 1e-3
    np.testing.assert_allclose(grad[:2], 0.0, atol=0)
    np.testing.assert_allclose(grad[2:4], -1.0 / (scale * (1.0 + np.exp(-raw_s))), rtol=1e-12)


@pytest.mark.parametrize("kind", ["student_t", "normal"])
def test_kl_matches_head(kind: str) -> None:
    head = StudentTHead(ACT) if kind == "student_t" else NormalHead(ACT)
    raw_p, _ = _raw_u(kind, 20, seed=1)
    raw_q, _ = _raw_u(kind, 20, seed=2)
    for p, q in zip(raw_p, raw_q):
        ref = head.kl(torch.tensor(p, dtype=torch.float64), torch.tensor(q, dtype=torch.float64))
        ours = kl_closed(p, q, HEADS[kind], ACT, 1e-3)
        assert ours == pytest.approx(float(ref), rel=1e-10, abs=1e-12)
    assert kl_closed(raw_p[0], raw_p[0], HEADS[kind], ACT, 1e-3) == 0.0


SURROGATES = [
    ("ppo", "derived", 0.1, 0.5, 0.3),
    ("rb", "derived", 0.2, 0.5, 0.3),
    ("rpe", "derived", 0.1, 0.5, 0.3),
    ("rpe", "derived", 0.3, 0.2, 0.3),
    ("rpe", "printed", 0.1, 0.5, 0.3),
    ("spo", "derived", 0.2, 0.5, 0.3),
    ("spo", "derived", 0.05, 0.5, 0.3),
]


@pytest.mark.parametrize(("method", "form", "eps", "beta", "eta"), SURROGATES)
def test_surrogate_and_derivative_match_autograd(
    method: str, form: str, eps: float, beta: float, eta: float
) -> None:
    code = METHOD_CODES[(method, form)]
    # ratios on both sides of every threshold (avoiding the kinks themselves)
    rhos = np.concatenate([np.linspace(0.3, 2.0, 173), [1.0]])
    for sigma in (1.0, -1.0):
        rho = torch.tensor(rhos, dtype=torch.float64, requires_grad=True)
        adv = torch.full_like(rho, sigma)
        obj = surrogate_objective(method, rho, adv, eps, beta, eta, form)  # type: ignore[arg-type]
        (dobj,) = torch.autograd.grad(obj.sum(), rho)
        for i, x in enumerate(rhos):
            o, d = surrogate_closed(code, float(x), sigma, eps, beta, eta)
            assert o == pytest.approx(float(obj[i]), rel=1e-12, abs=1e-12)
            assert d == pytest.approx(float(dobj[i]), rel=1e-10, abs=1e-12)


def test_surrogate_derivative_identities() -> None:
    """d obj/d rho is A at rho = 1 for every method, and 0 (PPO) / -eta sigma (RB) past the
    threshold; for RPE (derived) it is the surrogate advantage A~ of eq. (12), for SPO its
    own, which vanishes at its maximiser 1 + sigma eps."""
    assert sorted(set(METHOD_CODES.values())) == list(range(5))
    for code in range(5):
        for sigma in (1.0, -1.0):
            assert surrogate_closed(code, 1.0, sigma, 0.1, 0.5, 0.3)[1] == pytest.approx(sigma)
    assert surrogate_closed(0, 1.3, 1.0, 0.1, 0.5, 0.3)[1] == 0.0
    assert surrogate_closed(1, 0.7, -1.0, 0.1, 0.5, 0.3)[1] == pytest.approx(0.3)
    rho = torch.tensor([0.7, 0.95, 1.1, 1.4], dtype=torch.float64)
    for sigma in (1.0, -1.0):
        ref = rpe_surrogate_advantage(rho, torch.full_like(rho, sigma), 0.1, 0.5)
        ours = [surrogate_closed(2, float(x), sigma, 0.1, 0.5, 0.3)[1] for x in rho]
        np.testing.assert_allclose(ours, ref.numpy(), rtol=1e-12)
        ref = spo_surrogate_advantage(rho, torch.full_like(rho, sigma), 0.2)
        ours = [surrogate_closed(4, float(x), sigma, 0.2, 0.5, 0.3)[1] for x in rho]
        np.testing.assert_allclose(ours, ref.numpy(), rtol=1e-12)
        at_max = surrogate_closed(4, 1.0 + sigma * 0.2, sigma, 0.2, 0.5, 0.3)[1]
        assert at_max == pytest.approx(0.0, abs=1e-12)


# ------------------------------------------------------------------------ the engines
SPLIT_SMALL = {"layers": 2, "units": 16, "head_tensors": "per_output"}
"""The small net with the test bed's split head (``head_tensors="per_output"``)."""
MIXED = [
    cfg(),  # today's defaults
    cfg(**AUTHOR_CHOICES, method="ppo"),
    cfg(**BASELINE_CHOICES, method="rb"),
    cfg(method="rpe", rpe_form="printed", kappa=0.0, nu=float("inf"), k_dof=float("inf")),
    cfg(method="ppo", policy_gradient="weighted_score", time_limit="terminal", tau=1.0,
        lambdas=(0.5, 0.9), kappa=1.0, amsgrad_decay=0.0),
    cfg(layer_norm_affine=True, opt_betas=(0.0, 0.99), critic_signal="actor", lr=1e-3),
    cfg(method="spo", eps=0.05, lr=3e-3),
]  # fmt: skip
OTHER_SHAPES = [
    [cfg(policy="normal", layer_norm=False, activation="relu", min_scale=1e-8)] * 2,
    [cfg(activation="tanh", min_scale=1e-8, policy_gradient="weighted_score"),
     cfg(activation="tanh", min_scale=1e-8, method="rb", entropy_density="pre_squash")],
    # the test bed's learner, whose head is three layers for the t-momentum, beside others
    [cfg(**{**TESTBED, **SPLIT_SMALL}),
     cfg(**{**TESTBED, **SPLIT_SMALL}, k_dof=float("inf")),
     cfg(**SPLIT_SMALL, min_scale=1e-8, method="rpe")],
]  # fmt: skip


def _data(n: int, k: int, seed: int = 0, episode: int = 9) -> list[tuple]:
    """Per-step (reward, next_obs, terminated, truncated) of K members; episodes end by a
    time limit or a termination in turn, at different steps for different members."""
    rng = np.random.default_rng(seed)
    out = []
    for t in range(n):
        end = (t + np.arange(k)) % episode == episode - 1
        term = end & (((t + np.arange(k)) // episode) % 2 == 1)
        out.append((rng.normal(size=k), rng.normal(size=(k, OBS)), term, end & ~term))
    return out


def _run(p: PopulationLearner, data: list[tuple]) -> tuple[list, list]:
    K = p.K
    stats, acts = [], [p.begin_episode(range(K), np.zeros((K, OBS)))]
    for r, o, term, trunc in data:
        s, a = p.step(r, o, term, trunc)
        stats.append(s)
        acts.append(a)
        ends = np.nonzero(term | trunc)[0]
        if len(ends):
            p.begin_episode(ends, o[ends])
    return stats, acts


def _buffers(p: PopulationLearner) -> dict[str, np.ndarray]:
    """The population's state_dict as arrays, with the noise positions."""
    out = {n: t.numpy() for n, t in p.state.state_dict().items()}
    out["pos"] = p.noise.pos.copy()
    return out


def _pair(configs: list[OnlineConfig], n: int) -> tuple[dict, dict, list, list, list, list]:
    seeds = list(range(10, 10 + len(configs)))
    t = PopulationLearner(OBS, LOW, HIGH, configs, seeds, compile_update=False)
    f = PopulationLearner(OBS, LOW, HIGH, configs, seeds, engine="fused")
    data = _data(n, len(configs))
    st, at = _run(t, data)
    sf, af = _run(f, data)
    return _buffers(t), _buffers(f), st, sf, at, af


@pytest.mark.parametrize(
    "configs", [MIXED, *OTHER_SHAPES], ids=["mixed", "normal", "tanh", "split_head"]
)
def test_fused_engine_matches_torch_engine(configs: list[OnlineConfig]) -> None:
    """Every buffer after 25 steps (episode ends included) within float rounding.

    Tolerance: float32 rounding (6e-8 relative per operation) differs between the engines
    (reassociated sums, FMA, the head in float64), and td-AmsProp's normalisation
    q / sqrt(v) turns a relative error of the gradient into one of the same size in the
    step, so it grows with the steps about linearly: 25 steps of ~1e-6 each. Bounded by
    1e-4 of each buffer's scale (2e-4 for the moments, whose tiny entries carry the
    largest relative error); the step counts, noise positions and episode flags are exact.
    The trace divergence (and D, its sum) is a difference of nearly equal numbers
    (rho - 1 - log rho near rho = 1, a KL of two close policies), which the torch engine
    computes in float32 (absolute error ~1e-7 per step) and the fused one in float64:
    absolute tolerance 1e-6 there.
    """
    bt, bf, st, sf, at, af = _pair(configs, 25)
    exact = ("steps", "pending.waiting", "pos")
    for name in exact:
        assert np.array_equal(bt[name], bf[name]), name
    for name, x in bt.items():
        if name in exact:
            continue
        scale = max(float(np.abs(x).max()), 1e-6)
        tol = 2e-4 if name in ("opt_v", "opt_vmax", "opt_weight") else 1e-4
        err = float(np.abs(x - bf[name]).max())
        assert err <= (1e-6 if name == "trace_divergence" else tol * scale), (name, err, scale)
    for a, b in zip(st, sf):
        for field in ("delta", "adv", "ratio", "divergence", "trace_decay"):
            atol = 1e-6 if field == "divergence" else 1e-5
            torch.testing.assert_close(getattr(b, field), getattr(a, field), rtol=1e-4, atol=atol)
    np.testing.assert_allclose(np.stack(af), np.stack(at), rtol=0, atol=1e-4)
    # the parameters did move (the comparison is not of two idle learners)
    fresh = PopulationLearner(OBS, LOW, HIGH, configs, list(range(10, 10 + len(configs))))
    assert float(np.abs(bt["params"] - fresh.state.params.numpy()).max()) > 1e-3


def test_fused_engine_first_step_matches_torch_tightly() -> None:
    bt, bf, st, sf, _, _ = _pair(MIXED, 1)
    assert float(st[0].ratio.sub(1).abs().max()) <= 1e-6
    assert torch.equal(sf[0].ratio, torch.ones(len(MIXED)))  # same forward for pi_b and pi
    # one step: the gradient (the trace e) to 2e-5 of its scale (float32 rounding of the
    # LayerNorm backward's mean subtractions, which cancel), and m = (1 - b) gv with it;
    # the parameters moved by lr * m, so their error is far below float32's resolution
    for name, tol in (("trace_e", 2e-5), ("opt_m", 2e-5), ("params", 1e-6)):
        scale = float(np.abs(bt[name]).max())
        assert float(np.abs(bt[name] - bf[name]).max()) <= tol * scale, name


def test_fused_engine_is_bitwise_deterministic() -> None:
    seeds = list(range(len(MIXED)))
    a = PopulationLearner(OBS, LOW, HIGH, MIXED, seeds, engine="fused")
    b = PopulationLearner(OBS, LOW, HIGH, MIXED, seeds, engine="fused")
    data = _data(15, len(MIXED), seed=4)
    _, aa = _run(a, data)
    _, ab = _run(b, data)
    assert np.array_equal(np.stack(aa), np.stack(ab))
    ba, bb = _buffers(a), _buffers(b)
    assert all(np.array_equal(ba[n], bb[n], equal_nan=True) for n in ba)


def test_fused_inactive_and_non_finite_members_stay_alone() -> None:
    configs = MIXED[:3]
    a = PopulationLearner(OBS, LOW, HIGH, configs, [0, 1, 2], engine="fused")
    b = PopulationLearner(OBS, LOW, HIGH, configs, [0, 1, 2], engine="fused")
    for p in (a, b):
        p.begin_episode([0, 1, 2], np.zeros((3, OBS)))
    z = np.zeros(3, bool)
    rng = np.random.default_rng(0)
    for t in range(8):
        r, o = rng.normal(size=3), rng.normal(size=(3, OBS))
        b.step(r, o, z, z)
        r = r.copy()
        if t == 3:
            r[1] = np.nan
        a.step(r, o, z, z)
    assert a.finite().tolist() == [True, False, True]
    ba, bb = _buffers(a), _buffers(b)
    for k in (0, 2):
        for n in ("params", "trace_e", "trace_r", "opt_v", "opt_vmax", "opt_m", "opt_weight"):
            assert np.array_equal(ba[n][:, k], bb[n][:, k]), (n, k)
        for n in (
            "trace_divergence",
            "decay",
            "tsoft_weight",
            "tsoft_sigma2",
            "pending.raw_b",
            "pending.logp_b",
            "pending.obs",
        ):
            assert np.array_equal(ba[n][k], bb[n][k]), (n, k)
    # an inactive member keeps every buffer bitwise, whatever its row of the inputs holds
    active = np.array([True, True, False])
    a.step(np.array([0.1, 0.1, np.nan]), np.full((3, OBS), np.nan), z, z, active=active)
    after = _buffers(a)
    for n in ("params", "trace_e", "trace_r", "opt_v", "opt_vmax", "opt_m", "opt_weight"):
        assert np.array_equal(after[n][:, 2], ba[n][:, 2]), n
    for n in ("trace_divergence", "decay", "tsoft_weight", "tsoft_sigma2", "pending.obs",
              "pending.u", "pending.logp_b", "pending.value_b", "steps", "pos"):  # fmt: skip
        assert np.array_equal(after[n][2], ba[n][2]), n


def test_fused_member_state_round_trip_continues_bitwise() -> None:
    configs = MIXED[:3]
    a = PopulationLearner(OBS, LOW, HIGH, configs, [0, 1, 2], engine="fused")
    _run(a, _data(7, 3, seed=1))  # mid-episode for every member
    state = a.member_state(1)
    b = PopulationLearner(OBS, LOW, HIGH, [cfg(), cfg(), cfg(lr=1e-2)], [7, 8, 9], engine="fused")
    b.load_member_state(1, configs[1], state)
    b.begin_episode([0, 2], np.zeros((2, OBS)))
    data = _data(12, 3, seed=2)
    for p in (a, b):
        for r, o, term, trunc in data:
            p.step(r, o, term, trunc)
            ends = np.nonzero(term | trunc)[0]
            if len(ends):
                p.begin_episode(ends, o[ends])
    ba, bb = _buffers(a), _buffers(b)
    for n in ba:
        x, y = ba[n], bb[n]
        stacked = ("params", "trace_e", "trace_r", "opt_v", "opt_vmax", "opt_m", "opt_weight")
        sl = (slice(None), 1) if n in stacked else 1
        assert np.array_equal(x[sl], y[sl]), n


def test_fused_eval_forward_matches_torch() -> None:
    t = PopulationLearner(OBS, LOW, HIGH, MIXED[:2], [0, 1])
    f = PopulationLearner(OBS, LOW, HIGH, MIXED[:2], [0, 1], engine="fused")
    obs = np.random.default_rng(0).normal(size=(2, OBS))
    np.testing.assert_allclose(f.act_deterministic(obs), t.act_deterministic(obs), atol=1e-6)
    np.testing.assert_allclose(f.value(obs), t.value(obs), atol=1e-6)


def test_unknown_engine_is_refused() -> None:
    with pytest.raises(ValueError, match="engine"):
        PopulationLearner(OBS, LOW, HIGH, [cfg()], [0], engine="jax")


@pytest.mark.parametrize("split", [False, True])
def test_segment_ranges_hand_worked(split: bool) -> None:
    """One hidden layer of 8 units on 3 inputs, a student-t head on 2 actions (location 2,
    scale 2, df 1): the weight (24 elements, 3 rows) at 0, its bias at 24, the output
    weight (5 rows) at 32 and its bias row at 72. Split, the output weight's rows and the
    bias's columns go to their part; the bias's padding columns 77-79 to none."""
    lay = NetLayout(3, 5, 1, 8, False, head_parts=(2, 2, 1) if split else None)
    ranges = [tuple(r) for r in segment_ranges(lay).tolist()]
    hidden = [(0, 24), (24, 32)]
    if split:
        assert ranges == [*hidden, (32, 48), (48, 64), (64, 72), (72, 74), (74, 76), (76, 77)]
    else:
        assert ranges == [*hidden, (32, 72), (72, 80)]


def fresh_process(env: dict[str, str]) -> list[str]:
    """What ``kernels_once.py`` prints in a process of its own: ``compiled`` or ``loaded``,
    and the hash of the parameters it got."""
    done = subprocess.run([sys.executable, str(Path(kernels_once.__file__))], env=env,
                          check=True, capture_output=True, text=True)  # fmt: skip
    return done.stdout.split()[-2:]


def test_same_numbers_whether_the_kernels_were_compiled_or_loaded(tmp_path: Path) -> None:
    """A process that found numba's cache empty (it compiles), one after it (it loads) and
    this test's own process: the same parameters, bitwise, after 40 steps of the default
    learner (swish, whose fastmath loops computed otherwise in a process that compiled).
    The compiling process is the suite's warm-up where that one compiled (``conftest.py``:
    a fresh clone under pytest-xdist), else one here, with a cache of its own."""
    compiled = os.environ.get(kernels_once.COMPILED_HASH)
    if compiled is not None:
        runs = [["compiled", compiled], fresh_process(dict(os.environ))]
    else:
        env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
        runs = [fresh_process(env) for _ in range(2)]
        assert any((tmp_path / "numba").rglob("*.nbi"))  # the first process filled the cache
    assert [said for said, _ in runs] == ["compiled", "loaded"]
    assert runs[0][1] == runs[1][1] == kernels_once.parameters_hash()


def test_a_failed_compile_subprocess_warns_and_the_kernels_still_run(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Where the subprocess cannot run (here: an interpreter that exits 1), the kernels
    are compiled (or loaded) in this process, with a warning saying what that costs."""
    from pporpe.online import fused_engine

    monkeypatch.setattr(fused_engine._Loaded, "done", False)
    monkeypatch.setattr(fused_engine, "_in_cache", lambda: False)
    monkeypatch.setattr(fused_engine.sys, "executable", "/bin/false")
    with pytest.warns(RuntimeWarning, match="compiling the fused kernels in a subprocess"):
        fused_engine.warm_up()
    assert fused_engine._Loaded.done
    p = PopulationLearner(OBS, LOW, HIGH, [cfg()], [0], engine="fused")
    p.begin_episode([0], np.zeros((1, OBS)))
    assert np.all(np.isfinite(p.value(np.zeros((1, OBS)))))
