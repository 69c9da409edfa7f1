"""Evaluation of a trained policy: returns of test episodes and their summary.

The paper scores a trained policy by the *median* return of 50 test episodes acted
with the policy's location (no sampling).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .envs import make_env

__all__ = [
    "EVAL_SEED_OFFSET",
    "EvalResult",
    "evaluate_policy",
    "load_evaluation",
    "summarize_returns",
]

EVAL_SEED_OFFSET = 1_000_003
"""Test episodes of a run with seed s use environment seed s + EVAL_SEED_OFFSET, apart from
training seeds."""


@dataclass(frozen=True)
class EvalResult:
    """Summary of test returns."""

    episodes: int
    """Number of test episodes."""
    median: float
    """Median return: the paper's score."""
    mean: float
    """Mean return."""
    q25: float
    """25th percentile of the returns."""
    q75: float
    """75th percentile of the returns."""
    returns: list[float]
    """Every test return, in episode order."""

    @property
    def iqr(self) -> float:
        """Interquartile range q75 - q25."""
        return self.q75 - self.q25

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary (with the IQR)."""
        return {**asdict(self), "iqr": self.iqr}


def summarize_returns(returns: list[float]) -> EvalResult:
    """Median, mean and quartiles of a list of returns."""
    if not returns:
        raise ValueError("returns must hold at least one episode return; got []")
    arr = np.asarray(returns, dtype=np.float64)
    q25, med, q75 = np.percentile(arr, [25, 50, 75])
    return EvalResult(
        len(returns),
        float(med),
        float(arr.mean()),
        float(q25),
        float(q75),
        [float(r) for r in returns],
    )


def load_evaluation(run_dir: str | Path) -> EvalResult | None:
    """The test-episode summary saved in ``run_dir/evaluation.json``, or None without one."""
    path = Path(run_dir) / "evaluation.json"
    if not path.exists():
        return None
    return summarize_returns(json.loads(path.read_text())["returns"])


def evaluate_policy(
    act: Callable[[np.ndarray], np.ndarray], env_name: str, episodes: int, seed: int
) -> EvalResult:
    """Run ``episodes`` test episodes with the deterministic policy ``act``.

    The environment is seeded once with ``seed`` (callers pass the training seed plus
    :data:`EVAL_SEED_OFFSET`) and each episode runs until termination or truncation.
    """
    if not (isinstance(episodes, int) and episodes >= 1):
        raise ValueError(f"episodes must be an int >= 1; got episodes={episodes!r}")
    env = make_env(env_name, seed=seed)
    returns: list[float] = []
    try:
        obs, _ = env.reset(seed=seed)
        for _ in range(episodes):
            total, done = 0.0, False
            while not done:
                obs, reward, terminated, truncated, _ = env.step(act(obs))
                total += float(reward)
                done = terminated or truncated
            returns.append(total)
            obs, _ = env.reset()
    finally:
        env.close()
    return summarize_returns(returns)
