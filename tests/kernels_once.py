"""Forty steps of the default online learner (swish, whose fastmath loops once computed
otherwise in a process that compiled the fused kernels) and a hash of its parameters:
what ``tests/test_fused.py`` compares between a process that found numba's cache empty
(it compiles the kernels, in a subprocess, then loads them) and processes that loaded them.

Run as a script it prints ``compiled HASH`` or ``loaded HASH``: whether this process found
the kernels missing from the cache. Under pytest-xdist the suite's controller runs it as
its warm-up (``conftest.py``), so on a fresh clone the one compile of the suite is also the
test's compiling process.
"""

from __future__ import annotations

import hashlib

import numpy as np

COMPILED_HASH = "PPORPE_TEST_COMPILED_HASH"
"""Where the controller leaves the hash of its warm-up, if that process compiled."""


def parameters_hash() -> str:
    """The SHA-1 of the learner's parameters after 40 steps on fixed random inputs."""
    from pporpe.online import OnlineConfig, OnlineLearner

    learner = OnlineLearner(4, -np.ones(2), np.ones(2), OnlineConfig(layers=2, units=16), seed=3)
    rng = np.random.default_rng(0)
    learner.begin_episode(rng.normal(size=4))
    for _ in range(40):
        learner.step(float(rng.normal()), rng.normal(size=4), False, False)
    return hashlib.sha1(learner.population.state.params.numpy().tobytes()).hexdigest()


if __name__ == "__main__":
    from pporpe.online import fused_engine

    compiles = not fused_engine._in_cache()
    print("compiled" if compiles else "loaded", parameters_hash())
