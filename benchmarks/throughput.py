"""Throughput of the online learner against the raw environment, side by side.

For each task it measures, in one process with torch on one thread:

* raw environment steps/s with random actions;
* full-learner training steps/s (environment step + one learner update per step).

Rounds alternate the two so that machine noise hits both alike; the table reports
medians over rounds, the ratio training/raw, and the learner's own cost per step
(1/train - 1/raw) next to the environment's (1/raw).

    python benchmarks/throughput.py [--steps 3000] [--rounds 3] [--compile] [--breakdown]
                                    [--out FILE]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import write_json

from pporpe.envs import env_spec_summary, make_env
from pporpe.online import OnlineLearner
from pporpe.online.config import OnlineConfig

TARGETS = {"pendulum": 2000.0, "halfcheetah": 1400.0}


def raw_steps_per_s(env_name: str, steps: int, seed: int) -> float:
    env = make_env(env_name, seed=seed)
    env.reset(seed=seed)
    t0 = time.perf_counter()
    for _ in range(steps):
        _, _, term, trunc, _ = env.step(env.action_space.sample())
        if term or trunc:
            env.reset()
    dt = time.perf_counter() - t0
    env.close()
    return steps / dt


def train_steps_per_s(
    env_name: str, steps: int, seed: int, cfg: OnlineConfig, warmup: int
) -> float:
    env = make_env(env_name, seed=seed)
    spec = env_spec_summary(env)
    torch.manual_seed(seed)
    learner = OnlineLearner(spec["obs_dim"], spec["action_low"], spec["action_high"], cfg)
    obs, _ = env.reset(seed=seed)
    action = learner.begin_episode(obs)
    t0 = 0.0
    for i in range(warmup + steps):
        if i == warmup:
            t0 = time.perf_counter()
        obs, reward, term, trunc, _ = env.step(action)
        _, action = learner.step(float(reward), obs, term, trunc)
        if term or trunc:
            obs, _ = env.reset()
            action = learner.begin_episode(obs)
    dt = time.perf_counter() - t0
    env.close()
    return steps / dt


def breakdown(repeats: int = 500) -> dict[str, float]:
    """Microseconds per call of each part of one online step (InvertedPendulum sizes)."""
    torch.manual_seed(0)
    learner = OnlineLearner(5, -np.ones(1), np.ones(1), OnlineConfig())
    obs = np.random.default_rng(0).normal(size=(1000, 5)).astype(np.float32)
    learner.begin_episode(obs[0])
    for i in range(100):
        learner.step(0.1, obs[i], False, False)
    assert learner._obs is not None and learner._u is not None
    x = torch.cat([learner._obs, torch.as_tensor(obs[5]).reshape(1, 5)])
    scalars = torch.tensor([0.1, 0.99])

    def loss() -> tuple[torch.Tensor, ...]:
        return learner._loss_fn(
            learner._pol_views,
            learner._val_views,
            learner._tgt_views,
            x,
            learner._u,
            learner._logp_b,
            learner._value_b,
            scalars[0],
            scalars[1],
        )

    def forward_backward() -> None:
        out = loss()
        learner._grad.zero_()
        out[0].backward()

    raw = torch.randn(1, learner.head.raw_dim)
    u = learner.head.sample(raw)
    div = torch.tensor(0.01)
    parts = {
        "forward + loss": loss,
        "forward + loss + backward": forward_backward,
        "sample (head.sample)": lambda: learner.head.sample(raw),
        "sample (torch.distributions)": lambda: learner.head.distribution(raw).sample(),
        "head log_prob": lambda: learner.head.log_prob(raw, u),
        "traces.step_": lambda: learner.traces.step_(learner._grad, div),
        "optimizer.step": learner.optimizer.step,
        "tsoft.update_": lambda: learner.tsoft.update_(
            learner.target, learner.theta[learner.n_policy :]
        ),
        "full learner.step": lambda: learner.step(0.1, obs[7], False, False),
    }
    out = {}
    for name, fn in parts.items():
        for _ in range(20):
            fn()
        t0 = time.perf_counter()
        for _ in range(repeats):
            fn()
        out[name] = (time.perf_counter() - t0) / repeats * 1e6
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", nargs="+", default=["pendulum", "halfcheetah"])
    parser.add_argument("--steps", type=int, default=3000, help="timed steps per measurement")
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds")
    parser.add_argument("--compile", action="store_true", help="also measure compile=True")
    parser.add_argument(
        "--breakdown",
        action="store_true",
        help="also time each part of one online step (microseconds per call)",
    )
    parser.add_argument("--out", default="benchmarks/results/throughput.json")
    args = parser.parse_args()
    torch.set_num_threads(1)
    parts = breakdown() if args.breakdown else None
    if parts is not None:
        print(f"{'part of one online step':32s} {'us/call':>9s}")
        for name, us in parts.items():
            print(f"{name:32s} {us:9.1f}")
        print()

    variants = {"eager": OnlineConfig()}
    if args.compile:
        variants["compiled"] = OnlineConfig(compile=True)
    rows = []
    for env_name in args.envs:
        raw: list[float] = []
        train: dict[str, list[float]] = {k: [] for k in variants}
        for r in range(args.rounds):
            raw.append(raw_steps_per_s(env_name, args.steps, seed=r))
            for name, cfg in variants.items():
                warmup = 200 if not cfg.compile else 400
                train[name].append(train_steps_per_s(env_name, args.steps, r, cfg, warmup))
        raw_med = statistics.median(raw)
        for name in variants:
            tr = statistics.median(train[name])
            rows.append(
                {
                    "env": env_name,
                    "variant": name,
                    "raw_steps_per_s": raw_med,
                    "train_steps_per_s": tr,
                    "ratio_train_over_raw": tr / raw_med,
                    "env_ms_per_step": 1e3 / raw_med,
                    "learner_ms_per_step": 1e3 / tr - 1e3 / raw_med,
                    "target_train_steps_per_s": TARGETS.get(env_name),
                    "rounds_raw": raw,
                    "rounds_train": train[name],
                }
            )

    header = (
        f"{'env':12s} {'variant':9s} {'raw/s':>9s} {'train/s':>9s} {'ratio':>7s} "
        f"{'env ms':>8s} {'learner ms':>11s} {'target/s':>9s}"
    )
    print(header)
    print("-" * len(header))
    for row in rows:
        tgt = row["target_train_steps_per_s"]
        print(
            f"{row['env']:12s} {row['variant']:9s} {row['raw_steps_per_s']:9.0f} "
            f"{row['train_steps_per_s']:9.0f} {row['ratio_train_over_raw']:7.3f} "
            f"{row['env_ms_per_step']:8.3f} {row['learner_ms_per_step']:11.3f} "
            f"{tgt if tgt is not None else float('nan'):9.0f}"
        )
    path = write_json(
        args.out, {"steps": args.steps, "rounds": args.rounds, "rows": rows, "breakdown_us": parts}
    )
    print(f"wrote {path}")
    np.set_printoptions()


if __name__ == "__main__":
    main()
