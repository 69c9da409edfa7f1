"""The fused engine: one step of every member as one compiled numba kernel
(``engine="fused"``), and the loading of that kernel, once per process (:func:`warm_up`).

:class:`FusedEngine` (:mod:`.engine`) is its Python side; the kernel is in
:mod:`.kernels`, one file per stage of the step.
"""

from __future__ import annotations

import os
import subprocess
import sys
import warnings

import numpy as np

from ..config import OnlineConfig
from ..engine import PopulationParts
from .engine import FusedEngine, segment_ranges
from .kernels.step import fused_begin, fused_forward, fused_step

__all__ = ["FusedEngine", "compile_kernels", "segment_ranges", "warm_up"]


_KERNELS = (fused_begin, fused_step, fused_forward)
"""The kernels Python calls; each carries the code of every function it calls."""


class _Loaded:
    """Whether this process has loaded the kernels: :func:`warm_up`."""

    done = False


def _run_kernels() -> None:
    """The smallest population, set up as a
    :class:`~pporpe.online.population.PopulationLearner` sets up its members, through a
    first action, a step and both forwards: every kernel called once, with the argument
    types every population passes (its engine converts its inputs). The kernels' types do
    not depend on the population's sizes, so this covers every population."""
    config = OnlineConfig(layers=1, units=2)
    parts = PopulationParts.build(1, -np.ones(1), np.ones(1), config, 1)
    engine = FusedEngine(parts)
    parts.consts.write(0, config, parts.lay)
    engine.set_member(0, config)
    parts.init_member(0, config, 0)
    obs, no = np.zeros((1, 1)), np.zeros(1, dtype=bool)
    engine.begin(np.zeros(1, dtype=np.int64), obs, None)
    engine.step(np.zeros(1), obs, no, no, np.ones(1, dtype=bool), None)
    engine.outputs(0, obs)
    engine.outputs(1, obs)


def compile_kernels() -> None:
    """Compile every kernel into numba's disk cache (the body of :func:`warm_up`'s
    subprocess)."""
    _Loaded.done = True
    _run_kernels()


def _in_cache() -> bool:
    """Whether numba's disk cache holds every kernel for today's source (its index is
    empty where the source changed). numba has no public call for this; its version is
    pinned in constraints.txt."""
    for kernel in _KERNELS:
        index = getattr(getattr(kernel, "_cache", None), "_cache_file", None)
        if index is None or not index._load_index():
            return False
    return True


def warm_up() -> None:
    """Load every kernel of :mod:`.kernels` from numba's disk cache (:mod:`.kernels`'s
    docstring says where), once per process; if it is not there, compile it first in a
    subprocess. :class:`~pporpe.online.population.PopulationLearner` calls this when it
    is built with the fused engine, so the compile falls before a run's clock starts.

    Why a subprocess: a process that compiled the kernels computes float rounding
    differently from one that loaded them (measured with numba 0.68.1 on this project's
    machine, with the swish activation only: the same cached code, loaded in both), so the
    numbers of a run would depend on whether its process found the cache. A process that
    trains only ever loads; where the cache cannot be written, every process compiles,
    and they agree with one another. Tested in tests/test_fused.py.
    """
    if _Loaded.done:
        return
    _Loaded.done = True  # set first, reset below if loading fails
    try:
        if not _in_cache():
            _compile_in_subprocess()
        _run_kernels()  # loads them (compiles them where the cache cannot be written)
    except BaseException:
        _Loaded.done = False
        raise


def _compile_in_subprocess() -> None:
    """:func:`compile_kernels` in a fresh interpreter that finds pporpe where this one did
    (its ``sys.path``); if that fails, a warning, and the kernels compile in this process."""
    code = "from pporpe.online.fused_engine import compile_kernels; compile_kernels()"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    if done.returncode != 0:
        warnings.warn(
            "compiling the fused kernels in a subprocess failed, so this process compiles "
            "them, and its float rounding may differ from a process that loads them from "
            f"numba's cache:\n{done.stderr[-2000:]}",
            RuntimeWarning,
            stacklevel=3,
        )
