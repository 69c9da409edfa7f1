"""pporpe's batch PPO / PPO-RB / PPO-RPE against Stable-Baselines3's PPO, side by side.

Both libraries train in the same process, one after the other for each seed (the order
rotates from seed to seed so that machine noise hits them alike), with torch on one
thread, on the same tasks with the same settings:

* the same environments (``pporpe.envs.make_env``; sub-environment i seeded seed + i),
  stepped sequentially (Gymnasium ``SyncVectorEnv`` / SB3 ``DummyVecEnv``);
* the same hyperparameters (``pporpe.batch.zoo_config``): n_envs, n_steps, batch size,
  epochs, learning rate, clip range (eps), GAE lambda, gamma, value and entropy weights,
  gradient clipping, Adam eps 1e-5, network sizes and activations, initialisation
  (``init``/``ortho_init``), initial log std, observation and reward normalisation
  (clip 10), and actions clipped into the box (pporpe's ``action_bound="clip"`` is what
  SB3 does). gSDE is not implemented in pporpe, so SB3 runs with ``use_sde=False`` too
  although the zoo's PyBullet entries use it;
* the same number of environment steps (whole rollouts) and the same evaluations: after
  every ``eval_every`` updates, ``eval_episodes`` deterministic test episodes through
  ``pporpe.evaluation.evaluate_policy`` (frozen observation statistics), and at the end
  ``final_episodes`` test episodes.

Reported per task and trainer (medians over seeds):

(a) training steps/s: environment steps per wall second of training (acting + learning +
    the trainer's own logging; evaluation time excluded), and ours / SB3 (target >= 1.2);
(b) final test return: median of the final test episodes (target: at least SB3's);
(c) time to reach a median test return of ``threshold`` (InvertedPendulum, 950): training
    seconds up to the first evaluation at or above it, ours / SB3 (< 1: ours is faster).

Default budgets fit a 2-core machine in about 20 minutes (see ``--help``);
``--budget large`` gives longer runs.

    python benchmarks/vs_sb3.py [--envs pendulum halfcheetah] [--seeds 3] [--budget large]

Needs stable-baselines3 (``pip install -c constraints.txt stable-baselines3``); it is not
a runtime dependency of pporpe.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import write_json

from pporpe.batch import BatchConfig, BatchLearner, UpdateStats, train_batch, zoo_config
from pporpe.envs import make_env
from pporpe.evaluation import EVAL_SEED_OFFSET, EvalResult, evaluate_policy

if TYPE_CHECKING:
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.vec_env import VecNormalize

BUDGETS: dict[str, dict[str, dict[str, int]]] = {
    # total_steps per run (whole rollouts); evaluate every N updates (0: only at the end)
    # with eval_episodes test episodes; final test episodes after training
    "default": {
        "pendulum": {"steps": 61_440, "eval_every": 2, "eval_episodes": 5, "final": 10},
        "halfcheetah": {"steps": 40_960, "eval_every": 0, "eval_episodes": 3, "final": 5},
    },
    "large": {
        "pendulum": {"steps": 200_704, "eval_every": 2, "eval_episodes": 10, "final": 50},
        "halfcheetah": {"steps": 1_007_616, "eval_every": 10, "eval_episodes": 5, "final": 50},
    },
}
"""Per-task budgets (steps are whole rollouts of the task's n_envs * n_steps)."""

OURS = ("ppo", "rb", "rpe")

Policy = Callable[[np.ndarray], np.ndarray]
"""A deterministic policy: observations of one environment to its action."""


@dataclass(frozen=True)
class Budget:
    """One task's budget (an entry of :data:`BUDGETS`)."""

    steps: int
    """Environment steps per run (rounded by ``zoo_config`` to whole rollouts)."""
    eval_every: int
    """Test after every this many updates (0: only after the last)."""
    eval_episodes: int
    """Test episodes of each test on the way."""
    final: int
    """Test episodes after training."""

    @classmethod
    def of(cls, budget: str, env: str, steps: int | None) -> Budget:
        """The task's entry of ``BUDGETS[budget]`` (HalfCheetah's for a task without one),
        with ``steps`` in place of its steps unless None."""
        chosen = cls(**BUDGETS[budget].get(env, BUDGETS[budget]["halfcheetah"]))
        return chosen if steps is None else replace(chosen, steps=steps)


@dataclass(frozen=True)
class Evaluation:
    """A test on the way (a point of a run's history)."""

    steps: int
    """Environment steps trained so far."""
    train_time: float
    """Training seconds so far (evaluations excluded)."""
    median: float
    """Median return of the test episodes."""


@dataclass(frozen=True)
class RunResult:
    """One trainer's run on one seed, as ``runs`` of the JSON keeps it."""

    steps: int
    train_time: float
    steps_per_s: float
    history: tuple[Evaluation, ...]
    final_median: float
    final_returns: list[float]
    seed: int
    time_to_threshold: float | None
    """Training seconds up to the first test at or above the threshold (None: never)."""


def _history_time_to(history: tuple[Evaluation, ...], threshold: float) -> float | None:
    for h in history:
        if h.median >= threshold:
            return h.train_time
    return None


class Evaluations:
    """The tests of one run, on its budget's schedule: ``eval_episodes`` test episodes after
    every ``eval_every`` updates and after the last, and ``final`` test episodes after the
    last (``pporpe.evaluation.evaluate_policy``, environment seed ``seed + EVAL_SEED_OFFSET``)."""

    def __init__(self, cfg: BatchConfig, budget: Budget) -> None:
        self.cfg = cfg
        self.budget = budget
        self.history: list[Evaluation] = []
        self.final: EvalResult | None = None

    def after_update(
        self, act: Policy, updates: int, steps: int, train_time: float, last: bool
    ) -> None:
        """Test as the schedule says after update number ``updates`` (``last``: the run's last)."""
        env, every, seed = self.cfg.env, self.budget.eval_every, self.cfg.seed + EVAL_SEED_OFFSET
        if (every and updates % every == 0) or last:
            ev = evaluate_policy(act, env, self.budget.eval_episodes, seed)
            self.history.append(Evaluation(steps, train_time, ev.median))
        if last:
            self.final = evaluate_policy(act, env, self.budget.final, seed)

    def on_batch_update(self, learner: BatchLearner, stats: UpdateStats, train_time: float) -> None:
        """``train_batch``'s ``on_update``."""
        last = learner.updates == self.cfg.n_updates
        self.after_update(
            learner.act_deterministic, learner.updates, learner.total_steps, train_time, last
        )

    def result(self, steps: int, train_time: float, threshold: float) -> RunResult:
        """The run's result, once trained for ``steps`` in ``train_time`` training seconds."""
        assert self.final is not None, "the run has not finished"
        history = tuple(self.history)
        return RunResult(
            steps=steps,
            train_time=train_time,
            steps_per_s=steps / train_time,
            history=history,
            final_median=self.final.median,
            final_returns=self.final.returns,
            seed=self.cfg.seed,
            time_to_threshold=_history_time_to(history, threshold),
        )


def run_ours(cfg: BatchConfig, budget: Budget, threshold: float) -> RunResult:
    """Train with ``train_batch`` (run folder in a temporary directory), evaluating on the way."""
    tests = Evaluations(cfg, budget)
    with tempfile.TemporaryDirectory() as tmp:
        run_dir = Path(tmp) / "run"
        result = train_batch(replace(cfg, eval_episodes=0), run_dir, False, tests.on_batch_update)
    return tests.result(result.total_steps, result.train_time, threshold)


class Stopwatch:
    """Training seconds: the wall time since :meth:`start`, less the pauses."""

    def __init__(self) -> None:
        self.started = 0.0
        self.excluded = 0.0
        self.paused = 0.0

    def start(self) -> None:
        self.started = time.perf_counter()

    def pause(self) -> float:
        """Stop counting; returns the training seconds so far."""
        self.paused = time.perf_counter()
        return self.paused - self.started - self.excluded

    def resume(self) -> None:
        self.excluded += time.perf_counter() - self.paused

    def elapsed(self) -> float:
        return time.perf_counter() - self.started - self.excluded


def _sb3_env(cfg: BatchConfig) -> VecNormalize:
    """The task's ``n_envs`` environments stepped in turn, normalised as ours are."""
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    return VecNormalize(
        DummyVecEnv([(lambda: make_env(cfg.env)) for _ in range(cfg.n_envs)]),
        norm_obs=cfg.normalize_obs,
        norm_reward=cfg.normalize_reward,
        clip_obs=cfg.clip_obs,
        clip_reward=cfg.clip_reward,
        gamma=cfg.gamma,
        epsilon=1e-8,
    )


def _sb3_model(cfg: BatchConfig, venv: VecNormalize) -> PPO:
    """SB3's PPO with ``cfg``'s hyperparameters, network and initialisation."""
    from stable_baselines3 import PPO

    activation = {"relu": torch.nn.ReLU, "tanh": torch.nn.Tanh, "swish": torch.nn.SiLU}
    return PPO(
        "MlpPolicy",
        venv,
        learning_rate=cfg.lr,
        n_steps=cfg.n_steps,
        batch_size=cfg.batch_size,
        n_epochs=cfg.n_epochs,
        gamma=cfg.gamma,
        gae_lambda=cfg.gae_lambda,
        clip_range=cfg.eps,
        clip_range_vf=cfg.clip_vf,
        normalize_advantage=cfg.adv_norm != "none",
        ent_coef=cfg.ent_coef,
        vf_coef=cfg.vf_coef,
        max_grad_norm=cfg.max_grad_norm if cfg.max_grad_norm is not None else 1e12,
        target_kl=cfg.target_kl,
        use_sde=False,
        seed=cfg.seed,
        device="cpu",
        verbose=0,
        policy_kwargs=dict(
            net_arch=dict(pi=[cfg.units] * cfg.layers, vf=[cfg.units] * cfg.layers),
            activation_fn=activation[cfg.activation],
            ortho_init=cfg.init == "orthogonal",
            log_std_init=cfg.log_std_init,
        ),
    )


def _sb3_act(model: PPO, venv: VecNormalize, obs: np.ndarray) -> np.ndarray:
    """The model's deterministic action for raw observations (normalised with frozen stats)."""
    action, _ = model.predict(venv.normalize_obs(obs), deterministic=True)
    return np.asarray(action)


def _sb3_callback(act: Policy, tests: Evaluations, clock: Stopwatch) -> BaseCallback:
    """An SB3 callback that counts the updates and hands each to ``tests``, its time paused."""
    from stable_baselines3.common.callbacks import BaseCallback

    class Evaluate(BaseCallback):
        def __init__(self, act: Policy, tests: Evaluations, clock: Stopwatch) -> None:
            super().__init__()
            self.act, self.tests, self.clock = act, tests, clock
            self.updates = 0

        def _on_step(self) -> bool:
            return True

        def _after_update(self, last: bool) -> None:
            train_time = self.clock.pause()
            self.tests.after_update(
                self.act, self.updates, int(self.num_timesteps), train_time, last
            )
            self.clock.resume()

        def _on_rollout_start(self) -> None:  # after each update but the last
            if self.num_timesteps > 0:
                self.updates += 1
                self._after_update(last=False)

        def _on_training_end(self) -> None:
            self.updates += 1
            self._after_update(last=True)

    return Evaluate(act, tests, clock)


def run_sb3(cfg: BatchConfig, budget: Budget, threshold: float) -> RunResult:
    """Train Stable-Baselines3's PPO with the same settings, evaluating on the same schedule."""
    venv = _sb3_env(cfg)
    model = _sb3_model(cfg, venv)
    tests, clock = Evaluations(cfg, budget), Stopwatch()
    callback = _sb3_callback(partial(_sb3_act, model, venv), tests, clock)
    clock.start()
    model.learn(total_timesteps=cfg.n_updates * cfg.rollout_size, callback=callback)
    train_time = clock.elapsed()
    venv.close()
    return tests.result(int(model.num_timesteps), train_time, threshold)


def _median(xs: list[float]) -> float:
    return float(statistics.median(xs)) if xs else float("nan")


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", nargs="+", default=["pendulum", "halfcheetah"])
    parser.add_argument("--seeds", type=int, default=3, help="seeds per trainer (>= 3)")
    parser.add_argument("--budget", choices=sorted(BUDGETS), default="default")
    parser.add_argument("--steps", type=int, default=None, help="override total steps per run")
    parser.add_argument("--methods", nargs="+", default=list(OURS), choices=list(OURS))
    parser.add_argument("--no-sb3", action="store_true", help="skip Stable-Baselines3")
    parser.add_argument("--threshold", type=float, default=950.0, help="test return for (c)")
    parser.add_argument("--out", default="benchmarks/results/vs_sb3.json")
    return parser.parse_args()


def _method(trainer: str) -> Any:
    """The pporpe method of a trainer's configuration (SB3's is PPO)."""
    return "ppo" if trainer == "sb3" else trainer


def _announce(env: str, base: BatchConfig, budget: Budget, seeds: int) -> None:
    print(
        f"== {env}: {base.n_updates} updates x {base.rollout_size} steps "
        f"= {base.n_updates * base.rollout_size} steps per run, {seeds} seeds, "
        f"eval every {budget.eval_every} updates ({budget.eval_episodes} episodes), "
        f"final {budget.final} episodes",
        flush=True,
    )


def _print_run(name: str, res: RunResult, threshold: float) -> None:
    ttt = res.time_to_threshold
    print(
        f"  seed {res.seed} {name:4s}: {res.steps_per_s:7.0f} steps/s, "
        f"final median {res.final_median:8.1f}, "
        f"time to {threshold:g}: "
        f"{'-' if ttt is None else f'{ttt:.1f} s'}",
        flush=True,
    )


def train_task(
    base: BatchConfig, budget: Budget, trainers: list[str], seeds: int, threshold: float
) -> dict[str, list[RunResult]]:
    """Every trainer's runs on one task, seed by seed, the trainers' order rotating."""
    runs: dict[str, list[RunResult]] = {name: [] for name in trainers}
    for seed in range(seeds):
        order = trainers[seed % len(trainers) :] + trainers[: seed % len(trainers)]
        for name in order:
            cfg = replace(base, seed=seed, method=_method(name))
            train = run_sb3 if name == "sb3" else run_ours
            res = train(cfg, budget, threshold)
            runs[name].append(res)
            _print_run(name, res, threshold)
    return runs


def _against_sb3(rs: list[RunResult], sb3: list[RunResult], final_median: float) -> dict[str, Any]:
    """A trainer's ratios to SB3's runs (seed by seed) and its final median less SB3's."""
    ratios = [a.steps_per_s / b.steps_per_s for a, b in zip(rs, sb3, strict=True)]
    against: dict[str, Any] = {
        "sps_ratio_vs_sb3": _median(ratios),
        "final_minus_sb3": final_median - _median([r.final_median for r in sb3]),
    }
    ttt = [r.time_to_threshold for r in rs if r.time_to_threshold is not None]
    t_sb3 = [r.time_to_threshold for r in sb3 if r.time_to_threshold is not None]
    if len(ttt) == len(rs) and len(t_sb3) == len(sb3):
        against["time_ratio_vs_sb3"] = _median([a / b for a, b in zip(ttt, t_sb3, strict=True)])
    return against


def summary_row(
    env: str, name: str, base: BatchConfig, rs: list[RunResult], sb3: list[RunResult]
) -> dict[str, Any]:
    """A trainer's row of the JSON's ``rows``: medians over its seeds, then against SB3."""
    reached = [r.time_to_threshold for r in rs if r.time_to_threshold is not None]
    final = _median([r.final_median for r in rs])
    row: dict[str, Any] = {
        "env": env,
        "trainer": name,
        "config": dict(vars(replace(base, method=_method(name)))),
        "steps": rs[0].steps,
        "steps_per_s": _median([r.steps_per_s for r in rs]),
        "final_median": final,
        "time_to_threshold": _median(reached) if len(reached) == len(rs) else None,
        "reached": f"{len(reached)}/{len(rs)}",
    }
    if sb3 and name != "sb3":
        row.update(_against_sb3(rs, sb3, final))
    return row


def _num(x: Any, spec: str) -> str:
    return "-" if x is None else format(x, spec)


def print_table(rows: list[dict[str, Any]], threshold: float, wall: float) -> None:
    print()
    header = (
        f"{'env':12s} {'trainer':7s} {'steps':>8s} {'steps/s':>8s} {'x SB3':>6s} "
        f"{'final med':>10s} {'- SB3':>8s} {'t->' + format(threshold, 'g'):>8s} "
        f"{'x SB3':>6s} {'reached':>7s}"
    )
    print(header)
    print("-" * len(header))
    for r in rows:
        print(
            f"{r['env']:12s} {r['trainer']:7s} {r['steps']:8d} {r['steps_per_s']:8.0f} "
            f"{_num(r.get('sps_ratio_vs_sb3'), '6.2f'):>6s} {r['final_median']:10.1f} "
            f"{_num(r.get('final_minus_sb3'), '+8.1f'):>8s} "
            f"{_num(r['time_to_threshold'], '8.1f'):>8s} "
            f"{_num(r.get('time_ratio_vs_sb3'), '6.2f'):>6s} {r['reached']:>7s}"
        )
    print(
        f"targets: steps/s x SB3 >= 1.2; final median >= SB3's; time to "
        f"{threshold:g} ours/SB3 (lower is better). Total wall time {wall:.0f} s."
    )


def _sb3_version() -> str | None:
    try:
        from importlib.metadata import version

        return version("stable-baselines3")
    except Exception:
        return None


def write_results(
    args: argparse.Namespace,
    wall: float,
    rows: list[dict[str, Any]],
    runs: dict[str, dict[str, list[RunResult]]],
) -> Path:
    return write_json(
        args.out,
        {
            "budget": args.budget,
            "budgets": {env: BUDGETS[args.budget].get(env) for env in args.envs},
            "seeds": args.seeds,
            "threshold": args.threshold,
            "stable_baselines3": _sb3_version(),
            "wall_time_s": wall,
            "rows": rows,
            "runs": {
                env: {name: [asdict(r) for r in rs] for name, rs in by_trainer.items()}
                for env, by_trainer in runs.items()
            },
        },
    )


def main() -> None:
    args = parse_args()
    torch.set_num_threads(1)
    trainers = ([] if args.no_sb3 else ["sb3"]) + list(args.methods)
    rows: list[dict[str, Any]] = []
    runs: dict[str, dict[str, list[RunResult]]] = {}
    t_all = time.perf_counter()
    for env in args.envs:
        budget = Budget.of(args.budget, env, args.steps)
        base = zoo_config(env, total_steps=budget.steps)
        _announce(env, base, budget, args.seeds)
        runs[env] = train_task(base, budget, trainers, args.seeds, args.threshold)
        sb3 = runs[env].get("sb3", [])
        rows += [summary_row(env, name, base, runs[env][name], sb3) for name in trainers]
    wall = time.perf_counter() - t_all
    print_table(rows, args.threshold, wall)
    path = write_results(args, wall, rows, runs)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
