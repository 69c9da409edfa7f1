"""What trained pendulum policies do: balance, or keep swinging.

For each run folder of InvertedPendulum or Swingup (the two tasks whose observation is
``[x, x_dot, cos(theta), sin(theta), theta_dot]``), it replays the trained policy
deterministically for a few test episodes and prints, over the second half of each
episode (after a swing-up has had time):

* ``upright``: the fraction of steps with cos(theta) > 0.9 (the pole within about 26
  degrees of vertical);
* ``mean |a|`` and ``saturated``: the mean action magnitude and the fraction of steps with
  ``|a| > 0.95`` (actions are in [-1, 1]);
* ``turns``: net full turns of the pole from the first step to the last (a spinning pole
  scores about 0 on Swingup's reward cos(theta));
* the return of the episode.

Values are means over the episodes; the table groups the runs by their parent folders
(variant/task/method) and gives the mean over seeds. Example, the ablation's Swingup runs::

    python benchmarks/pendulum_behaviour.py benchmarks/results/ablation/{baseline,all}/swingup

The test environments are seeded with ``--seed`` plus the episode's index. Every run's
task is checked (from its ``config.json``) before the first episode. Replaying needs each
run's checkpoint, which is not committed, so a later machine can measure only the runs it
trained: ``--merge`` keeps the groups already in the JSON that this call does not measure
(measured with the same ``--episodes`` and ``--seed``), each with the command that
measured it.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import payload_command, write_json

import pporpe
from pporpe.envs import make_env
from pporpe.runs.folder import read_config

TASKS = ("pendulum", "swingup")


def find_runs(folders: list[Path]) -> list[Path]:
    """The finished run folders (with ``done.json``) in each folder, each checked to be
    one of :data:`TASKS`.

    Raises:
        ValueError: a folder holds no finished run, or a run is of another task.
    """
    runs = []
    for folder in folders:
        found = sorted(p.parent for p in folder.glob("**/done.json"))
        if not found:
            raise ValueError(f"{folder}: no finished run folder (with done.json) in it")
        for run in found:
            task = read_config(run)[1].env
            if task not in TASKS:
                raise ValueError(f"{run}: env must be one of {TASKS}; got {task!r}")
        runs.extend(found)
    return runs


def episode_stats(angles: np.ndarray, actions: np.ndarray, ret: float) -> dict[str, float]:
    """One episode's statistics from the pole angle atan2(sin, cos) at each step (in
    (-pi, pi]) and the largest action component's magnitude at each step."""
    theta = np.unwrap(np.asarray(angles, dtype=np.float64))
    a = np.asarray(actions, dtype=np.float64)
    half = len(theta) // 2
    return {
        "upright": float(np.mean(np.cos(theta[half:]) > 0.9)),
        "mean_abs_action": float(a[half:].mean()),
        "saturated": float(np.mean(a[half:] > 0.95)),
        "turns": float(abs(theta[-1] - theta[0]) / (2 * np.pi)),
        "return": float(ret),
        "length": float(len(theta)),
    }


def behaviour(run: Path, episodes: int, seed: int) -> dict[str, Any]:
    """The behaviour statistics of one run's deterministic policy, averaged over episodes."""
    policy = pporpe.load_policy(run)
    per_episode = []
    env = make_env(policy.config.env)
    for i in range(episodes):
        obs, _ = env.reset(seed=seed + i)
        angles, actions, ret = [], [], 0.0
        while True:
            action = policy.act(obs)
            obs, reward, terminated, truncated, _ = env.step(action)
            ret += float(reward)
            angles.append(np.arctan2(obs[3], obs[2]))
            actions.append(float(np.abs(action).max()))
            if terminated or truncated:
                break
        per_episode.append(episode_stats(np.asarray(angles), np.asarray(actions), ret))
    env.close()
    keys = per_episode[0].keys()
    return {"run": str(run), **{k: float(np.mean([e[k] for e in per_episode])) for k in keys}}


SEED = 10_000
"""Default ``--seed``: test episode i of every run is seeded with SEED + i."""


def merged(
    previous: dict[str, Any], groups: list[dict[str, Any]], rows: list[dict[str, Any]]
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """``previous``'s groups and runs that ``groups`` does not measure, then ``groups``
    and ``rows``; a previous group without its own command gets the file's."""
    fresh = {g["group"] for g in groups}
    old_groups = [
        {"command": previous.get("command", ""), **g}
        for g in previous.get("groups", [])
        if g["group"] not in fresh
    ]
    old_runs = [r for r in previous.get("runs", []) if str(Path(r["run"]).parent) not in fresh]
    return [*old_groups, *groups], [*old_runs, *rows]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folders", nargs="+", help="run folders, or folders holding them")
    parser.add_argument("--episodes", type=int, default=3, help="test episodes per run")
    parser.add_argument("--seed", type=int, default=SEED)
    parser.add_argument("--json", default="benchmarks/results/pendulum_behaviour.json")
    parser.add_argument(
        "--merge",
        action="store_true",
        help="keep the groups already in --json that this call does not measure",
    )
    args = parser.parse_args()
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1; got {args.episodes}")
    previous: dict[str, Any] = {}
    if args.merge and Path(args.json).exists():
        previous = json.loads(Path(args.json).read_text())
        measured = (previous.get("episodes"), previous.get("seed", SEED))  # seed: a 0.3 file
        if measured != (args.episodes, args.seed):
            parser.error(
                f"--merge: {args.json} was measured with --episodes {measured[0]} "
                f"--seed {measured[1]}; "
                f"got --episodes {args.episodes} --seed {args.seed}"
            )
    try:
        runs = find_runs([Path(f) for f in args.folders])
    except ValueError as err:
        parser.error(str(err))
    rows = [behaviour(run, args.episodes, args.seed) for run in runs]
    groups: dict[str, list[dict[str, Any]]] = {}
    for row in rows:
        groups.setdefault(str(Path(row["run"]).parent), []).append(row)
    cols = ("upright", "mean_abs_action", "saturated", "turns", "return")
    width = max([4, *(len(g) for g in groups)])
    header = f"{'runs':{width}s} {'n':>3s} " + " ".join(f"{c:>15s}" for c in cols)
    print(header)
    print("-" * len(header))
    summary = []
    command = payload_command()
    for group, members in groups.items():
        means = {c: float(np.mean([m[c] for m in members])) for c in cols}
        summary.append({"group": group, "command": command, "runs": len(members), **means})
        print(f"{group:{width}s} {len(members):3d} " + " ".join(f"{means[c]:15.2f}" for c in cols))
    if previous:
        summary, rows = merged(previous, summary, rows)
    payload = {"episodes": args.episodes, "seed": args.seed, "groups": summary, "runs": rows}
    path = write_json(args.json, payload)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
