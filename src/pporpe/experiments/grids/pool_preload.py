"""What the local pool's server process imports once, before it forks the grid's workers
(:func:`~pporpe.experiments.grids.backends.run_local`): torch, the trainers, the fused
engine's kernels (loaded from numba's disk cache) and what torch imports when its first
optimizer is built (``torch._dynamo``, about 3 s alone). Every worker then starts with
them in memory instead of importing them itself (about 3 s of a core each, 6 for a batch
PPO worker).

Two settings come first, as a worker would have them: one thread for torch unless
``OMP_NUM_THREADS`` says otherwise (set before torch reads it), and SIGTERM ignored, so that
a SIGTERM to the grid's process group (a scheduler's stop) leaves the server, and with it
the workers, to finish the checkpoints the grid asks for; the server ends when the grid's
process does. Nothing imported here prints (PyBullet, which does, is imported by a worker).
"""

from __future__ import annotations

import os
import signal

os.environ.setdefault("OMP_NUM_THREADS", "1")
signal.signal(signal.SIGTERM, signal.SIG_IGN)

import torch  # noqa: E402

from ... import batch, envs, online  # noqa: E402, F401
from ...online.fused_engine import warm_up  # noqa: E402
from ...runs import loop  # noqa: E402, F401
from . import backends  # noqa: E402, F401

warm_up()
torch.optim.Adam([torch.zeros(1, requires_grad=True)])  # its first one imports torch._dynamo
