"""Batch PPO (pporpe.batch): GAE, truncation bootstrapping, determinism, the four
surrogates, configuration checks, normalisation, run folders and exact resume."""

from __future__ import annotations

import itertools
import json
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium import spaces

from pporpe.batch import (
    ZOO_DEFAULTS,
    BatchConfig,
    BatchLearner,
    RunningMeanStd,
    UpdateStats,
    compute_gae,
    load_batch_learner,
    train_batch,
    zoo_config,
)
from pporpe.runs.logger import EpisodeRecord, read_records
from pporpe.surrogates import METHODS

# A tiny, fast configuration on the Bullet InvertedPendulum (about 10k raw steps/s).
TINY = dict(
    env="pendulum",
    seed=3,
    n_envs=2,
    n_steps=32,
    batch_size=16,
    n_epochs=2,
    total_steps=256,
    layers=1,
    units=16,
    checkpoint_every=2,
    eval_episodes=2,
)


def tiny(**kw: Any) -> BatchConfig:
    return BatchConfig(**{**TINY, **kw})  # type: ignore[arg-type]


def strip_time(records: list[EpisodeRecord]) -> list[EpisodeRecord]:
    return [replace(r, wall_time=0.0) for r in records]


# ------------------------------------------------------------------------------------
# GAE against an independent float64 reference
# ------------------------------------------------------------------------------------
def ref_gae(
    r: np.ndarray,
    v: np.ndarray,
    v_next: np.ndarray,
    term: np.ndarray,
    trunc: np.ndarray,
    gamma: float,
    lam: float,
) -> np.ndarray:
    """A_t = sum_k (gamma*lam)^k delta_{t+k}, summed forward until the episode or data ends."""
    T, N = r.shape
    out = np.zeros((T, N))
    for i in range(N):
        for t in range(T):
            total, weight = 0.0, 1.0
            for k in range(t, T):
                boot = 0.0 if term[k, i] else gamma * v_next[k, i]
                total += weight * (r[k, i] + boot - v[k, i])
                if term[k, i] or trunc[k, i]:
                    break
                weight *= gamma * lam
            out[t, i] = total
    return out


@pytest.mark.parametrize("gamma,lam", [(0.99, 0.95), (0.9, 1.0), (0.5, 0.0)])
def test_gae_matches_float64_reference_with_terminations_and_truncations(
    gamma: float, lam: float
) -> None:
    rng = np.random.default_rng(0)
    T, N = 40, 3
    r = rng.normal(size=(T, N))
    v = rng.normal(size=(T, N))
    v_next = rng.normal(size=(T, N))
    end = rng.random((T, N)) < 0.15
    kind = rng.random((T, N)) < 0.5
    term, trunc = end & kind, end & ~kind
    assert term.sum() >= 3 and trunc.sum() >= 3  # both kinds occur
    adv, ret = compute_gae(
        torch.tensor(r, dtype=torch.float32),
        torch.tensor(v, dtype=torch.float32),
        torch.tensor(v_next, dtype=torch.float32),
        torch.tensor(term),
        torch.tensor(trunc),
        gamma,
        lam,
    )
    expected = ref_gae(r, v, v_next, term, trunc, gamma, lam)
    np.testing.assert_allclose(adv.numpy(), expected, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(ret.numpy(), expected + v, rtol=1e-4, atol=1e-4)


def test_gae_by_hand() -> None:
    # one env, 3 steps: step 0 truncated (bootstraps 2.0), step 1 normal, step 2 terminated
    r = torch.tensor([[1.0], [1.0], [1.0]])
    v = torch.zeros(3, 1)
    v_next = torch.tensor([[2.0], [5.0], [7.0]])
    term = torch.tensor([[False], [False], [True]])
    trunc = torch.tensor([[True], [False], [False]])
    adv, _ = compute_gae(r, v, v_next, term, trunc, 0.5, 1.0)
    # step 2: delta = 1 (no bootstrap), A2 = 1; step 1: delta = 1 + 0.5*5 = 3.5,
    # A1 = 3.5 + 0.5*A2 = 4; step 0: delta = 1 + 0.5*2 = 2, chain cut by the truncation
    assert adv[:, 0].tolist() == pytest.approx([2.0, 4.0, 1.0])
    adv_nb, _ = compute_gae(r, v, v_next, term, trunc, 0.5, 1.0, bootstrap_truncated=False)
    assert adv_nb[:, 0].tolist() == pytest.approx([1.0, 4.0, 1.0])


# ------------------------------------------------------------------------------------
# Infinite horizon: constant reward 1, never terminating, truncated by a TimeLimit
# ------------------------------------------------------------------------------------
class ConstantRewardEnv(gym.Env):  # type: ignore[type-arg]
    """Reward 1 every step, never terminates; the observation carries no time."""

    observation_space = spaces.Box(-1.0, 1.0, (1,), np.float32)
    action_space = spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> Any:
        super().reset(seed=seed)
        return np.zeros(1, np.float32), {}

    def step(self, action: Any) -> Any:
        return np.zeros(1, np.float32), 1.0, False, False, {}


HORIZON = 20
gym.register("PporpeConstantReward-v0", entry_point=ConstantRewardEnv, max_episode_steps=HORIZON)


@pytest.mark.parametrize("bootstrap", [True, False])
def test_truncation_bootstrap_gives_infinite_horizon_value(bootstrap: bool) -> None:
    gamma = 0.9
    cfg = BatchConfig(
        env="PporpeConstantReward-v0",
        n_envs=2,
        n_steps=HORIZON,  # one rollout = one episode per sub-environment
        batch_size=2 * HORIZON,
        n_epochs=10,
        total_steps=2 * HORIZON * 20,
        gamma=gamma,
        gae_lambda=1.0,
        lr=3e-2,
        vf_coef=1.0,
        max_grad_norm=None,
        normalize_obs=False,
        normalize_reward=False,
        layers=1,
        units=8,
        bootstrap_truncated=bootstrap,
        eval_episodes=0,
    )
    torch.manual_seed(0)
    learner = BatchLearner(cfg)
    for _ in range(cfg.n_updates):
        learner.collect_rollouts()
        assert bool(learner.buffer.truncated[-1].all()) and not learner.buffer.terminated.any()
        learner.train()
    with torch.no_grad():
        value = float(learner.model.value(torch.zeros(1, 1))[0])
    learner.close()
    infinite = 1.0 / (1.0 - gamma)  # 10
    # treating the time limit as an end: the mean of the truncated returns-to-go
    truncated = float(np.mean([(1 - gamma ** (HORIZON - t)) / (1 - gamma) for t in range(HORIZON)]))
    assert truncated == pytest.approx(6.047, abs=1e-3)
    if bootstrap:
        assert value == pytest.approx(infinite, abs=0.2)
    else:
        assert value == pytest.approx(truncated, abs=0.2)


# ------------------------------------------------------------------------------------
# The surrogates change the update
# ------------------------------------------------------------------------------------
def _updates_by_method(cfg: BatchConfig) -> dict[str, torch.Tensor]:
    torch.manual_seed(cfg.seed)
    learner = BatchLearner(cfg)
    learner.collect_rollouts()
    theta0 = learner.model.theta.clone()
    opt0 = learner.optimizer.state_dict()
    out = {}
    for method in METHODS:
        with torch.no_grad():
            learner.model.theta.copy_(theta0)
        learner.optimizer.load_state_dict(opt0)
        learner.cfg = replace(cfg, method=method)  # type: ignore[arg-type]
        torch.manual_seed(123)  # the same minibatches for every method
        stats = learner.train()
        assert isinstance(stats, UpdateStats)
        out[method] = learner.model.theta.clone()
    learner.close()
    return out


def test_each_surrogate_changes_the_update_on_the_same_batch() -> None:
    cfg = tiny(eps=0.05, lr=1e-2, n_epochs=4)
    thetas = _updates_by_method(cfg)
    assert list(thetas) == ["ppo", "rb", "rpe", "spo"]
    for a, b in itertools.combinations(thetas, 2):
        assert (thetas[a] - thetas[b]).abs().max() > 1e-5, (a, b)


def test_surrogates_agree_on_a_single_step_from_rho_one() -> None:
    # one epoch with one minibatch: the only gradient is taken at rho = 1, where every
    # surrogate's gradient is A * grad log pi, so the updates coincide
    cfg = tiny(n_epochs=1, batch_size=64, eps=0.05, lr=1e-2)
    thetas = _updates_by_method(cfg)
    for method in ("rb", "rpe", "spo"):
        torch.testing.assert_close(thetas["ppo"], thetas[method])


# ------------------------------------------------------------------------------------
# Configuration
# ------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "field,value",
    [
        ("method", "trpo"),
        ("eps", 0.0),
        ("eps", 1.5),
        ("beta", 1.2),
        ("eta", -1.0),
        ("gamma", 1.0),
        ("gae_lambda", 1.1),
        ("lr", 0.0),
        ("n_envs", 0),
        ("n_steps", 0),
        ("n_epochs", 0),
        ("batch_size", 65),
        ("batch_size", 0),
        ("total_steps", 0),
        ("vec_env", "threads"),
        ("max_grad_norm", -1.0),
        ("target_kl", 0.0),
        ("clip_vf", -0.1),
        ("ent_coef", -0.01),
        ("adv_norm", "global"),
        ("policy", "beta"),
        ("scale", "learned"),
        ("action_bound", "tanh"),
        ("activation", "gelu"),
        ("layers", 0),
        ("seed", -1),
        ("checkpoint_every", 0),
        ("lr_schedule", "cosine"),
        ("clip_obs", 0.0),
        ("normalize_obs", "yes"),
    ],
)
def test_bad_config_raises_value_error_naming_the_field(field: str, value: Any) -> None:
    with pytest.raises(ValueError, match=field) as info:
        tiny(**{field: value})
    assert repr(value) in str(info.value) or str(value) in str(info.value)


def test_spo_takes_eps_alone_and_refuses_a_bad_one_as_the_others() -> None:
    assert tiny(method="spo", eps=0.4, beta=0.8).method == "spo"  # beta is not SPO's
    for method in METHODS:
        with pytest.raises(ValueError, match=r"eps must be a number in the open interval \(0, 1\)"):
            tiny(method=method, eps=1.0)


def test_a_short_spo_run_writes_its_diagnostics(tmp_path: Path) -> None:
    result = train_batch(tiny(method="spo", eval_episodes=0), tmp_path, progress=False)
    assert json.loads((tmp_path / "config.json").read_text())["method"] == "spo"
    assert result.updates == 4 and len(result.records) > 0
    for r in result.records:
        assert r.diagnostics is not None and 0.0 <= r.diagnostics.past_threshold <= 1.0
        assert r.diagnostics.reg_amount >= 0.0
    assert math.isfinite(result.last_stats["policy_loss"])


def test_rpe_needs_a_threshold() -> None:
    with pytest.raises(ValueError, match=r"beta\*\(1\+eps\)"):
        tiny(method="rpe", eps=0.4, beta=0.8)


def test_zoo_defaults() -> None:
    cheetah = zoo_config("halfcheetah")
    assert (cheetah.n_envs, cheetah.n_steps, cheetah.batch_size, cheetah.n_epochs) == (
        16,
        512,
        128,
        20,
    )
    assert (cheetah.lr, cheetah.eps, cheetah.gae_lambda, cheetah.log_std_init) == (
        3e-5,
        0.4,
        0.9,
        -2.0,
    )
    assert (cheetah.activation, cheetah.units, cheetah.layers, cheetah.init) == (
        "relu",
        256,
        2,
        "default",
    )
    assert zoo_config("AntBulletEnv-v0").log_std_init == -1.0
    assert zoo_config("halfcheetah", method="rpe").method == "rpe"
    assert set(ZOO_DEFAULTS) == {"pendulum", "swingup", "halfcheetah", "ant"}
    assert zoo_config("Pendulum-v1") == BatchConfig(env="Pendulum-v1")


# ------------------------------------------------------------------------------------
# Normalisation
# ------------------------------------------------------------------------------------
def test_running_mean_std_matches_numpy() -> None:
    rng = np.random.default_rng(1)
    data = rng.normal(3.0, 2.0, size=(300, 4))
    rms = RunningMeanStd((4,), epsilon=0.0)
    for chunk in np.array_split(data, 7):
        rms.update(chunk)
    np.testing.assert_allclose(rms.mean, data.mean(0), rtol=1e-12)
    np.testing.assert_allclose(rms.var, data.var(0), rtol=1e-12)
    assert rms.count == 300
    other = RunningMeanStd((4,))
    other.load_state_dict(rms.state_dict())
    np.testing.assert_array_equal(other.mean, rms.mean)


def test_act_deterministic_is_bounded_and_sampling_is_not_validated() -> None:
    for bound in ("clip", "map"):
        for policy in ("normal", "student_t"):
            torch.manual_seed(0)
            learner = BatchLearner(tiny(action_bound=bound, policy=policy, log_std_init=2.0))
            learner.collect_rollouts()
            stats = learner.train()
            assert math.isfinite(float(stats.policy_loss))
            a = learner.act_deterministic(np.full(5, 50.0, np.float32))
            assert a.shape == (1,) and -1.0 <= float(a[0]) <= 1.0
            learner.close()


def test_next_step_autoreset_is_refused() -> None:
    envs = gym.vector.SyncVectorEnv([lambda: gym.make("PporpeConstantReward-v0")])
    with pytest.raises(ValueError, match="SAME_STEP"):
        BatchLearner(BatchConfig(env="PporpeConstantReward-v0", n_steps=4, batch_size=4), envs)
    envs.close()


# ------------------------------------------------------------------------------------
# Runs: folder, determinism, resume
# ------------------------------------------------------------------------------------
def test_run_folder_contents(tmp_path: Path) -> None:
    result = train_batch(tiny(), tmp_path, progress=False)
    names = {p.name for p in tmp_path.iterdir()}
    assert {
        "config.json",
        "episodes.csv",
        "checkpoint.pt",
        "evaluation.json",
        "done.json",
        "tensorboard",
    } <= names
    saved = json.loads((tmp_path / "config.json").read_text())
    assert saved["kind"] == "batch" and saved["method"] == "ppo" and saved["n_envs"] == 2
    assert result.updates == 4 and result.total_steps == 256
    records = read_records(tmp_path / "episodes.csv")
    assert records == result.records and len(records) > 0
    assert [r.episode for r in records] == list(range(len(records)))
    assert sum(r.length for r in records) <= 256
    diags = [r.diagnostics for r in records]
    assert all(d is not None and d.trace_decay is None for d in diags)  # no traces
    assert all(d is not None and 0.0 <= d.past_threshold <= 1.0 for d in diags)
    assert all(d is not None and d.reg_amount >= 0.0 for d in diags)
    assert all(r.ret == r.length for r in records)  # reward 1/step
    ev = json.loads((tmp_path / "evaluation.json").read_text())
    assert ev["episodes"] == 2 and ev["median"] == pytest.approx(np.median(ev["returns"]))
    done = json.loads((tmp_path / "done.json").read_text())
    assert done["updates"] == 4 and done["total_steps"] == 256
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(tmp_path / "tensorboard"))
    events.Reload()
    tags = set(events.Tags()["scalars"])  # one sink: episode and update scalars in one log
    assert {"train/ret", "update/approx_kl", "update/policy_loss"} <= tags
    assert len(events.Scalars("update/approx_kl")) == 4
    assert set(result.last_stats) >= {"policy_loss", "approx_kl", "past_threshold"}
    again = train_batch(tiny(), tmp_path, progress=False)  # done: returns at once
    assert strip_time(again.records) == strip_time(result.records)
    with pytest.raises(ValueError, match="different config"):
        train_batch(tiny(lr=1e-3), tmp_path, progress=False)
    cfg, learner = load_batch_learner(tmp_path)
    assert cfg == tiny()
    assert learner.act_deterministic(np.zeros(5, np.float32)).shape == (1,)
    learner.close()


def test_same_seed_same_numbers(tmp_path: Path) -> None:
    a = train_batch(tiny(eval_episodes=0, method="rpe"), tmp_path / "a", progress=False)
    b = train_batch(tiny(eval_episodes=0, method="rpe"), tmp_path / "b", progress=False)
    assert strip_time(a.records) == strip_time(b.records)
    sa = torch.load(tmp_path / "a" / "checkpoint.pt", weights_only=False)
    sb = torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=False)
    assert torch.equal(sa["learner"]["theta"], sb["learner"]["theta"])
    c = train_batch(tiny(eval_episodes=0, method="rpe", seed=4), tmp_path / "c", progress=False)
    sc = torch.load(tmp_path / "c" / "checkpoint.pt", weights_only=False)
    assert not torch.equal(sa["learner"]["theta"], sc["learner"]["theta"])
    assert strip_time(a.records) != strip_time(c.records)


class Crash(RuntimeError):
    pass


def test_resume_continues_exactly_like_the_uninterrupted_run(tmp_path: Path) -> None:
    cfg = tiny(eval_episodes=0, total_steps=384, method="rb")  # 6 updates, checkpoints at 2, 4
    full = train_batch(cfg, tmp_path / "full", progress=False)

    def crash_at_update_5(learner: BatchLearner, stats: UpdateStats, t: float) -> None:
        if learner.updates == 5:
            raise Crash

    run = tmp_path / "crashed"
    with pytest.raises(Crash):
        train_batch(cfg, run, progress=False, on_update=crash_at_update_5)
    state = torch.load(run / "checkpoint.pt", weights_only=False)
    assert state["learner"]["updates"] == 4  # update 5 is lost
    assert not (run / "done.json").exists()
    resumed = train_batch(cfg, run, progress=False)
    assert resumed.resumed_from == 4 and resumed.updates == 6
    assert strip_time(resumed.records) == strip_time(full.records)
    assert strip_time(read_records(run / "episodes.csv")) == strip_time(full.records)
    s_full = torch.load(tmp_path / "full" / "checkpoint.pt", weights_only=False)
    s_res = torch.load(run / "checkpoint.pt", weights_only=False)
    assert torch.equal(s_full["learner"]["theta"], s_res["learner"]["theta"])
    np.testing.assert_array_equal(s_full["learner"]["raw_obs"], s_res["learner"]["raw_obs"])
    np.testing.assert_array_equal(
        s_full["learner"]["normalizer"]["obs_rms"]["mean"],
        s_res["learner"]["normalizer"]["obs_rms"]["mean"],
    )


def test_async_vector_env_gives_the_same_numbers(tmp_path: Path) -> None:
    a = train_batch(tiny(eval_episodes=0, total_steps=128), tmp_path / "a", progress=False)
    b = train_batch(
        tiny(eval_episodes=0, total_steps=128, vec_env="async"), tmp_path / "b", progress=False
    )
    assert strip_time(a.records) == strip_time(b.records)
    sa = torch.load(tmp_path / "a" / "checkpoint.pt", weights_only=False)
    sb = torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=False)
    assert torch.equal(sa["learner"]["theta"], sb["learner"]["theta"])
