"""pporpe's batched step of the four Bullet tasks against pybullet_envs_gymnasium's own
step, side by side over many steps (the long version of ``tests/test_bullet_step.py``).

For each task, both environments from the same seeds take the same actions (held 1-60
steps, outside the bounds too), with resets at the ends of episodes and at random times;
every observation, reward, ``terminated``, ``truncated`` and reset observation is compared
bit for bit (:func:`pporpe.envs.side_by_side.side_by_side`). The JSON says, per task, whether
it held, and how many resets, natural terminations and time-limit truncations it covered.

    python benchmarks/bullet_identity.py [--steps 30000] [--seed 0] [--out FILE]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import write_json

from pporpe.envs import ALIASES
from pporpe.envs.side_by_side import side_by_side


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=30000, help="steps per task (>= 1)")
    parser.add_argument("--seed", type=int, default=0, help="seed of resets and actions")
    parser.add_argument("--tasks", nargs="+", default=list(ALIASES), choices=list(ALIASES))
    parser.add_argument("--out", default="benchmarks/results/bullet_identity.json")
    args = parser.parse_args()
    if args.steps < 1:
        parser.error(f"--steps must be >= 1, not {args.steps}")
    rows = []
    for task in args.tasks:
        t0 = time.perf_counter()
        seen = side_by_side(task, args.steps, seed=args.seed)
        row = {**dataclasses.asdict(seen), "identical": seen.identical,
               "seconds": time.perf_counter() - t0}  # fmt: skip
        rows.append(row)
        verdict = "identical" if seen.identical else f"DIFFERS: {seen.first_difference}"
        print(f"{task:12s} {seen.steps} steps, {seen.resets} resets, {seen.terminations} "
              f"terminations, {seen.truncations} truncations: {verdict}", flush=True)  # fmt: skip
    held = all(r["identical"] for r in rows)
    print(f"wrote {write_json(args.out, {'held': held, 'tasks': rows})}")
    if not held:
        sys.exit(1)


if __name__ == "__main__":
    main()
