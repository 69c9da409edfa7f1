"""Queues of runs that a test kills with SIGKILL: built the same way in the test process and
in the child that is killed (``python tests/killable.py CASE ROOT WITHIN``, which trains
:func:`queue` of ``CASE`` under ``ROOT`` with checkpoints by time every ``WITHIN`` seconds
at the latest). Their ``checkpoint_every`` is never reached: every checkpoint before a
run's last is one by time."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from pporpe.batch import BatchConfig
from pporpe.online import OnlineConfig, TrainConfig
from pporpe.runs.loop import run_queue

NEVER = 1_000_000
"""A ``checkpoint_every`` no run reaches."""

TINY = OnlineConfig(layers=1, units=8, compile=False)


def online(seed: int, episodes: int = 400) -> TrainConfig:
    return TrainConfig(env="pendulum", seed=seed, episodes=episodes, checkpoint_every=NEVER,
                       eval_episodes=1, learner=TINY)  # fmt: skip


def batch(seed: int) -> BatchConfig:
    return BatchConfig(
        env="pendulum", seed=seed, n_envs=2, n_steps=32, batch_size=16, n_epochs=2,
        total_steps=64 * 60, layers=1, units=16, checkpoint_every=NEVER, eval_episodes=1,
    )  # fmt: skip


CASES: dict[str, tuple[list[Any], int]] = {
    "online": ([online(5)], 1),  # a single online run: checkpoints mid-episode
    "batch": ([batch(3)], 1),  # a batch run: checkpoints between updates
    "population": ([online(1, 300), online(2, 200), online(3, 150)], 2),  # 3 runs, 2 slots
}
"""Each case's run configurations and the trainer's slots."""


def queue(case: str, root: Path) -> list[tuple[Any, Path]]:
    """The case's ``(config, run folder)`` pairs under ``root``."""
    return [(cfg, root / f"run{i}") for i, cfg in enumerate(CASES[case][0])]


def train_case(case: str, root: Path, within: float) -> list[Any]:
    """Train the case's queue into ``root`` (its home too), resuming what is there; a
    population's count-asked checkpoints at most once a minute, as a grid's."""
    return run_queue(queue(case, root), capacity=CASES[case][1], home=root,
                     checkpoint_seconds=60.0, checkpoint_within=within)  # fmt: skip


if __name__ == "__main__":
    train_case(sys.argv[1], Path(sys.argv[2]), float(sys.argv[3]))
