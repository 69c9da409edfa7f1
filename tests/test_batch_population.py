"""The batch population (pporpe.batch.population): K batch runs in lockstep in one process.

The reference is the solo trainer: a member must compute what a :class:`BatchLearner` of
its own computes with the same config and seed (the stacked networks, normalisers,
optimiser and random streams are a different implementation of the same numbers), bit
for bit: episodes, every update statistic, the parameters after every update, and the
state a checkpoint keeps.
"""

from __future__ import annotations

import math
import os
import signal
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch
import warm_process
from resume_points import checkpointed_records, resume_problems

from pporpe.batch import BatchConfig, BatchLearner, train_batch
from pporpe.batch.kind import BatchPopulationTrainer
from pporpe.batch.population import BatchPopulation, check_member
from pporpe.experiments.grids.reproduce import reproduce
from pporpe.experiments.grids.spec import load_spec
from pporpe.runs.logger import EpisodeRecord, LoggedUpdate, read_records, read_updates
from pporpe.runs.loop import run_queue


@pytest.fixture(autouse=True)
def one_thread() -> Any:
    """torch on one thread, as the run loop trains (and far faster on small matrices)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


class DriftTask(gym.Env):  # type: ignore[type-arg]
    """Observations drawn from the seeded RNG, a reward that depends on the action, a
    random termination (about 1 step in 40) and a time limit of 30 steps: both ends of an
    episode occur within a few rollouts."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, (3,), np.float64)
    action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)

    def reset(self, *, seed: int | None = None, options: Any = None) -> Any:
        super().reset(seed=seed)
        self.x = self.np_random.normal(size=3)
        return self.x.copy(), {}

    def step(self, action: Any) -> Any:
        a = np.asarray(action, dtype=np.float64)
        reward = 2.0 - abs(a[0] - 0.5 * self.x[0]) - abs(a[1] + self.x[1]) + 0.1 * self.x[2]
        self.x = 0.8 * self.x + 0.5 * self.np_random.normal(size=3)
        terminated = bool(self.np_random.random() < 0.025)
        return self.x.copy(), float(reward), terminated, False, {}


gym.register("PporpeDriftTask-v0", entry_point=DriftTask, max_episode_steps=30)

DRIFT = BatchConfig(
    env="PporpeDriftTask-v0",
    n_envs=2,
    n_steps=48,
    batch_size=24,
    n_epochs=3,
    total_steps=96 * 4,
    layers=2,
    units=16,
    eval_episodes=0,
    checkpoint_every=1,
)
MIXED = [
    replace(DRIFT, seed=0, target_kl=1e-5, ent_coef=0.01, lr_schedule="linear"),
    replace(DRIFT, seed=1, method="rpe", lr=1e-3, max_grad_norm=None, gamma=0.95),
    replace(DRIFT, seed=2, method="rb", adam_eps=1e-7, clip_vf=0.2, gae_lambda=0.9,
            clip_obs=2.0, clip_reward=3.0, vf_coef=0.7, target_kl=3e-6),
    replace(DRIFT, seed=3, eps=0.1, bootstrap_truncated=False, total_steps=96 * 6),
]  # fmt: skip
"""Members that differ in every per-member setting (and budget); two of them stop some
updates early at their target KL."""


def episode_rows(episodes: list[Any]) -> list[tuple[Any, ...]]:
    return [(e.env_index, e.ret, e.length, e.total_steps, e.terminated) for e in episodes]


def same_stats(a: dict[str, float], b: dict[str, float]) -> bool:
    return a.keys() == b.keys() and all(
        a[k] == b[k] or (math.isnan(a[k]) and math.isnan(b[k])) for k in a
    )


def solo_run(cfg: BatchConfig, updates: int) -> tuple[list[Any], BatchLearner]:
    """``updates`` updates of a run alone, seeded as train_batch seeds it: per update its
    episodes, statistics and parameters."""
    torch.manual_seed(cfg.seed)
    learner = BatchLearner(cfg)
    out = []
    for _ in range(updates):
        episodes = learner.collect_rollouts()
        stats = learner.train()
        out.append((episode_rows(episodes), stats.as_dict(), learner.model.theta.detach().clone()))
    return out, learner


def assert_same_states(solo: BatchLearner, member: dict[str, Any]) -> None:
    """A member's checkpoint state equals the run alone's, bit for bit."""
    ref = {"learner": solo.state_dict(), "torch_rng": torch.get_rng_state()}

    def equal(a: Any, b: Any, where: str) -> None:
        if isinstance(a, dict):
            assert a.keys() == b.keys(), where
            for key in a:
                equal(a[key], b[key], f"{where}.{key}")
        elif isinstance(a, list | tuple):
            assert len(a) == len(b), where
            for i, (x, y) in enumerate(zip(a, b, strict=True)):
                equal(x, y, f"{where}[{i}]")
        elif isinstance(a, torch.Tensor):
            assert torch.equal(a, b), where
        elif isinstance(a, np.ndarray):
            assert a.dtype == b.dtype and np.array_equal(a, b), where
        else:
            assert a == b, where

    equal(ref, member, "state")


def check_population_against_solo(cfgs: list[BatchConfig], updates: int) -> list[list[Any]]:
    """Train ``cfgs`` as one population for ``updates`` updates and compare every member,
    update by update, with its run alone; returns every member's (episodes, statistics,
    parameters) of every update."""
    pop = BatchPopulation(cfgs[0], len(cfgs))
    for k, cfg in enumerate(cfgs):
        pop.start(k, cfg)
    per_member: list[list[Any]] = [[] for _ in cfgs]
    for _ in range(updates):
        for k, report in pop.update().items():
            assert report.error is None and report.stats is not None
            theta = pop.model.theta[k].detach().clone()
            per_member[k].append((episode_rows(report.episodes), report.stats.as_dict(), theta))
    for k, cfg in enumerate(cfgs):
        ref, learner = solo_run(cfg, updates)
        for u, ((eps_a, st_a, th_a), (eps_b, st_b, th_b)) in enumerate(
            zip(ref, per_member[k], strict=True)
        ):
            assert eps_a == eps_b, (k, u)
            assert same_stats(st_a, st_b), (k, u, st_a, st_b)
            assert torch.equal(th_a, th_b), (k, u, float((th_a - th_b).abs().max()))
        assert_same_states(learner, pop.member_state(k))
        learner.close()
    pop.close()
    return per_member


def test_members_with_mixed_settings_equal_their_runs_alone_bit_for_bit() -> None:
    """Four members differing in method, seed, learning rate and schedule, clipping, Adam's
    epsilon, gamma, lambda, loss weights, normalisation bounds, target KL and budget: each
    equals its run alone over four updates (two stop an update early at the target KL;
    episodes end by termination and by the time limit)."""
    updates = check_population_against_solo(MIXED, 4)
    epochs = [[stats["epochs"] for _, stats, _ in member] for member in updates]
    assert min(epochs[0] + epochs[2]) < DRIFT.n_epochs  # the target KL stopped an update
    assert min(epochs[1] + epochs[3]) == DRIFT.n_epochs
    ends = [(ep[2], ep[4]) for member in updates for eps, _, _ in member for ep in eps]
    assert (30, False) in ends and any(term for _, term in ends)  # truncated and terminated


def test_hopper_sized_members_equal_their_runs_alone_bit_for_bit() -> None:
    """Hopper-v4 with CleanRL's network (64 x 64 tanh, value clipping, linear annealing):
    twelve PPO, PPO-RPE and PPO-RB members (enough that the stacked policy head's tensors
    fill vector registers where a run alone's do not) equal their runs alone over two
    updates."""
    pytest.importorskip("mujoco")
    base = BatchConfig(
        env="Hopper-v4", n_steps=128, batch_size=64, n_epochs=2, total_steps=128 * 2,
        clip_vf=0.2, lr_schedule="linear", eval_episodes=0,
    )  # fmt: skip
    methods = ("ppo", "rpe", "rb")
    cfgs = [replace(base, seed=s, method=methods[s % 3]) for s in range(12)]
    check_population_against_solo(cfgs, 2)


def test_a_member_continues_a_run_alone_and_a_run_alone_continues_a_member() -> None:
    """A run's checkpoint moves between a process of its own and a population: 2 updates
    alone then 2 in a population (and back) equal 4 updates alone."""
    cfg = MIXED[0]
    ref, learner = solo_run(cfg, 4)
    learner.close()
    torch.manual_seed(cfg.seed)
    alone = BatchLearner(cfg)
    for _ in range(2):
        alone.collect_rollouts()
        alone.train()
    state = {"learner": alone.state_dict(), "torch_rng": torch.get_rng_state()}
    alone.close()
    pop = BatchPopulation(cfg, 2)
    pop.start(1, MIXED[2])
    pop.start(0, cfg, state)
    report = pop.update()[0]
    assert report.stats is not None and same_stats(report.stats.as_dict(), ref[2][1])
    back = pop.member_state(0)
    pop.close()
    torch.manual_seed(12345)  # overwritten by the state's stream
    again = BatchLearner(cfg)
    again.load_state_dict(back["learner"])
    torch.set_rng_state(back["torch_rng"])
    again.collect_rollouts()
    again.train()
    assert torch.equal(again.model.theta, ref[3][2])
    again.close()


def test_a_member_whose_loss_goes_nan_stops_alone() -> None:
    """Member 1's value network made NaN after its first update: its next update's loss is
    NaN and the trainer reports it (its slot alone); members 0 and 2 go on with the
    numbers of their runs alone."""
    cfgs = [replace(DRIFT, seed=s) for s in (0, 1, 2)]
    trainer = BatchPopulationTrainer(cfgs[0], 3)
    for k, cfg in enumerate(cfgs):
        trainer.start(k, cfg, None)
    first = trainer.advance()
    assert all(p.error is None for p in first.values())
    model = trainer.population.model
    with torch.no_grad():
        model.theta[1, model.template.flat.n_policy :] = float("nan")
    second = trainer.advance()
    assert second[1].error == "non-finite loss at update 2"
    assert second[0].error is None and second[2].error is None
    assert not trainer.parameters_finite(1) and trainer.parameters_finite(0)
    trainer.stop(1)
    third = trainer.advance()
    assert sorted(third) == [0, 2]
    for k in (0, 2):
        ref, learner = solo_run(cfgs[k], 3)
        learner.close()
        assert torch.equal(model.theta[k], ref[2][2])
        assert same_stats(dict(third[k].scalars), ref[2][1])
    trainer.close()


def records(results: list[Any]) -> list[list[EpisodeRecord]]:
    return [[replace(r, wall_time=0.0) for r in res.records] for res in results]


def logged_updates(run: Path) -> list[LoggedUpdate]:
    """A run's ``updates.csv`` without its wall times; its updates are 0..N-1 once each."""
    got = [replace(u, wall_time=0.0) for u in read_updates(run / "updates.csv")]
    assert [u.update for u in got] == list(range(len(got)))
    return got


PENDULUM = BatchConfig(
    env="pendulum", n_envs=2, n_steps=32, batch_size=16, n_epochs=2, layers=1, units=16,
    total_steps=64, eval_episodes=2, checkpoint_every=1,
)  # fmt: skip
QUEUE = [
    replace(PENDULUM, seed=0, total_steps=64 * 3),
    replace(PENDULUM, seed=1, method="rpe"),
    replace(PENDULUM, seed=2, method="rb", total_steps=64 * 2),
    replace(PENDULUM, seed=3, method="rpe", total_steps=64 * 4),
]
"""Four runs for three slots: the second finishes after one update and the queued fourth
takes its slot; after the third update one run is left and the trainer is compacted to it."""


def queue(root: Path) -> list[tuple[BatchConfig, Path]]:
    return [(c, root / f"s{c.seed}") for c in QUEUE]


def test_a_population_of_runs_gives_the_records_of_runs_alone(tmp_path: Path) -> None:
    """Four InvertedPendulum runs through one population of three slots (a slot refilled
    from the queue, the trainer compacted to the last run): the same records, test returns,
    parameters and random streams as each run trained alone, and the same again."""
    pop = run_queue(queue(tmp_path / "pop"), capacity=3, home=tmp_path / "pop")
    again = run_queue(queue(tmp_path / "again"), capacity=3, home=tmp_path / "again")
    alone = [train_batch(c, d, progress=False) for c, d in queue(tmp_path / "alone")]
    assert [r.chunks for r in pop] == [3, 1, 2, 4] and all(r.error is None for r in pop)
    assert records(pop) == records(alone) == records(again)
    assert [r.evaluation for r in pop] == [r.evaluation for r in alone]
    for c in QUEUE:  # a row per update, the same statistics as alone
        pop_updates = logged_updates(tmp_path / "pop" / f"s{c.seed}")
        assert len(pop_updates) == c.total_steps // 64
        assert pop_updates == logged_updates(tmp_path / "alone" / f"s{c.seed}")
        assert "approx_kl" in pop_updates[0].values
    for c in QUEUE:
        a = torch.load(tmp_path / "pop" / f"s{c.seed}" / "checkpoint.pt", weights_only=False)
        b = torch.load(tmp_path / "alone" / f"s{c.seed}" / "checkpoint.pt", weights_only=False)
        assert torch.equal(a["learner"]["theta"], b["learner"]["theta"])
        assert torch.equal(a["torch_rng"], b["torch_rng"])


def test_a_stopped_population_resumes_to_the_records_of_an_uninterrupted_one(
    tmp_path: Path,
) -> None:
    """The queue stopped by an exception in its third update (after the population's
    checkpoints of the first two) and restarted: every run's records are complete and equal
    to the uninterrupted queue's."""
    full = run_queue(queue(tmp_path / "full"), capacity=3, home=tmp_path / "full")
    seen: list[Any] = []

    class Stop(RuntimeError):
        pass

    def stop(trainer: Any, report: Any, t: float) -> None:
        seen.append(report)
        if len(seen) == 7:  # 3 runs' first update, 3 runs' second, one run's third
            raise Stop

    with pytest.raises(Stop):
        run_queue(queue(tmp_path / "b"), capacity=3, home=tmp_path / "b", on_chunk=stop)
    assert (tmp_path / "b" / "checkpoint.pt").exists()
    resumed = run_queue(queue(tmp_path / "b"), capacity=3, home=tmp_path / "b")
    assert any(r.resumed_from > 0 for r in resumed)
    assert records(resumed) == records(full)
    for c in QUEUE:
        assert logged_updates(tmp_path / "b" / f"s{c.seed}") == logged_updates(
            tmp_path / "full" / f"s{c.seed}"
        )


def test_members_must_share_the_shape_of_the_computation() -> None:
    with pytest.raises(ValueError, match=r"n_steps=64 \(not 48\), units=8 \(not 16\)"):
        check_member(DRIFT, replace(DRIFT, n_steps=64, units=8))
    with pytest.raises(ValueError, match="policy='normal' only"):
        check_member(DRIFT, replace(DRIFT, policy="student_t"))
    pop = BatchPopulation(DRIFT, 2)
    with pytest.raises(ValueError, match=r"batch_size=16 \(not 24\)"):
        pop.start(0, replace(DRIFT, batch_size=16))
    pop.start(0, DRIFT)
    with pytest.raises(RuntimeError, match="slot 0 already holds a run"):
        pop.start(0, DRIFT)
    pop.close()


KILL_SPEC = """
name = "killbatch"
kind = "batch"
methods = ["ppo", "rpe"]
seeds = [0, 1]
eval_episodes = 1
checkpoint_every = 1

[learner]
layers = 1
units = 8
n_envs = 1
n_steps = 64
batch_size = 32
n_epochs = 2

[[tasks]]
env = "pendulum"
steps = 2560
"""


def _launch(spec: Path, out: Path) -> warm_process.Started:
    """``pporpe reproduce`` as a job of its own (:func:`warm_process.start`)."""
    args = ["--workers", "1", "--population", "2", "--checkpoint-seconds", "0", "--quiet"]
    return warm_process.start(["reproduce", str(spec), "--out", str(out), *args])


def test_sigkill_a_batch_population_then_resume_gives_the_same_records(tmp_path: Path) -> None:
    """Four batch runs (two methods, two seeds) through one worker's population of two
    slots: killed with SIGKILL mid-way and restarted, every run's records are complete and
    equal to those of the uninterrupted grid (and of the runs alone)."""
    spec_path = tmp_path / "kill.toml"
    spec_path.write_text(KILL_SPEC)
    spec = load_spec(spec_path)
    ref = tmp_path / "ref"
    assert reproduce(spec, ref, workers=1, population=2, progress=False).ok
    assert len(list((ref / "populations").glob("*/population.json"))) == 1
    out = tmp_path / "out"
    proc = _launch(spec_path, out)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:  # until the population has checkpointed a few times
        lines = [len(p.read_text().splitlines()) for p in out.glob("pendulum/*/seed*/episodes.csv")]
        if any(n > 8 for n in lines) and list(out.glob("populations/*/checkpoint.pt")):
            break
        time.sleep(0.02)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    time.sleep(0.5)
    unfinished = [r.key for r in spec.runs if not (out / r.key / "done.json").exists()]
    assert unfinished, "the kill came too late to test resuming"
    saved = checkpointed_records(out)
    proc = _launch(spec_path, out)
    assert proc.wait(timeout=300) == 0
    assert resume_problems(saved) == []  # resumed from the checkpoints, not started over
    for run in spec.runs:
        got = read_records(out / run.key / "episodes.csv")
        want = read_records(ref / run.key / "episodes.csv")
        assert [r.episode for r in got] == list(range(len(want)))
        assert [replace(r, wall_time=0.0) for r in got] == [replace(r, wall_time=0.0) for r in want]
        assert logged_updates(out / run.key) == logged_updates(ref / run.key)
    alone = train_batch(spec.runs[0].config, tmp_path / "alone", progress=False)
    assert records([alone])[0] == [
        replace(r, wall_time=0.0) for r in read_records(ref / spec.runs[0].key / "episodes.csv")
    ]


def test_members_with_layer_norm_swish_and_a_state_dependent_scale_equal_their_runs_alone() -> (
    None
):
    """Networks whose per-member sizes do not fill whole vector registers (20 units, one
    environment: SiLU's vectorised and scalar kernels round differently, so the probe
    computes it member by member) with LayerNorm and the scale as a network output."""
    base = replace(DRIFT, n_envs=1, n_steps=40, batch_size=20, units=20, activation="swish",
                   layer_norm=True, scale="state", total_steps=40 * 3)  # fmt: skip
    cfgs = [replace(base, seed=s, method=m) for s, m in ((5, "rpe"), (6, "ppo"), (7, "rb"))]
    check_population_against_solo(cfgs, 3)
