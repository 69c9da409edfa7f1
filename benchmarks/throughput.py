"""Throughput of the online learner, side by side in one process (torch on one thread),
in alternating rounds so that machine noise hits every variant alike:

* raw environment steps/s of the four tasks (random actions), each stepped by pporpe's
  batched step (the default of ``make_env``) and by pybullet_envs_gymnasium's own
  (``bullet_step="reference"``), and the physics alone (``stepSimulation`` with the same
  client: the floor of any step);
* the learner's µs per member-step on synthetic transitions of each task's size, for
  populations of K = 1, 4, 8, 15, 30, 60 members of mixed methods with the default
  config, by the fused engine (the default) and, at K = 1 and 30, by the torch engine
  (the reference, and the step before the fused kernel); each also as a ratio to the
  task's environment step;
* the start-up of ``pporpe train``: the wall time of a one-episode InvertedPendulum run
  minus its training time, with an empty numba cache (cold: the kernels compile) and
  with the cache that run left (warm);
* the best K (the cheapest member-step at HalfCheetah size, the grid's dominant cost)
  and, from its rates, the estimated wall time of experiments/paper-full.toml here, with
  either step.

    python benchmarks/throughput.py [--ks 1 4 8 15 30 60] [--torch-ks 1 30] [--rounds 3]
                                    [--member-steps 600] [--workers 2] [--out FILE]
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import pybullet
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import write_json

from pporpe.envs import env_spec_summary, make_env
from pporpe.experiments.grids.spec import load_spec
from pporpe.online.config import OnlineConfig
from pporpe.online.population import PopulationLearner

HERE = Path(__file__).resolve().parent
TASKS = ("pendulum", "swingup", "halfcheetah", "ant")
TORCH_SIZES = ("pendulum", "halfcheetah")
"""The tasks whose sizes the torch engine is measured at (it takes minutes to compile)."""
MAX_EPISODE_STEPS = 1000
"""The time limit of the four Bullet tasks under Gymnasium: an episode's length bound."""


def spaces(task: str) -> dict[str, Any]:
    env = make_env(task)
    try:
        return env_spec_summary(env)
    finally:
        env.close()


STEPS = ("batched", "reference", "physics")
"""What is timed per task: pporpe's step, pybullet_envs_gymnasium's, and the physics alone."""


def env_rate(task: str, steps: int, seed: int, step: str = "batched") -> float:
    """Raw environment steps/s with random actions (drawn before the clock starts), by
    ``step``: ``"batched"`` or ``"reference"`` (``make_env``'s ``bullet_step``), or
    ``"physics"``, PyBullet's ``stepSimulation`` alone on the batched environment's client."""
    env = make_env(task, seed=seed, bullet_step="reference" if step == "reference" else None)
    env.reset(seed=seed)
    env.action_space.seed(seed)
    actions = [env.action_space.sample() for _ in range(steps)]
    if step == "physics":
        client = env.unwrapped.physicsClientId  # type: ignore[attr-defined]
        t0 = time.perf_counter()
        for _ in range(steps):
            pybullet.stepSimulation(physicsClientId=client)
        dt = time.perf_counter() - t0
        env.close()
        return steps / dt
    t0 = time.perf_counter()
    for action in actions:
        _, _, term, trunc, _ = env.step(action)
        if term or trunc:
            env.reset()
    dt = time.perf_counter() - t0
    env.close()
    return steps / dt


class PopulationBench:
    """K members of mixed methods (default config) stepping on synthetic transitions."""

    def __init__(self, spec: dict[str, Any], k: int, engine: str) -> None:
        methods = ("ppo", "rb", "rpe")
        cfgs = [OnlineConfig(method=methods[i % 3], engine=engine) for i in range(k)]  # type: ignore[arg-type]
        self.k, self.obs_dim = k, spec["obs_dim"]
        self.learner = PopulationLearner(
            self.obs_dim, spec["action_low"], spec["action_high"], cfgs, list(range(k))
        )
        self.rng = np.random.default_rng(0)
        self.learner.begin_episode(range(k), self.rng.normal(size=(k, self.obs_dim)))
        self.run(30 * k)  # compile and warm up

    def run(self, member_steps: int) -> float:
        """Seconds per member-step over about ``member_steps`` member-steps (>= 5 steps)."""
        k, rng, no = self.k, self.rng, np.zeros(self.k, dtype=bool)
        steps = max(5, member_steps // k)
        obs = rng.normal(size=(steps, k, self.obs_dim)).astype(np.float32)
        rewards = rng.normal(size=(steps, k))
        t0 = time.perf_counter()
        for t in range(steps):
            self.learner.step(rewards[t], obs[t], no, no)
        return (time.perf_counter() - t0) / (steps * k)


STARTUP_COMMAND = (
    "pporpe train --env pendulum --episodes 1 --eval-episodes 0 --quiet --force --out DIR"
)
"""The run whose start-up is timed (the task whose episode is shortest at the start)."""


def startup_seconds(cache_dir: str, out_dir: str) -> dict[str, float]:
    """Wall time of :data:`STARTUP_COMMAND` in a fresh process with numba's cache in
    ``cache_dir``, its training time (from its closing line) and the difference: the
    time from process start to the first training step, plus the run folder's writes."""
    pporpe = Path(sys.executable).with_name("pporpe")
    argv = [str(pporpe), *STARTUP_COMMAND.split()[1:-1], out_dir]
    env = {**os.environ, "NUMBA_CACHE_DIR": cache_dir}
    t0 = time.perf_counter()
    out = subprocess.run(argv, env=env, capture_output=True, text=True, check=True).stdout
    wall = time.perf_counter() - t0
    found = re.search(r"steps in ([0-9.]+) s", out)
    if found is None:
        raise RuntimeError(f"no training time in the output of {argv}:\n{out}")
    train = float(found.group(1))
    return {"wall_s": wall, "train_s": train, "startup_s": wall - train}


def startup() -> dict[str, Any]:
    """:func:`startup_seconds` with an empty numba cache, then with the one it left."""
    with tempfile.TemporaryDirectory() as cache, tempfile.TemporaryDirectory() as out:
        cold = startup_seconds(cache, out)
        warm = startup_seconds(cache, out)
    return {"command": STARTUP_COMMAND, "cold": cold, "warm": warm}


def build(args: argparse.Namespace, specs: dict[str, Any]) -> dict[tuple[str, str, int], Any]:
    """Every (task, engine, K) learner of the sweep."""
    print("building the learners (the torch engine compiles every shape) ...", flush=True)
    benches: dict[tuple[str, str, int], Any] = {}
    for task in TASKS:
        for k in args.ks:
            benches[(task, "fused", k)] = PopulationBench(specs[task], k, "fused")
        for k in args.torch_ks if task in TORCH_SIZES else ():
            benches[(task, "torch", k)] = PopulationBench(specs[task], k, "torch")
    return benches


def measure(
    args: argparse.Namespace, benches: dict[tuple[str, str, int], Any]
) -> tuple[dict[str, list[float]], dict[tuple[str, str, int], list[float]]]:
    """Alternating rounds: every task's environment, then every learner, per round."""
    env_rounds: dict[str, list[float]] = {f"{t}/{s}": [] for t in TASKS for s in STEPS}
    cost_rounds: dict[tuple[str, str, int], list[float]] = {key: [] for key in benches}
    for r in range(args.rounds):
        for task in TASKS:
            for step in STEPS:
                env_rounds[f"{task}/{step}"].append(env_rate(task, args.env_steps, r, step))
        for key, bench in benches.items():
            cost_rounds[key].append(bench.run(args.member_steps))
        print(f"round {r + 1}/{args.rounds} done", flush=True)
    return env_rounds, cost_rounds


def result_rows(
    env_s: dict[str, float], cost_rounds: dict[tuple[str, str, int], list[float]]
) -> list[dict[str, Any]]:
    """One row per (task, engine, K): medians, ratios to the env step and to torch K = 1."""
    rows = []
    for (task, engine, k), costs in cost_rounds.items():
        cost = statistics.median(costs)
        base = cost_rounds.get((task, "torch", 1))
        rows.append(
            {
                "task": task,
                "engine": engine,
                "K": k,
                "learner_us_per_member_step": cost * 1e6,
                "member_steps_per_s": 1.0 / cost,
                "learner_over_env_step": cost / env_s[task],
                "speedup_vs_torch_k1": statistics.median(base) / cost if base else None,
                "rounds_us": [c * 1e6 for c in costs],
            }
        )
    return rows


def best_k(rows: list[dict[str, Any]], task: str = "halfcheetah") -> int:
    """The K whose fused member-step is cheapest at ``task``'s size."""
    fused = [r for r in rows if r["task"] == task and r["engine"] == "fused"]
    return int(min(fused, key=lambda r: r["learner_us_per_member_step"])["K"])


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
            f"member-step, fused engine at K = {k} + env s per step) / 3600 / workers "
            f"({workers})"
        ),
        "K": k,
        "per_task": per_task,
        "cpu_hours": total,
        "wall_hours": total / workers,
    }


def env_step_rows(env_rounds: dict[str, list[float]]) -> dict[str, dict[str, float]]:
    """Per task the median µs per step of each of :data:`STEPS` and the batched step's
    ratios to the reference step and to the physics."""
    rows = {}
    for task in TASKS:
        us = {s: 1e6 / statistics.median(env_rounds[f"{task}/{s}"]) for s in STEPS}
        rows[task] = {
            **{f"{s}_us": v for s, v in us.items()},
            "batched_over_reference": us["batched"] / us["reference"],
            "batched_over_physics": us["batched"] / us["physics"],
        }
    return rows


def print_report(env: dict[str, dict[str, float]], rows: list[dict[str, Any]],
                 est: dict[str, Any], est_ref: dict[str, Any],
                 start: dict[str, Any]) -> None:  # fmt: skip
    print(f"\n{'task':12s} {'batched us':>11s} {'reference us':>13s} {'physics us':>11s} "
          f"{'/reference':>11s} {'/physics':>9s}")  # fmt: skip
    for task, e in env.items():
        print(f"{task:12s} {e['batched_us']:11.0f} {e['reference_us']:13.0f} "
              f"{e['physics_us']:11.0f} {e['batched_over_reference']:11.2f} "
              f"{e['batched_over_physics']:9.2f}")  # fmt: skip
    head = (f"{'task':12s} {'engine':7s} {'K':>3s} {'us/member-step':>15s} {'/env':>6s} "
            f"{'vs torch K=1':>13s}")  # fmt: skip
    print("\n" + head + "\n" + "-" * len(head))
    for r in rows:
        vs = "-" if r["speedup_vs_torch_k1"] is None else f"{r['speedup_vs_torch_k1']:.1f}x"
        print(f"{r['task']:12s} {r['engine']:7s} {r['K']:3d} "
              f"{r['learner_us_per_member_step']:15.0f} {r['learner_over_env_step']:6.2f} "
              f"{vs:>13s}")  # fmt: skip
    print(f"\nstart-up of `{start['command']}`: cold {start['cold']['startup_s']:.1f} s, "
          f"warm {start['warm']['startup_s']:.1f} s")  # fmt: skip
    print(f"\nbest K {est['K']}; estimated wall time of experiments/paper-full.toml: "
          f"{est['wall_hours']:.1f} h ({est['cpu_hours']:.1f} CPU hours); with the "
          f"reference step {est_ref['wall_hours']:.1f} h")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ks", type=int, nargs="+", default=[1, 4, 8, 15, 30, 60])
    parser.add_argument("--torch-ks", type=int, nargs="+", default=[1, 30])
    parser.add_argument("--member-steps", type=int, default=600, help="per measurement")
    parser.add_argument("--env-steps", type=int, default=3000, help="timed raw env steps")
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds")
    parser.add_argument("--workers", type=int, default=2, help="workers of the estimate")
    parser.add_argument("--out", default="benchmarks/results/throughput.json")
    args = parser.parse_args()
    if min(args.ks + args.torch_ks) < 1 or args.rounds < 1 or args.member_steps < 1:
        parser.error("--ks, --torch-ks, --rounds and --member-steps must be >= 1")
    torch.set_num_threads(1)
    torch._dynamo.config.cache_size_limit = 256  # every shape keeps its compiled update
    start = startup()
    specs = {t: spaces(t) for t in TASKS}
    env_rounds, cost_rounds = measure(args, build(args, specs))
    env = env_step_rows(env_rounds)
    env_s = {t: e["batched_us"] / 1e6 for t, e in env.items()}
    rows = result_rows(env_s, cost_rounds)
    k = best_k(rows)
    learner_s = {t: statistics.median(cost_rounds[(t, "fused", k)]) for t in TASKS}
    est = paper_estimate(env_s, learner_s, args.workers, k)
    env_ref = {t: e["reference_us"] / 1e6 for t, e in env.items()}
    est_ref = paper_estimate(env_ref, learner_s, args.workers, k)
    print_report(env, rows, est, est_ref, start)
    payload = {"rounds": args.rounds, "member_steps": args.member_steps,
               "env_steps": args.env_steps, "env_step": env,
               "env_steps_per_s": {t: 1 / s for t, s in env_s.items()},
               "env_rounds_steps_per_s": env_rounds, "rows": rows, "best_k": k,
               "startup": start, "paper_grid_estimate": est,
               "paper_grid_estimate_reference_step": est_ref}  # fmt: skip
    print(f"wrote {write_json(args.out, payload)}")


if __name__ == "__main__":
    main()
