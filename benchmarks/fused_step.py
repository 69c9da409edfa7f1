"""The fused engine against the torch engine of PopulationLearner, side by side in one
process (torch on one thread), in alternating rounds, plus the start-up of the fused one.

* µs of learner per member-step at each K for the pendulum (obs 5, act 1) and HalfCheetah
  (obs 26, act 6) sizes, default config, methods PPO / PPO-RB / PPO-RPE in turn, on
  synthetic transitions; the torch engine with its compiled update (today's path);
* the time from a fresh process's start to the first finished step of a fused K = 1
  learner, with an empty numba cache (cold: compiles) and with the cache it left (warm).

    python benchmarks/fused_step.py [--ks 1 4 8 15 30 60] [--rounds 3] [--out FILE]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import write_json

from pporpe.online.config import OnlineConfig
from pporpe.online.population import PopulationLearner

SIZES = {"pendulum": (5, 1), "halfcheetah": (26, 6)}
STARTUP = """
import time, numpy as np
t0 = time.perf_counter()
from pporpe.online import OnlineConfig, OnlineLearner
learner = OnlineLearner(26, -np.ones(6), np.ones(6), OnlineConfig(), seed=0, engine="fused")
learner.begin_episode(np.zeros(26))
learner.step(0.0, np.zeros(26), False, False)
print(time.perf_counter() - t0)
"""


class Bench:
    """K members of one engine stepping on synthetic transitions."""

    def __init__(self, obs: int, act: int, k: int, engine: str) -> None:
        cfgs = [OnlineConfig(method=("ppo", "rb", "rpe")[i % 3]) for i in range(k)]
        self.p = PopulationLearner(obs, -np.ones(act), np.ones(act), cfgs, list(range(k)),
                                   engine=engine)  # fmt: skip
        self.k, self.obs = k, obs
        self.rng = np.random.default_rng(0)
        self.p.begin_episode(range(k), self.rng.normal(size=(k, obs)))
        self.run(10)  # compile and warm up

    def run(self, steps: int) -> float:
        """µs per member-step over ``steps`` steps."""
        no = np.zeros(self.k, dtype=bool)
        obs = self.rng.normal(size=(steps, self.k, self.obs))
        rew = self.rng.normal(size=(steps, self.k))
        t0 = time.perf_counter()
        for t in range(steps):
            self.p.step(rew[t], obs[t], no, no)
        return (time.perf_counter() - t0) / (steps * self.k) * 1e6


def startup(cache_dir: str) -> float:
    """Seconds from a fresh interpreter to the first finished step (numba cache dir given)."""
    t0 = time.perf_counter()
    env = {**os.environ, "NUMBA_CACHE_DIR": cache_dir}
    out = subprocess.run([sys.executable, "-c", STARTUP], env=env, capture_output=True,
                         text=True, check=True)  # fmt: skip
    inner = float(out.stdout.strip().splitlines()[-1])
    return max(inner, time.perf_counter() - t0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ks", type=int, nargs="+", default=[1, 4, 8, 15, 30, 60])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--member-steps", type=int, default=300, help="per measurement")
    parser.add_argument("--out", default="benchmarks/results/fused_step.json")
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch._dynamo.config.cache_size_limit = 256
    with tempfile.TemporaryDirectory() as cache:
        cold, warm = startup(cache), startup(cache)
    print(f"start to first step, fused K = 1: cold cache {cold:.1f} s, warm {warm:.1f} s")
    benches: dict[tuple[str, int, str], Bench] = {}
    for size, (obs, act) in SIZES.items():
        for k in args.ks:
            for engine in ("torch", "fused"):
                benches[(size, k, engine)] = Bench(obs, act, k, engine)
    rounds: dict[tuple[str, int, str], list[float]] = {key: [] for key in benches}
    for r in range(args.rounds):
        for key, bench in benches.items():
            rounds[key].append(bench.run(max(5, args.member_steps // key[1])))
        print(f"round {r + 1}/{args.rounds} done", flush=True)
    rows: list[dict[str, Any]] = []
    print(f"{'size':12s} {'K':>3s} {'torch us':>9s} {'fused us':>9s} {'speed-up':>9s}")
    for size in SIZES:
        for k in args.ks:
            t = statistics.median(rounds[(size, k, "torch")])
            f = statistics.median(rounds[(size, k, "fused")])
            print(f"{size:12s} {k:3d} {t:9.0f} {f:9.0f} {t / f:9.1f}")
            rows.append({"size": size, "K": k, "torch_us": t, "fused_us": f, "speedup": t / f,
                         "torch_rounds_us": rounds[(size, k, "torch")],
                         "fused_rounds_us": rounds[(size, k, "fused")]})  # fmt: skip
    path = write_json(args.out, {"rounds": args.rounds, "rows": rows,
                                 "startup_s": {"cold": cold, "warm": warm}})  # fmt: skip
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
