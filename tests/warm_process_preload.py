"""What :mod:`warm_process`'s server imports before it forks a command: torch, what torch
imports when its first optimizer is built (``torch._dynamo``, about 3 s alone), and the
fused engine's kernels loaded from numba's cache (compiled into it first if they are not
there). Nothing here reads an environment variable that a test sets for one command, bar
the prefixes :data:`warm_process.IMPORT_TIME_ENV` names."""

import gc
import json
import os
import subprocess
import sys

import torch

from pporpe.online.fused_engine import warm_up

warm_up()
torch.optim.Adam([torch.zeros(1, requires_grad=True)])  # its first one imports torch._dynamo

WARNINGS = os.environ.get("PYTHONWARNINGS")
"""The warning options the server started with (a child that wants others resets them)."""

INTERPRETER_PATH: list[str] = json.loads(
    subprocess.run(
        [sys.executable, "-c", "import json, sys; print(json.dumps(sys.path[1:]))"],
        env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"},
        capture_output=True, text=True, check=True,
    ).stdout
)  # fmt: skip
"""The folders a fresh interpreter searches after its first and ``PYTHONPATH``'s: the
standard library and site-packages, with what their ``.pth`` files add (as this
interpreter, started without ``PYTHONPATH``, lists them)."""

gc.freeze()  # the children's collections leave these objects (and their pages) alone
