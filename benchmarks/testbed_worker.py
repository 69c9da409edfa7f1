"""One seed of the author's test bed (GitHub kbys-t/test_et), run unmodified, resumable.

This file runs in the test bed's own environment (gym 0.25.2, numpy < 2, its PyTorch),
not in pporpe's: it imports nothing from pporpe. ``benchmarks/testbed.py reference``
starts it once per seed; run by hand::

    TESTBED_PYTHON benchmarks/testbed_worker.py --checkout DIR --env ID --seed 1 \\
        --config testbed --episodes 200 --tests 50 --work WORKDIR --out RESULT.json

It loads the checkout's ``test.py`` and calls its own ``train()`` and ``test()`` loops
with its ``modules.ac.AC`` agent (seeding and order of calls as its ``process()``: the
seed for training, ``2**31 - seed`` for the test episodes, the agent saved with its
``release()`` and reloaded with ``load()`` before testing). Nothing of the author's code
is copied here. Three adapters, none touching the author's files:

* ``torch._six`` (removed in torch 2.0) is provided with ``inf`` and ``nan``, the two
  names the author's distributions import from it;
* gym 0.25.2's ``TimeLimit`` never ends a Bullet episode (it tests the inner ``done``
  with ``is False``, and pybullet returns a ``numpy.bool_``), so the environment is
  re-wrapped in the earlier ``TimeLimit`` semantics (done after the registered
  ``max_episode_steps``);
* ``torch.load`` is called with ``weights_only=False`` for the worker's own checkpoint
  (the author's ``load()`` reads tensors only and is left as it is).

Every ``--checkpoint-every`` episodes the worker saves the agent's networks and optimiser
(its traces are zeroed by ``train()`` at every episode's start, so an episode boundary
holds none), the torch and numpy generators and the environment's generator into
``WORKDIR/checkpoint.pt`` (written to a temporary file, then renamed); a killed worker
resumes from there. At the end it writes ``--out`` (atomically): per training episode
the return and length, the 50 test returns, wall times and the versions.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import os
import sys
import time
import types
from pathlib import Path
from typing import Any

CONFIGS: dict[str, dict[str, Any]] = {
    # the last entry of test.py's METHODS; every other argument at AC's defaults
    "testbed": {"lambda1": 0.5, "lambda2": 0.9, "div_weight": 1.0},
    # the paper's Table I through AC's constructor (tar_tau / tar_dof are accepted and
    # unused: AC has no target network); its TD error carries the regularisers with
    # weight w and balance b as w b^2 (TD) and w b (1 - b) (entropy) and scales the reward
    # by (1 - gamma)(1 - w b): w = 0.04, b = 0.5 give the paper's 0.01 per term
    "paper": {
        "fc_params": {"h_dims": [100] * 5},
        "opt_params": {"lr": 3e-4, "amsgrad": 0.99999, "method": "tlaprop"},
        "lambda1": 0.5,
        "lambda2": 0.95,
        "div_weight": 10.0,
        "tar_tau": 0.3,
        "tar_dof": 1.0,
        "ppo_threshold": 0.1,
        "reg_weight": 0.04,
        "reg_balance": 0.5,
    },
}
"""The test bed's settings by name: what ``--config`` passes to ``AC(...)``."""


def provide_torch_six() -> None:
    """Make ``from torch._six import inf, nan`` work on torch >= 2.0."""
    import torch

    if "torch._six" in sys.modules or hasattr(torch, "_six"):
        return
    six = types.ModuleType("torch._six")
    six.inf = math.inf  # type: ignore[attr-defined]
    six.nan = math.nan  # type: ignore[attr-defined]
    sys.modules["torch._six"] = six


def load_testbed(checkout: Path) -> types.ModuleType:
    """The checkout's ``test.py`` as a module (not named ``test``: the standard library
    has a package of that name), with its plotting and video monitor switched off."""
    if not (checkout / "test.py").is_file() or not (checkout / "modules" / "ac.py").is_file():
        raise SystemExit(f"--checkout: {checkout} holds no test.py and modules/ac.py of test_et")
    sys.path.insert(0, str(checkout))
    provide_torch_six()
    spec = importlib.util.spec_from_file_location("test_et_driver", checkout / "test.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.IS_VIEW = False  # no gym Monitor (videos) in test()
    return module


class EpisodeLimit:
    """gym <= 0.23's ``TimeLimit``: ``done`` after ``max_steps`` steps."""

    def __init__(self, env: Any, max_steps: int) -> None:
        self._env = env
        self._max_steps = max_steps
        self._steps = 0

    def reset(self, **kwargs: Any) -> Any:
        self._steps = 0
        return self._env.reset(**kwargs)

    def step(self, action: Any) -> Any:
        obs, reward, done, info = self._env.step(action)
        self._steps += 1
        if self._steps >= self._max_steps:
            info["TimeLimit.truncated"] = not done
            done = True
        return obs, reward, done, info

    def __getattr__(self, name: str) -> Any:
        return getattr(self._env, name)


def make_env(env_id: str) -> Any:
    """The Bullet task with the registered episode limit applied as older gym did."""
    import gym
    import pybullet_envs  # noqa: F401  (registers the Bullet tasks)

    env = gym.make(env_id)
    inner = env
    while isinstance(inner, gym.Wrapper) and not isinstance(inner, gym.wrappers.TimeLimit):
        inner = inner.env
    if not isinstance(inner, gym.wrappers.TimeLimit):
        raise SystemExit(f"--env: {env_id} has no registered time limit")
    return EpisodeLimit(inner.env, int(env.spec.max_episode_steps))


def new_agent(tb: types.ModuleType, env: Any, config: str) -> Any:
    """``AC`` as test.py's ``process()`` builds it, with the named settings."""
    s_dim = env.observation_space.shape[0]
    a_dim = env.action_space.shape[0]
    return tb.RL(s_dim, a_dim, False, use_cuda=False, **CONFIGS[config])


def env_rng_state(env: Any) -> dict[str, Any]:
    """The state of the environment's generator (the robot draws its start from it)."""
    return dict(env.unwrapped.np_random.bit_generator.state)


def set_env_rng_state(env: Any, state: dict[str, Any]) -> None:
    env.unwrapped.np_random.bit_generator.state = state
    robot = getattr(env.unwrapped, "robot", None)
    if robot is not None and robot.np_random is not env.unwrapped.np_random:
        robot.np_random.bit_generator.state = state


def save_checkpoint(path: Path, agent: Any, env: Any, log: dict[str, Any]) -> None:
    import numpy as np
    import torch

    state = {
        "nets": agent.state_dict(),
        "optimizer": agent.optimizer.state_dict(),
        "torch_rng": torch.get_rng_state(),
        "numpy_rng": np.random.get_state(),  # noqa: NPY002 (the test bed seeds it)
        "env_rng": env_rng_state(env),
        "log": log,
    }
    tmp = path.with_suffix(".tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)


def load_checkpoint(path: Path, agent: Any, env: Any) -> dict[str, Any]:
    """Restore the agent (built as at the start) and the generators; return the log."""
    import numpy as np
    import torch

    state = torch.load(path, weights_only=False)
    agent.load_state_dict(state["nets"])
    agent.optimizer.load_state_dict(state["optimizer"])
    torch.set_rng_state(state["torch_rng"])
    np.random.set_state(state["numpy_rng"])  # noqa: NPY002
    set_env_rng_state(env, state["env_rng"])
    return state["log"]


def train_phase(tb: types.ModuleType, args: argparse.Namespace, work: Path) -> tuple[Any, dict]:
    """Training episodes 1..N with the test bed's ``train()``, checkpointed; resumes."""
    ckpt = work / "checkpoint.pt"
    env = make_env(args.env)
    tb.set_Seed(args.seed, env)
    agent = new_agent(tb, env, args.config)
    if ckpt.exists():
        log = load_checkpoint(ckpt, agent, env)
        print(f"resumed at episode {len(log['returns'])}", flush=True)
    else:
        log = {"returns": [], "lengths": [], "decay": [], "train_s": 0.0}
    while len(log["returns"]) < args.episodes:
        t0 = time.perf_counter()
        score, _loss, decay, length = tb.train(agent, env, "sum")
        log["train_s"] += time.perf_counter() - t0
        log["returns"].append(float(score))
        log["lengths"].append(int(length))
        log["decay"].append(float(decay))
        n = len(log["returns"])
        print(f"episode {n}: return {score:.1f}, {length} steps", flush=True)
        if n % args.checkpoint_every == 0 or n == args.episodes:
            save_checkpoint(ckpt, agent, env, log)
    env.close()
    return agent, log


def test_phase(tb: types.ModuleType, agent: Any, args: argparse.Namespace, work: Path) -> list:
    """``args.tests`` test episodes as test.py's ``process()`` runs them: the agent saved
    and reloaded, a fresh environment seeded ``2**31 - seed``, acting with the mean."""
    model_dir = str(work / "model") + "/"
    os.makedirs(model_dir, exist_ok=True)
    agent.release(model_dir)
    env = make_env(args.env)
    tb.set_Seed(2**31 - args.seed, env)
    if not agent.load(model_dir):
        raise SystemExit(f"the test bed's load() could not read {model_dir}")
    scores = [float(tb.test(agent, env, "sum", model_dir)[0]) for _ in range(args.tests)]
    env.close()
    return scores


def versions() -> dict[str, str]:
    from importlib.metadata import version

    import gym
    import numpy as np
    import torch

    return {
        "python": sys.version.split()[0],
        "torch": torch.__version__,
        "numpy": np.__version__,
        "gym": gym.__version__,
        "pybullet": version("pybullet"),
    }


def write_result(path: Path, payload: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(payload, indent=1) + "\n")
    os.replace(tmp, path)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--checkout", type=Path, required=True, help="folder of test_et (test.py)")
    ap.add_argument(
        "--env", required=True, help="a Bullet task id, e.g. InvertedPendulumBulletEnv-v0"
    )
    ap.add_argument("--seed", type=int, required=True, help="the test bed's n_trial (>= 1)")
    ap.add_argument("--config", choices=sorted(CONFIGS), default="testbed")
    ap.add_argument("--episodes", type=int, default=200)
    ap.add_argument("--tests", type=int, default=50)
    ap.add_argument("--checkpoint-every", type=int, default=10)
    ap.add_argument("--work", type=Path, required=True, help="folder of the checkpoint")
    ap.add_argument("--out", type=Path, required=True, help="the result JSON")
    args = ap.parse_args(argv)
    for name in ("episodes", "checkpoint_every"):
        if getattr(args, name) < 1:
            ap.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if args.tests < 0:
        ap.error(f"--tests must be >= 0, got {args.tests}")
    return args


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")  # before torch is imported
    os.environ.setdefault("MKL_NUM_THREADS", "1")
    import torch

    torch.set_num_threads(1)
    tb = load_testbed(args.checkout.resolve())
    args.work.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    agent, log = train_phase(tb, args, args.work)
    tests = test_phase(tb, agent, args, args.work)
    steps = sum(log["lengths"])
    write_result(
        args.out,
        {
            "implementation": "testbed",
            "env": args.env,
            "seed": args.seed,
            "config": args.config,
            "settings": CONFIGS[args.config],
            "returns": log["returns"],
            "lengths": log["lengths"],
            "mean_decay": log["decay"],
            "test_returns": tests,
            "train_ms_per_step": 1e3 * log["train_s"] / max(steps, 1),
            "wall_s_last_invocation": time.time() - t0,
            "versions": versions(),
        },
    )
    print(f"wrote {args.out}", flush=True)


if __name__ == "__main__":
    main()
