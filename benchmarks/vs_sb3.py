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
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import write_json

from pporpe.batch import BatchConfig, BatchLearner, UpdateStats, train_batch, zoo_config
from pporpe.envs import make_env
from pporpe.evaluation import EVAL_SEED_OFFSET, evaluate_policy

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


def _history_time_to(history: list[dict[str, float]], threshold: float) -> float | None:
    for h in history:
        if h["median"] >= threshold:
            return h["train_time"]
    return None


def run_ours(
    cfg: BatchConfig, eval_every: int, eval_episodes: int, final_episodes: int
) -> dict[str, Any]:
    """Train with ``train_batch`` (run folder in a temporary directory), evaluating on the way."""
    history: list[dict[str, float]] = []
    eval_seed = cfg.seed + EVAL_SEED_OFFSET
    final: dict[str, Any] = {}

    def on_update(learner: BatchLearner, stats: UpdateStats, train_time: float) -> None:
        if (eval_every and learner.updates % eval_every == 0) or learner.updates == cfg.n_updates:
            ev = evaluate_policy(learner.act_deterministic, cfg.env, eval_episodes, eval_seed)
            history.append(
                {"steps": learner.total_steps, "train_time": train_time, "median": ev.median}
            )
        if learner.updates == cfg.n_updates:
            ev = evaluate_policy(learner.act_deterministic, cfg.env, final_episodes, eval_seed)
            final["final_median"] = ev.median
            final["final_returns"] = ev.returns

    with tempfile.TemporaryDirectory() as tmp:
        result = train_batch(replace(cfg, eval_episodes=0), Path(tmp) / "run", False, on_update)
    return {
        "steps": result.total_steps,
        "train_time": result.train_time,
        "steps_per_s": result.total_steps / result.train_time,
        "history": history,
        **final,
    }


def run_sb3(
    cfg: BatchConfig, eval_every: int, eval_episodes: int, final_episodes: int
) -> dict[str, Any]:
    """Train Stable-Baselines3's PPO with the same settings, evaluating on the same schedule."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    venv = VecNormalize(
        DummyVecEnv([(lambda: make_env(cfg.env)) for _ in range(cfg.n_envs)]),
        norm_obs=cfg.normalize_obs,
        norm_reward=cfg.normalize_reward,
        clip_obs=cfg.clip_obs,
        clip_reward=cfg.clip_reward,
        gamma=cfg.gamma,
        epsilon=1e-8,
    )
    activation = {"relu": torch.nn.ReLU, "tanh": torch.nn.Tanh, "swish": torch.nn.SiLU}
    model = PPO(
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
    history: list[dict[str, float]] = []
    eval_seed = cfg.seed + EVAL_SEED_OFFSET
    out: dict[str, Any] = {}

    def act(obs: np.ndarray) -> np.ndarray:
        action, _ = model.predict(venv.normalize_obs(obs), deterministic=True)
        return np.asarray(action)

    class Evaluate(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.excluded = 0.0
            self.updates = 0

        def _on_step(self) -> bool:
            return True

        def _evaluate(self, final: bool) -> None:
            t = time.perf_counter()
            if (eval_every and self.updates % eval_every == 0) or final:
                ev = evaluate_policy(act, cfg.env, eval_episodes, eval_seed)
                history.append(
                    {
                        "steps": int(self.num_timesteps),
                        "train_time": t - t0 - self.excluded,
                        "median": ev.median,
                    }
                )
            if final:
                ev = evaluate_policy(act, cfg.env, final_episodes, eval_seed)
                out["final_median"] = ev.median
                out["final_returns"] = ev.returns
            self.excluded += time.perf_counter() - t

        def _on_rollout_start(self) -> None:  # after each update but the last
            if self.num_timesteps > 0:
                self.updates += 1
                self._evaluate(final=False)

        def _on_training_end(self) -> None:
            self.updates += 1
            self._evaluate(final=True)

    callback = Evaluate()
    t0 = time.perf_counter()
    model.learn(total_timesteps=cfg.n_updates * cfg.rollout_size, callback=callback)
    train_time = time.perf_counter() - t0 - callback.excluded
    venv.close()
    steps = int(model.num_timesteps)
    return {
        "steps": steps,
        "train_time": train_time,
        "steps_per_s": steps / train_time,
        "history": history,
        **out,
    }


def _median(xs: list[float]) -> float:
    return float(statistics.median(xs)) if xs else float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", nargs="+", default=["pendulum", "halfcheetah"])
    parser.add_argument("--seeds", type=int, default=3, help="seeds per trainer (>= 3)")
    parser.add_argument("--budget", choices=sorted(BUDGETS), default="default")
    parser.add_argument("--steps", type=int, default=None, help="override total steps per run")
    parser.add_argument("--methods", nargs="+", default=list(OURS), choices=list(OURS))
    parser.add_argument("--no-sb3", action="store_true", help="skip Stable-Baselines3")
    parser.add_argument("--threshold", type=float, default=950.0, help="test return for (c)")
    parser.add_argument("--out", default="benchmarks/results/vs_sb3.json")
    args = parser.parse_args()
    torch.set_num_threads(1)

    trainers = ([] if args.no_sb3 else ["sb3"]) + list(args.methods)
    rows: list[dict[str, Any]] = []
    runs: dict[str, dict[str, list[dict[str, Any]]]] = {}
    t_all = time.perf_counter()
    for env in args.envs:
        budget = dict(BUDGETS[args.budget].get(env, BUDGETS[args.budget]["halfcheetah"]))
        if args.steps is not None:
            budget["steps"] = args.steps
        base = zoo_config(env, total_steps=budget["steps"])
        runs[env] = {k: [] for k in trainers}
        print(
            f"== {env}: {base.n_updates} updates x {base.rollout_size} steps "
            f"= {base.n_updates * base.rollout_size} steps per run, {args.seeds} seeds, "
            f"eval every {budget['eval_every']} updates ({budget['eval_episodes']} episodes), "
            f"final {budget['final']} episodes",
            flush=True,
        )
        for seed in range(args.seeds):
            order = trainers[seed % len(trainers) :] + trainers[: seed % len(trainers)]
            for name in order:
                cfg = replace(base, seed=seed, method=name if name != "sb3" else "ppo")
                fn = run_sb3 if name == "sb3" else run_ours
                res = fn(cfg, budget["eval_every"], budget["eval_episodes"], budget["final"])
                res["seed"] = seed
                res["time_to_threshold"] = _history_time_to(res["history"], args.threshold)
                runs[env][name].append(res)
                ttt = res["time_to_threshold"]
                print(
                    f"  seed {seed} {name:4s}: {res['steps_per_s']:7.0f} steps/s, "
                    f"final median {res['final_median']:8.1f}, "
                    f"time to {args.threshold:g}: "
                    f"{'-' if ttt is None else f'{ttt:.1f} s'}",
                    flush=True,
                )
        sb3 = runs[env].get("sb3", [])
        for name in trainers:
            rs = runs[env][name]
            sps = [r["steps_per_s"] for r in rs]
            final = [r["final_median"] for r in rs]
            ttt = [r["time_to_threshold"] for r in rs]
            reached = [t for t in ttt if t is not None]
            row: dict[str, Any] = {
                "env": env,
                "trainer": name,
                "config": {
                    k: v
                    for k, v in vars(replace(base, method="ppo" if name == "sb3" else name)).items()
                },
                "steps": rs[0]["steps"],
                "steps_per_s": _median(sps),
                "final_median": _median(final),
                "time_to_threshold": _median(reached) if len(reached) == len(rs) else None,
                "reached": f"{len(reached)}/{len(rs)}",
            }
            if sb3 and name != "sb3":
                ratios = [a["steps_per_s"] / b["steps_per_s"] for a, b in zip(rs, sb3, strict=True)]
                row["sps_ratio_vs_sb3"] = _median(ratios)
                row["final_minus_sb3"] = row["final_median"] - _median(
                    [r["final_median"] for r in sb3]
                )
                t_sb3 = [r["time_to_threshold"] for r in sb3]
                if all(t is not None for t in ttt + t_sb3):
                    row["time_ratio_vs_sb3"] = _median(
                        [a / b for a, b in zip(ttt, t_sb3, strict=True)]
                    )
            rows.append(row)
    wall = time.perf_counter() - t_all

    print()
    header = (
        f"{'env':12s} {'trainer':7s} {'steps':>8s} {'steps/s':>8s} {'x SB3':>6s} "
        f"{'final med':>10s} {'- SB3':>8s} {'t->' + format(args.threshold, 'g'):>8s} "
        f"{'x SB3':>6s} {'reached':>7s}"
    )
    print(header)
    print("-" * len(header))
    for r in rows:

        def f(x: Any, spec: str) -> str:
            return "-" if x is None else format(x, spec)

        print(
            f"{r['env']:12s} {r['trainer']:7s} {r['steps']:8d} {r['steps_per_s']:8.0f} "
            f"{f(r.get('sps_ratio_vs_sb3'), '6.2f'):>6s} {r['final_median']:10.1f} "
            f"{f(r.get('final_minus_sb3'), '+8.1f'):>8s} "
            f"{f(r['time_to_threshold'], '8.1f'):>8s} "
            f"{f(r.get('time_ratio_vs_sb3'), '6.2f'):>6s} {r['reached']:>7s}"
        )
    print(
        f"targets: steps/s x SB3 >= 1.2; final median >= SB3's; time to "
        f"{args.threshold:g} ours/SB3 (lower is better). Total wall time {wall:.0f} s."
    )
    try:
        from importlib.metadata import version

        sb3_version = version("stable-baselines3")
    except Exception:
        sb3_version = None
    path = write_json(
        args.out,
        {
            "budget": args.budget,
            "budgets": {env: BUDGETS[args.budget].get(env) for env in args.envs},
            "seeds": args.seeds,
            "threshold": args.threshold,
            "stable_baselines3": sb3_version,
            "wall_time_s": wall,
            "rows": rows,
            "runs": runs,
        },
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
