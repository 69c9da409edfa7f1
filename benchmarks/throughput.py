"""Throughput of the online learner: the environments, the scalar reference, and the
population learner at several K, side by side in one process (torch on one thread).

It measures, in alternating rounds so that machine noise hits every variant alike:

* raw environment steps/s of the four tasks (random actions);
* the learner's cost per member-step on synthetic transitions of each task's size:
  the scalar reference learner (pporpe 0.2.0's single-run learner, kept in
  tests/reference_online.py) and the population learner at K = 1, 4, 15, 30, 60
  (compiled update); as member-steps/s and as the ratio to the task's env step;
* the estimated wall time of experiments/paper-full.toml on this machine from those rates.

    python benchmarks/throughput.py [--steps 150] [--rounds 3] [--ks 1 4 15 30 60]
                                    [--workers 2] [--out FILE]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from _common import write_json
from reference_online import ReferenceLearner

from pporpe.envs import env_spec_summary, make_env
from pporpe.experiments.grid import load_spec
from pporpe.online.config import OnlineConfig
from pporpe.online.population import PopulationLearner

HERE = Path(__file__).resolve().parent
TASKS = ("pendulum", "swingup", "halfcheetah", "ant")
MAX_EPISODE_STEPS = 1000
"""The time limit of the four Bullet tasks under Gymnasium: an episode's length bound."""


def spaces(task: str) -> dict[str, Any]:
    env = make_env(task)
    try:
        return env_spec_summary(env)
    finally:
        env.close()


def env_rate(task: str, steps: int, seed: int) -> float:
    """Raw environment steps/s with random actions."""
    env = make_env(task, seed=seed)
    env.reset(seed=seed)
    env.action_space.seed(seed)
    t0 = time.perf_counter()
    for _ in range(steps):
        _, _, term, trunc, _ = env.step(env.action_space.sample())
        if term or trunc:
            env.reset()
    dt = time.perf_counter() - t0
    env.close()
    return steps / dt


class PopulationBench:
    """A population of K members of mixed methods stepping on synthetic transitions."""

    def __init__(self, spec: dict[str, Any], k: int) -> None:
        methods = ("ppo", "rb", "rpe")
        cfgs = [OnlineConfig(method=methods[i % 3], compile=True) for i in range(k)]
        self.k, self.obs_dim = k, spec["obs_dim"]
        self.learner = PopulationLearner(
            self.obs_dim, spec["action_low"], spec["action_high"], cfgs, list(range(k))
        )
        self.rng = np.random.default_rng(0)
        self.learner.begin_episode(range(k), self.rng.normal(size=(k, self.obs_dim)))
        self.run(30)  # compile and warm up

    def run(self, steps: int) -> float:
        """Seconds per member-step over ``steps`` steps."""
        k, rng, no = self.k, self.rng, np.zeros(self.k, dtype=bool)
        obs = rng.normal(size=(steps, k, self.obs_dim)).astype(np.float32)
        rewards = rng.normal(size=(steps, k))
        t0 = time.perf_counter()
        for t in range(steps):
            self.learner.step(rewards[t], obs[t], no, no)
        return (time.perf_counter() - t0) / (steps * k)


class ReferenceBench:
    """The scalar reference learner (one run) on synthetic transitions."""

    def __init__(self, spec: dict[str, Any]) -> None:
        torch.manual_seed(0)
        self.obs_dim = spec["obs_dim"]
        self.learner = ReferenceLearner(
            self.obs_dim, spec["action_low"], spec["action_high"], OnlineConfig()
        )
        self.rng = np.random.default_rng(0)
        self.learner.begin_episode(self.rng.normal(size=self.obs_dim).astype(np.float32))
        self.run(30)

    def run(self, steps: int) -> float:
        """Seconds per step over ``steps`` steps."""
        obs = self.rng.normal(size=(steps, self.obs_dim)).astype(np.float32)
        t0 = time.perf_counter()
        for t in range(steps):
            self.learner.step(0.1, obs[t], False, False)
        return (time.perf_counter() - t0) / steps


def paper_estimate(
    env_s: dict[str, float], learner_s: dict[str, float], workers: int, k: int
) -> dict[str, Any]:
    """Wall time of experiments/paper-full.toml from per-step costs (an upper bound: episodes
    that end before the time limit are shorter)."""
    spec = load_spec(HERE.parent / "experiments" / "paper-full.toml")
    per_task: dict[str, dict[str, float]] = {}
    for run in spec.runs:
        cfg = run.config
        steps = (cfg.episodes or 0) * MAX_EPISODE_STEPS if cfg.episodes else cfg.steps
        row = per_task.setdefault(run.env, {"runs": 0, "member_steps": 0.0})
        row["runs"] += 1
        row["member_steps"] += float(steps)
    total = 0.0
    for task, row in per_task.items():
        row["s_per_member_step"] = learner_s[task] + env_s[task]
        row["cpu_hours"] = row["member_steps"] * row["s_per_member_step"] / 3600
        total += row["cpu_hours"]
    return {
        "formula": (
            "hours = sum over tasks of runs x episodes x 1000 steps x (learner s per "
            f"member-step at K = {k} + env s per step) / 3600 / workers ({workers})"
        ),
        "per_task": per_task,
        "cpu_hours": total,
        "wall_hours": total / workers,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=150, help="timed steps per measurement")
    parser.add_argument("--env-steps", type=int, default=3000, help="timed raw env steps")
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds")
    parser.add_argument("--ks", type=int, nargs="+", default=[1, 4, 15, 30, 60])
    parser.add_argument(
        "--sizes",
        nargs="+",
        default=["pendulum", "halfcheetah"],
        help="tasks whose sizes get the K sweep (the others: the estimate's K only)",
    )
    parser.add_argument("--k", type=int, default=15, help="K of the paper-grid estimate")
    parser.add_argument("--workers", type=int, default=2, help="workers of the estimate")
    parser.add_argument("--out", default="benchmarks/results/throughput.json")
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch._dynamo.config.cache_size_limit = 256  # every shape keeps its compiled update

    specs = {t: spaces(t) for t in TASKS}
    print("building learners (compiling the update for every shape) ...", flush=True)
    benches: dict[tuple[str, str], Any] = {}
    for task in TASKS:
        ks = sorted({*args.ks, args.k}) if task in args.sizes else [args.k]
        if task in args.sizes:
            benches[(task, "reference")] = ReferenceBench(specs[task])
        for k in ks:
            benches[(task, f"K={k}")] = PopulationBench(specs[task], k)
    env_rounds: dict[str, list[float]] = {t: [] for t in TASKS}
    cost_rounds: dict[tuple[str, str], list[float]] = {key: [] for key in benches}
    for r in range(args.rounds):
        for task in TASKS:
            env_rounds[task].append(env_rate(task, args.env_steps, seed=r))
        for key, bench in benches.items():
            cost_rounds[key].append(bench.run(args.steps))
        print(f"round {r + 1}/{args.rounds} done", flush=True)

    env_s = {t: 1.0 / statistics.median(v) for t, v in env_rounds.items()}
    rows = []
    for (task, variant), costs in cost_rounds.items():
        cost = statistics.median(costs)
        rows.append(
            {
                "task": task,
                "variant": variant,
                "learner_us_per_member_step": cost * 1e6,
                "member_steps_per_s": 1.0 / cost,
                "learner_over_env_step": cost / env_s[task],
                "rounds_us": [c * 1e6 for c in costs],
            }
        )
    print()
    print(f"{'task':12s} {'raw env steps/s':>16s} {'env us/step':>12s}")
    for task in TASKS:
        print(f"{task:12s} {1 / env_s[task]:16.0f} {env_s[task] * 1e6:12.0f}")
    print()
    header = (
        f"{'task':12s} {'learner':10s} {'us/member-step':>15s} {'member-steps/s':>15s} "
        f"{'learner/env':>12s} {'vs K=1':>7s}"
    )
    print(header)
    print("-" * len(header))
    for row in rows:
        k1 = next((x for x in rows if x["task"] == row["task"] and x["variant"] == "K=1"), None)
        speedup = float("nan")
        if k1 is not None:
            speedup = k1["learner_us_per_member_step"] / row["learner_us_per_member_step"]
        print(
            f"{row['task']:12s} {row['variant']:10s} {row['learner_us_per_member_step']:15.0f} "
            f"{row['member_steps_per_s']:15.0f} {row['learner_over_env_step']:12.2f} "
            f"{speedup:7.2f}"
        )
        row["speedup_vs_k1"] = speedup
    learner_s = {t: statistics.median(cost_rounds[(t, f"K={args.k}")]) for t in TASKS}
    est = paper_estimate(env_s, learner_s, args.workers, args.k)
    print()
    print("estimated wall time of experiments/paper-full.toml on this machine:")
    print("  " + est["formula"])
    for task, row in est["per_task"].items():
        steps = row["member_steps"] / row["runs"]
        print(
            f"  {task:12s} {row['runs']:3d} runs x {steps:9.0f} steps x "
            f"{row['s_per_member_step'] * 1e3:.3f} ms = {row['cpu_hours']:6.2f} CPU hours"
        )
    print(f"  total {est['cpu_hours']:.1f} CPU hours -> {est['wall_hours']:.1f} hours wall")
    path = write_json(
        args.out,
        {
            "steps": args.steps,
            "rounds": args.rounds,
            "env_steps_per_s": {t: 1 / s for t, s in env_s.items()},
            "env_rounds_steps_per_s": env_rounds,
            "rows": rows,
            "paper_grid_estimate": est,
        },
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
