"""The documented upper bounds of a run's sizes, budgets and seeds, and of the files pporpe reads.

Every bound is far above any real use (the paper's networks are 5 x 100, its longest runs
2000 episodes, its seeds 0-24) and below what exhausts a machine's memory or time, so that
a typo on a command line, in a grid spec or in a run folder received from someone else is
one line naming the field, before anything is allocated or trained. The configs check
them in ``__post_init__`` (:class:`~pporpe.online.TrainConfig`,
:class:`~pporpe.online.OnlineConfig`, :class:`~pporpe.batch.BatchConfig`), so the CLI, the
grid specs and the run folders are covered alike; the readers of a run folder check the
file bounds (:mod:`pporpe.run_files`, :mod:`pporpe.runs.checkpoint_data`).
"""

from __future__ import annotations

from typing import Any

__all__ = [
    "MAX_CHECKPOINT_BYTES",
    "MAX_CHECKPOINT_DEPTH",
    "MAX_CHECKPOINT_ELEMENTS",
    "MAX_CSV_BYTES",
    "MAX_EPISODES",
    "MAX_EVAL_EPISODES",
    "MAX_GRID_RUNS",
    "MAX_HIDDEN_WEIGHTS",
    "MAX_JSON_BYTES",
    "MAX_JSON_DEPTH",
    "MAX_LAYERS",
    "MAX_N_ENVS",
    "MAX_N_EPOCHS",
    "MAX_ROLLOUT",
    "MAX_SEED",
    "MAX_STEPS",
    "MAX_UNITS",
    "check_int_in",
    "short_repr",
]

MAX_UNITS = 4096
"""Units per hidden layer (the paper: 100; rl-baselines3-zoo's largest PPO nets: 256)."""
MAX_LAYERS = 64
"""Hidden layers (the paper: 5)."""
MAX_HIDDEN_WEIGHTS = 2**24
"""units * units * layers, the weights of a network's hidden layers: 16,777,216 (the paper's
networks have 50,000; 2048 x 4 is at the bound). A run keeps about ten copies of them per
network (parameters, target, traces, optimiser moments): about 1 GB of float32 at the bound."""
MAX_SEED = 2**32 - 1
"""Largest seed: 4,294,967,295 (numpy's classic seed range). Test episodes use the seed plus
:data:`~pporpe.evaluation.EVAL_SEED_OFFSET`, sub-environments the seed plus their index:
both stay far below torch's limit of 2**64."""
MAX_EPISODES = 10**6
"""Largest training budget in episodes (the paper's longest runs: 2000); a run keeps a record
of each (a few hundred bytes)."""
MAX_STEPS = 10**9
"""Largest training budget in environment steps (the paper's longest runs: 2 x 10**6)."""
MAX_EVAL_EPISODES = 10**4
"""Most test episodes of a run (the paper scores 50)."""
MAX_N_ENVS = 1024
"""Most parallel sub-environments of a batch run (rl-baselines3-zoo's PPO: up to 16)."""
MAX_ROLLOUT = 2**20
"""Most transitions in one batch rollout, n_envs * n_steps: 1,048,576 (the zoo's: up to
16,384)."""
MAX_N_EPOCHS = 10**4
"""Most passes over each batch rollout (the zoo's: up to 20)."""

MAX_JSON_BYTES = 64 * 2**20
"""Largest JSON file of a run or grid folder read: 64 MiB (a grid.json of 300 runs: 0.4 MiB)."""
MAX_JSON_DEPTH = 32
"""Deepest nesting of lists and objects in such a file (pporpe's own files: 5)."""
MAX_GRID_RUNS = 10**6
"""Most runs a grid.json lists."""
MAX_CSV_BYTES = 1 * 2**30
"""Largest episodes.csv or updates.csv read: 1 GiB (a 2000-episode run's: 0.2 MiB)."""
MAX_CHECKPOINT_BYTES = 8 * 2**30
"""Largest checkpoint read: 8 GiB (a population of 30 of the paper's runs: about 0.1 GiB)."""
MAX_CHECKPOINT_ELEMENTS = 2**30
"""Most numbers (tensor and array elements, together) in one checkpoint."""
MAX_CHECKPOINT_DEPTH = 32
"""Deepest nesting of containers in a checkpoint (pporpe's own: 6)."""


def check_int_in(name: str, value: Any, lo: int, hi: int) -> None:
    """Raise ``ValueError("<name> must be an int in [lo, hi]; got <name>=<value>")`` unless
    ``value`` is an int (not a bool) in that range."""
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise ValueError(f"{name} must be an int in [{lo}, {hi:,}]; got {name}={short_repr(value)}")


def short_repr(value: Any, width: int = 60) -> str:
    """``repr(value)`` cut to ``width`` characters; an int of 30 digits or more as its number
    of digits (a value read from someone else's file may be huge)."""
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 99:
        return f"an int of {int(value.bit_length() * 0.30103) + 1} digits"
    text = repr(value)
    return text if len(text) <= width else text[: width - 3] + "..."
