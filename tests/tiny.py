"""The small learners and tasks the tests share (imported by the test files; conftest.py
holds the session settings).

Small networks keep a test fast; a test that needs other sizes passes them as keywords.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from pporpe.online import BASELINE_CHOICES, OnlineConfig, PopulationLearner

SMALL_NET: dict[str, Any] = {"layers": 2, "units": 16, "compile": False}
"""Two hidden layers of 16 units, no compiled update: the population and fidelity tests."""

OBS, ACT = 3, 2
"""Observation and action sizes of the synthetic transitions the learner tests feed."""
LOW, HIGH = -np.ones(ACT), np.ones(ACT)
"""Action bounds of those tests."""


def small_config(**kw: Any) -> OnlineConfig:
    """An :class:`OnlineConfig` with :data:`SMALL_NET` and today's defaults otherwise."""
    return OnlineConfig(**{**SMALL_NET, **kw})


def baseline_config(**kw: Any) -> OnlineConfig:
    """:func:`small_config` with :data:`~pporpe.online.BASELINE_CHOICES`: the choices the
    scalar reference learner (``reference_online.py``) implements."""
    return OnlineConfig(**{**SMALL_NET, **BASELINE_CHOICES, **kw})


def population(
    configs: list[OnlineConfig],
    seeds: list[int],
    compile_update: bool = False,
    engine: str | None = None,
) -> PopulationLearner:
    """A population of ``configs`` on the :data:`OBS` / :data:`ACT` synthetic task
    (``engine``: None, the configs' own)."""
    return PopulationLearner(
        OBS, LOW, HIGH, configs, seeds, compile_update=compile_update, engine=engine
    )


def tiny_learner(**kw: Any) -> OnlineConfig:
    """One hidden layer of 8 units: the smallest learner a whole training run uses."""
    return OnlineConfig(**{"layers": 1, "units": 8, "compile": False, **kw})


def tiny_grid_toml(
    name: str = "tiny",
    methods: tuple[str, ...] = ("ppo", "rpe"),
    seeds: tuple[int, ...] = (0, 1),
    episodes: int = 3,
    checkpoint_every: int | None = 1,
) -> str:
    """The TOML of a small online grid on InvertedPendulum (1 x 8 networks, 1 test
    episode per run): ``checkpoint_every`` None leaves the spec's default."""
    every = "" if checkpoint_every is None else f"checkpoint_every = {checkpoint_every}\n"
    quoted = ", ".join('"' + m + '"' for m in methods)
    return (
        f'name = "{name}"\nmethods = [{quoted}]\n'
        f"seeds = [{', '.join(map(str, seeds))}]\neval_episodes = 1\n{every}\n"
        '[learner]\nlayers = 1\nunits = 8\n\n[[tasks]]\nenv = "pendulum"\n'
        f"episodes = {episodes}\n"
    )


def records_text(run: Path, name: str = "episodes.csv") -> list[str]:
    """A run's ``episodes.csv`` or ``updates.csv`` without its wall-time column (the only one
    that is not computed): what two runs that compute the same numbers share line for line."""
    lines = (run / name).read_text().splitlines()
    column = lines[0].split(",").index("wall_time")
    return [",".join(v for i, v in enumerate(line.split(",")) if i != column) for line in lines]


def same_run_either_way(
    cfg: Any, variable: str, steps: tuple[str, str], tmp_path: Path, monkeypatch: Any
) -> None:
    """Train ``cfg`` once with the environment variable ``variable`` set to each of ``steps``
    (two implementations of an environment's step) and assert that both runs wrote the same
    records (``episodes.csv``, and ``updates.csv`` where there is one) and test returns."""
    from pporpe.runs import train

    runs = {}
    for step in steps:
        monkeypatch.setenv(variable, step)
        runs[step] = train(cfg, tmp_path / step, progress=False)
    a, b = (tmp_path / step for step in steps)
    assert records_text(a) == records_text(b)
    assert len(records_text(a)) >= 3  # a header and two episodes at least
    if (a / "updates.csv").exists():
        assert records_text(a, "updates.csv") == records_text(b, "updates.csv")
    assert runs[steps[0]].evaluation == runs[steps[1]].evaluation
