"""The fused engine's numba kernel, one file per stage of a step.

* :mod:`.step`: the step itself and the entry points Python calls (:func:`.fused_step`,
  :func:`.fused_begin`, :func:`.fused_forward`);
* :mod:`.network`: the networks' forward and the hand-written backward of row s_t;
* :mod:`.head` and :mod:`.surrogates`: the policy head and the surrogates in closed form;
* :mod:`.optimiser`: the traces, td-AmsProp with t-momentum, t-soft and the target;
* :mod:`.inputs`: the kernel's inputs by name; :mod:`.jit`: numba's decorators and the
  disk cache.

The numbers are those of the torch engine up to float rounding (the same operations in
the same order where it matters; reductions are reassociated for vectorisation and the
head's scalars are computed in float64); the fused engine is bitwise deterministic for
the same inputs on the same machine, and a member's numbers never depend on the others.

Compiled artefacts are cached on disk by numba (``cache=True``): in this package's
``__pycache__`` folder, or where ``NUMBA_CACHE_DIR`` points, keyed on every file of the
package (:mod:`.jit`); the next process loads them instead of compiling
(:func:`pporpe.online.fused_engine.warm_up` compiles or loads every kernel, once per
process, when the first fused population is built).
"""
