"""pporpe's step of Gymnasium's MuJoCo -v4 tasks against Gymnasium's own: the same numbers
over many steps, and the µs of each step side by side (the long version of
``tests/test_mujoco_step.py``).

For each task, first the identity: both environments from the same seeds take the same
actions (held 1-60 steps, outside the bounds too), with resets at the ends of episodes and
at random times, and every observation, reward, flag, info and reset observation is
compared bit for bit (:func:`pporpe.envs.side_by_side.side_by_side`). Then the time of a step,
in alternating rounds (lean, reference, physics, lean, ...) so that the machine's noise
hits them alike: each through :func:`pporpe.envs.make_env` and the batch learner's
``ReplayableEnv``, as a run steps it, on the same random actions (scaled by 0.3, so that
the walkers' episodes last), resets included; *physics* is the time inside the lean step's
two MuJoCo calls (``mj_step`` of ``frame_skip`` substeps and ``mj_rnePostConstraint``),
the floor of any step.

    python benchmarks/mujoco_step.py [--steps 30000] [--time-steps 5000] [--rounds 5]
        [--tasks Hopper-v4 ...] [--note "what shared the cores"] [--out FILE]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import write_json

from pporpe.envs import MUJOCO_LEAN_ENTRY_POINTS, ReplayableEnv, make_env
from pporpe.envs.side_by_side import side_by_side

STEPS = ("lean", "reference", "physics")
"""What is timed per task: pporpe's step, Gymnasium's, and the simulation calls alone."""


class _TimedSimulation:
    """Wraps a lean environment's ``_simulate`` and adds up the seconds spent in it."""

    def __init__(self, simulate: Any) -> None:
        self.simulate, self.seconds = simulate, 0.0

    def __call__(self, action: Any) -> None:
        t0 = time.perf_counter()
        self.simulate(action)
        self.seconds += time.perf_counter() - t0


def step_seconds(task: str, actions: np.ndarray, step: str) -> float:
    """Seconds per step of ``task`` over ``actions`` (resets included) by ``step`` (one of
    :data:`STEPS`; ``"physics"``: the time in the lean step's MuJoCo calls)."""
    env = ReplayableEnv(make_env(task, mujoco_step="reference" if step == "reference" else "lean"))
    timed = None
    if step == "physics":
        timed = _TimedSimulation(env.unwrapped._simulate)  # type: ignore[attr-defined]
        env.unwrapped._simulate = timed  # type: ignore[attr-defined]
    env.reset(seed=0)
    t0 = time.perf_counter()
    for action in actions:
        _, _, term, trunc, _ = env.step(action)
        if term or trunc:
            env.reset()
    seconds = time.perf_counter() - t0 if timed is None else timed.seconds
    env.close()
    return seconds / len(actions)


def time_task(task: str, steps: int, rounds: int) -> dict[str, Any]:
    """Median µs per step of each of :data:`STEPS` over alternating rounds, and the ratios."""
    env = make_env(task)
    dim = env.action_space.shape[0]  # type: ignore[index]
    env.close()
    actions = (0.3 * np.random.default_rng(0).uniform(-1, 1, (steps, dim))).astype(np.float32)
    seen: dict[str, list[float]] = {s: [] for s in STEPS}
    for _ in range(rounds):
        for s in STEPS:
            seen[s].append(step_seconds(task, actions, s) * 1e6)
    us = {s: statistics.median(v) for s, v in seen.items()}
    return {
        **{f"{s}_us": v for s, v in us.items()},
        **{f"rounds_{s}_us": seen[s] for s in STEPS},
        "lean_over_reference": us["lean"] / us["reference"],
        "python_us_reference": us["reference"] - us["physics"],
        "python_us_lean": us["lean"] - us["physics"],
    }


def _lean(task: str) -> Any:
    return make_env(task, mujoco_step="lean")


def _reference(task: str) -> Any:
    return make_env(task, mujoco_step="reference")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=30000, help="identity steps per task")
    parser.add_argument("--time-steps", type=int, default=5000, help="timed steps per round")
    parser.add_argument("--rounds", type=int, default=5, help="alternating rounds (>= 1)")
    tasks = list(MUJOCO_LEAN_ENTRY_POINTS)
    parser.add_argument("--tasks", nargs="+", default=tasks, choices=tasks)
    parser.add_argument("--note", default="", help="what shared the cores")
    parser.add_argument("--out", default="benchmarks/results/mujoco_step.json")
    args = parser.parse_args()
    for name in ("steps", "time_steps", "rounds"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1, not {getattr(args, name)}")
    rows = {}
    print(f"{'task':15s} {'lean us':>8s} {'reference us':>13s} {'physics us':>11s} "
          f"{'lean/ref':>9s}  identity")  # fmt: skip
    for task in args.tasks:
        same = side_by_side(task, args.steps, seed=0, make=_lean, reference=_reference)
        row = {**dataclasses.asdict(same), "identical": same.identical,
               **time_task(task, args.time_steps, args.rounds)}  # fmt: skip
        rows[task] = row
        verdict = "identical" if same.identical else f"DIFFERS: {same.first_difference}"
        print(f"{task:15s} {row['lean_us']:8.1f} {row['reference_us']:13.1f} "
              f"{row['physics_us']:11.1f} {row['lean_over_reference']:9.2f}  {same.steps} steps, "
              f"{same.resets} resets: {verdict}", flush=True)  # fmt: skip
    held = all(r["identical"] for r in rows.values())
    payload = {"held": held, "note": args.note, "steps": args.steps,
               "time_steps": args.time_steps, "rounds": args.rounds, "tasks": rows}  # fmt: skip
    print(f"wrote {write_json(args.out, payload)}")
    if not held:
        sys.exit(1)


if __name__ == "__main__":
    main()
