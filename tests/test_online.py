"""The online learner (Algorithm 1) for one run: step order, the surrogates, signals,
reliability. (Members of a population: tests/test_population.py.)"""

from __future__ import annotations

import dataclasses
import itertools
import math
from typing import Any

import numpy as np
import pytest
import torch
from tiny import baseline_config

from pporpe.nn.mlp import FlatMLP, flat_views, mlp
from pporpe.online import OnlineLearner, StepStats
from pporpe.online.config import OnlineConfig, TrainConfig
from pporpe.surrogates import METHODS, surrogate_objective

# pporpe 0.2's learner choices pinned: these hand-worked cases are written for them; the
# author's choices (the defaults) are tested one by one in test_fidelity_choices.py.


def make(method: str, seed: int = 0, **kw: object) -> OnlineLearner:
    cfg = baseline_config(method=method, **kw)
    return OnlineLearner(3, -np.ones(2), np.ones(2), cfg, seed=seed)


def nets(learner: OnlineLearner, theta: torch.Tensor) -> tuple[Any, list, list, Any]:
    """The learner's networks as FlatMLPs over views of a flat ``theta`` (its layout)."""
    cfg = learner.config
    kw = dict(layers=cfg.layers, units=cfg.units, layer_norm=cfg.layer_norm)
    pol_net = mlp(3, learner.population.head.raw_dim, **kw)  # type: ignore[arg-type]
    val_net = mlp(3, 1, **kw)  # type: ignore[arg-type]
    pol_shapes = [p.shape for p in pol_net.parameters()]
    val_shapes = [p.shape for p in val_net.parameters()]
    n_pol = sum(math.prod(s) for s in pol_shapes)
    pol = flat_views(theta[:n_pol], pol_shapes)
    val = flat_views(theta[n_pol:], val_shapes)
    return FlatMLP(pol_net), pol, val, FlatMLP(val_net)


def transitions(n: int, seed: int = 1) -> list[tuple[float, np.ndarray, bool, bool]]:
    rng = np.random.default_rng(seed)
    out = []
    for t in range(n):
        out.append((float(rng.normal()), rng.normal(size=3).astype(np.float32), False, t == n - 1))
    return out


def run(learner: OnlineLearner, trans: list, obs0: np.ndarray) -> list:
    stats = []
    learner.begin_episode(obs0)
    for r, obs, term, trunc in trans:
        s, _ = learner.step(r, obs, term, trunc)
        stats.append(s)
    return stats


def test_first_ratio_is_one_then_ratio_measures_one_update() -> None:
    learner = make("rpe", lr=1e-2)
    stats = run(learner, transitions(6), np.zeros(3, np.float32))
    assert stats[0].ratio.item() == pytest.approx(1.0, abs=1e-6)
    later = torch.stack([s.ratio for s in stats[1:]])
    assert torch.all((later - 1.0).abs() > 1e-6), later  # one update between sampling and loss


def test_the_methods_make_different_updates_from_same_transitions() -> None:
    trans = transitions(30)
    obs0 = np.zeros(3, np.float32)
    thetas = {}
    for method in METHODS:
        # a large lr pushes ratios past the thresholds, where the surrogates differ
        learner = make(method, lr=3e-2)
        run(learner, trans, obs0)
        thetas[method] = learner.theta.detach().clone()
    assert list(thetas) == ["ppo", "rb", "rpe", "spo"]
    for a, b in itertools.combinations(METHODS, 2):
        assert not torch.allclose(thetas[a], thetas[b]), (a, b)


def test_same_seed_same_numbers() -> None:
    trans = transitions(20)
    a = make("rpe", seed=3)
    sa = run(a, trans, np.zeros(3, np.float32))
    b = make("rpe", seed=3)
    sb = run(b, trans, np.zeros(3, np.float32))
    assert torch.equal(a.theta, b.theta) and torch.equal(a.target, b.target)
    assert [s.as_dict() for s in sa] == [s.as_dict() for s in sb]


def test_update_without_traces_is_gradient_of_surrogate_plus_td_loss() -> None:
    """With lambda = 0 the optimiser receives grad[-obj(rho, A) + delta^2/2] exactly: the
    trace r is the per-unit-signal gradient g, and the update's input is A g (policy) and
    delta g (value)."""
    # the torch engine's grad buffer (tests/test_fused.py holds the fused engine to it)
    learner = make("rpe", lambdas=(0.0, 0.0), lr=1e-2, engine="torch")
    pop = learner.population
    trans = transitions(3)
    learner.begin_episode(np.zeros(3, np.float32))
    learner.step(*trans[0])  # one update, so the next ratio differs from 1

    # recompute the expected gradient from the learner's pending state before it steps
    cfg = learner.config
    obs_t, u_t, logp_b = (
        pop.state.pending.obs[:1],
        pop.state.pending.u[:1],
        pop.state.pending.logp_b[:1],
    )
    theta = learner.theta.detach().clone().requires_grad_(True)
    policy_fn, pol, val, value_fn = nets(learner, theta)
    _, _, tgt, _ = nets(learner, torch.cat([learner.theta[: -learner.target.numel()],
                                            learner.target]))  # fmt: skip
    r, next_obs, term, trunc = trans[1]
    x1 = torch.as_tensor(next_obs).reshape(1, 3)
    v = value_fn(val, obs_t)[0, 0]
    with torch.no_grad():
        v_next = value_fn(tgt, x1)[0, 0]
    logp = pop.head.log_prob(policy_fn(pol, obs_t), u_t)[0]
    delta = r * cfg.effective_reward_scale + cfg.gamma * v_next - v.detach()
    logp_a = logp.detach() - pop.action_map.log_abs_det_jacobian(u_t)[0]
    adv = delta - (1 - cfg.gamma) * (cfg.beta_td * delta**2 + cfg.beta_de * logp_a)
    ratio = torch.exp(logp - logp_b[0])
    loss = (
        -surrogate_objective("rpe", ratio, adv)
        + 0.5 * (r * cfg.effective_reward_scale + cfg.gamma * v_next - v) ** 2
    )
    (expected,) = torch.autograd.grad(loss, theta)

    stats, _ = learner.step(r, next_obs, term, trunc)
    pi, vi = pop.lay.real_index
    g = pop.state.grad[:, 0].reshape(2, -1)  # this step's per-unit-signal gradient
    received = torch.cat([stats.adv * g[0, pi], stats.delta * g[1, vi]])
    torch.testing.assert_close(received, expected, rtol=1e-4, atol=1e-6)


def test_termination_does_not_bootstrap_but_truncation_does() -> None:
    obs0 = np.zeros(3, np.float32)
    nxt = np.ones(3, np.float32)
    deltas = {}
    for name, term, trunc in (("term", True, False), ("trunc", False, True)):
        learner = make("rpe", seed=5)
        learner.begin_episode(obs0)
        v0 = learner.value(obs0)
        _, _, tgt, value_fn = nets(learner, torch.cat([learner.theta[: -learner.target.numel()],
                                                       learner.target]))  # fmt: skip
        with torch.no_grad():
            vt = value_fn(tgt, torch.as_tensor(nxt).reshape(1, 3))
        s, _ = learner.step(1.0, nxt, term, trunc)
        deltas[name] = s.delta.item()
        scale = learner.config.effective_reward_scale
        boot = 0.0 if term else learner.config.gamma * vt.item()
        assert deltas[name] == pytest.approx(scale + boot - v0, abs=1e-6)


def test_step_before_begin_episode_raises() -> None:
    with pytest.raises(RuntimeError, match="begin_episode"):
        make("ppo").step(0.0, np.zeros(3), False, False)


def test_state_dict_round_trip_continues_identically() -> None:
    trans = transitions(10)
    a = make("rb", seed=2)
    run(a, trans[:5], np.zeros(3, np.float32))
    state = a.state_dict()
    b = make("rb", seed=99)
    b.load_state_dict(state)  # parameters, optimiser, traces, t-soft and the random stream
    sa = run(a, trans[5:], np.ones(3, np.float32))
    sb = run(b, trans[5:], np.ones(3, np.float32))
    assert torch.equal(a.theta, b.theta)
    assert [s.as_dict() for s in sa] == [s.as_dict() for s in sb]


def test_deterministic_action_is_in_bounds_and_repeatable() -> None:
    learner = make("rpe")
    a1 = learner.act_deterministic(np.ones(3))
    a2 = learner.act_deterministic(np.ones(3))
    assert a1.shape == (2,) and np.all(np.abs(a1) <= 1.0)
    assert np.array_equal(a1, a2)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"method": "trpo"}, "method"),
        ({"eps": 1.2}, "eps"),
        ({"beta": 0.95}, "beta"),
        ({"eta": -1.0}, "eta"),
        ({"gamma": 1.0}, "gamma"),
        ({"lr": 0.0}, "lr"),
        ({"tau": 0.0}, "tau"),
        ({"nu": -1.0}, "nu"),
        ({"lambdas": (0.5, 1.5)}, "lambdas"),
        ({"kappa": -1.0}, "kappa"),
        ({"beta_td": -0.1}, "beta_td"),
        ({"layers": 0}, "layers"),
        ({"policy": "beta"}, "policy"),
        ({"activation": "gelu"}, "activation"),
        ({"eps": "0.1"}, "eps"),
    ],
)
def test_online_config_rejects_bad_values(kwargs: dict, name: str) -> None:
    with pytest.raises(ValueError, match=name):
        OnlineConfig(**kwargs)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"episodes": -5}, "episodes"),
        ({"episodes": None, "steps": None}, "episodes/steps"),
        ({"episodes": 5, "steps": 5}, "episodes/steps"),
        ({"seed": -1}, "seed"),
        ({"checkpoint_every": 0}, "checkpoint_every"),
    ],
)
def test_train_config_rejects_bad_values(kwargs: dict, name: str) -> None:
    with pytest.raises(ValueError, match=name):
        TrainConfig(**kwargs)


def test_configs_are_frozen() -> None:
    cfg = OnlineConfig()
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.eps = 0.2  # type: ignore[misc]


def test_flat_forward_equals_the_module_it_mirrors() -> None:
    from pporpe.nn.mlp import FlatMLP, mlp

    torch.manual_seed(0)
    net = mlp(4, 7, layers=3, units=16)
    x = torch.randn(5, 4)
    flat = FlatMLP(net)
    torch.testing.assert_close(flat(list(net.parameters()), x), net(x))


def test_learner_forward_uses_the_parameters_it_reports() -> None:
    """Setting the flat parameters (theta's layout) changes the networks accordingly."""
    learner = make("rpe")
    obs = np.ones(3, np.float32)
    v0 = learner.value(obs)
    theta = learner.theta
    n_value = learner.target.numel()
    theta[-n_value:] = 0.0
    learner.population.set_member_theta(0, theta)
    assert v0 != 0.0 and learner.value(obs) == 0.0
    assert torch.equal(learner.theta, theta) and not learner.target.any()


def test_compiled_update_matches_eager() -> None:
    """compile=True computes the same update as eager (up to float rounding)."""
    trans = transitions(4)
    results = []
    for compiled in (False, True):
        learner = make("rpe", seed=4, compile=compiled)
        stats = run(learner, trans, np.zeros(3, np.float32))
        stacked = StepStats.stack(stats)
        results.append((learner.theta.clone(), torch.stack(list(vars(stacked).values()))))
    torch.testing.assert_close(results[0][0], results[1][0], rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(results[0][1], results[1][1], rtol=1e-4, atol=1e-5)
