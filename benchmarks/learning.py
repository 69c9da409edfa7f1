"""Learning quality of the online learner: PPO, PPO-RB and PPO-RPE with the same seeds.

Every run trains for a fixed number of episodes and is scored by the median return of
its test episodes (the paper's score). The runs go through the same grid machinery as
``pporpe reproduce`` (local process pool, checkpoints, resume), so an interrupted
benchmark continues where it stopped when started again with the same ``--out``.

Targets (issue: the paper's online learner):

* PPO-RPE on InvertedPendulum reaches >= 950 within 200 episodes in at least 4 of 5 seeds;
* PPO-RPE on InvertedPendulumSwingup within 200 episodes: median over seeds >= 800.

    python benchmarks/learning.py [--tasks pendulum swingup] [--seeds 5] [--episodes 200]
                                  [--swingup-episodes N] [--workers 2] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import write_json

from pporpe.experiments.grids.reproduce import reproduce
from pporpe.experiments.grids.spec import GridSpec, parse_spec

THRESHOLD = {"pendulum": 950.0, "swingup": 800.0}


@dataclass(frozen=True)
class Task:
    """A task of the grid and its training episodes per run."""

    env: str
    episodes: int


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tasks", nargs="+", default=["pendulum", "swingup"])
    parser.add_argument("--methods", nargs="+", default=["ppo", "rb", "rpe"])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--episodes", type=int, default=200, help="training episodes per run")
    parser.add_argument(
        "--swingup-episodes",
        type=int,
        default=None,
        help="episodes for swingup if different (its episodes are 1000 steps)",
    )
    parser.add_argument("--eval-episodes", type=int, default=50)
    parser.add_argument("--workers", type=int, default=None)
    parser.add_argument("--out", default="benchmarks/results/learning_runs")
    parser.add_argument("--json", default="benchmarks/results/learning.json")
    return parser.parse_args()


def tasks_of(args: argparse.Namespace) -> list[Task]:
    """The chosen tasks, Swingup with ``--swingup-episodes`` where given."""
    swingup = args.swingup_episodes
    return [
        Task(env, swingup if env == "swingup" and swingup else args.episodes) for env in args.tasks
    ]


def spec_for(args: argparse.Namespace, tasks: list[Task]) -> GridSpec:
    """The grid of every method, task and seed, as ``pporpe reproduce`` runs it."""
    return parse_spec(
        {
            "name": "learning",
            "methods": args.methods,
            "seeds": args.seeds,
            "eval_episodes": args.eval_episodes,
            "tasks": [{"env": t.env, "episodes": t.episodes} for t in tasks],
        },
        "learning",
    )


def summary_row(out: Path, task: Task, method: str, seeds: int) -> dict[str, Any]:
    """One method's row on one task: the scores of its finished seeds, their median, mean
    and the seeds at the threshold."""
    scores, steps = {}, {}
    for seed in range(seeds):
        run = out / task.env / method / f"seed{seed}"
        ev = run / "evaluation.json"
        if ev.exists():
            scores[seed] = json.loads(ev.read_text())["median"]
            steps[seed] = json.loads((run / "done.json").read_text())["total_steps"]
    vals = list(scores.values())
    thr = THRESHOLD.get(task.env)
    return {
        "env": task.env,
        "method": method,
        "episodes": task.episodes,
        "scores": scores,
        "train_steps": steps,
        "median_over_seeds": statistics.median(vals) if vals else None,
        "mean_over_seeds": statistics.fmean(vals) if vals else None,
        "seeds_reaching_threshold": (sum(v >= thr for v in vals) if thr else None),
        "threshold": thr,
        "seeds": len(vals),
    }


def print_table(rows: list[dict[str, Any]], eval_episodes: int) -> None:
    print(
        f"\n{'task':9s} {'method':7s} {'eps':>5s} {'median':>8s} {'mean':>8s} "
        f"{'>=thr':>6s}  per-seed medians of {eval_episodes} test episodes"
    )
    for r in rows:
        med = f"{r['median_over_seeds']:.1f}" if r["median_over_seeds"] is not None else "n/a"
        mean = f"{r['mean_over_seeds']:.1f}" if r["mean_over_seeds"] is not None else "n/a"
        reach = f"{r['seeds_reaching_threshold']}/{r['seeds']}" if r["threshold"] else "-"
        per = ", ".join(f"{v:.0f}" for v in r["scores"].values())
        print(
            f"{r['env']:9s} {r['method']:7s} {r['episodes']:5d} {med:>8s} {mean:>8s} "
            f"{reach:>6s}  [{per}]"
        )
    print(
        "targets: PPO-RPE pendulum >= 950 in >= 4/5 seeds (200 episodes); "
        "PPO-RPE swingup median over seeds >= 800 (200 episodes)"
    )


def main() -> None:
    args = parse_args()
    tasks = tasks_of(args)
    t0 = time.perf_counter()
    outcome = reproduce(spec_for(args, tasks), args.out, workers=args.workers, progress=True)
    wall = time.perf_counter() - t0
    out = Path(args.out)
    rows = [summary_row(out, task, method, args.seeds) for task in tasks for method in args.methods]
    print_table(rows, args.eval_episodes)
    print(f"wall time {wall:.0f} s; failed runs: {list(outcome.failed) or 'none'}")
    path = write_json(
        args.json,
        {"rows": rows, "wall_time_s": wall, "failed": outcome.failed, "settings": vars(args)},
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
