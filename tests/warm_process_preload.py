"""What :mod:`warm_process`'s server imports before it forks a command: torch, and the
fused engine's kernels loaded from numba's cache (compiled into it first if they are not
there). Nothing here reads an environment variable that a test sets for one command, bar
the prefixes :data:`warm_process.IMPORT_TIME_ENV` names."""

import gc
import os
import sys

import torch  # noqa: F401

from pporpe.online.fused_engine import warm_up

warm_up()

WARNINGS = os.environ.get("PYTHONWARNINGS")
"""The warning options the server started with (a child that wants others resets them)."""

INTERPRETER_PATH = [
    p for p in sys.path[1:] if p not in os.environ.get("PYTHONPATH", "").split(os.pathsep)
]
"""The folders a fresh interpreter searches besides its first and ``PYTHONPATH``'s: the
standard library and site-packages (with what their ``.pth`` files add)."""

gc.freeze()  # the children's collections leave these objects (and their pages) alone
