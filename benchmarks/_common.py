"""Shared helpers of the benchmarks: machine description and JSON output."""

from __future__ import annotations

import os
import platform
import sys
import time
from pathlib import Path
from typing import Any


def machine_info() -> dict[str, Any]:
    """The machine, the interpreter and the versions of the libraries that matter."""
    import gymnasium
    import numpy
    import torch

    cpu = platform.processor()
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    try:
        from importlib.metadata import version

        import pybullet  # noqa: F401

        bullet = version("pybullet")
    except Exception:  # pragma: no cover - optional
        bullet = None
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "platform": platform.platform(),
        "python": sys.version.split()[0],
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "numpy": numpy.__version__,
        "gymnasium": gymnasium.__version__,
        "pybullet": bullet,
        "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }


def payload_command() -> str:
    """The command line that is running this benchmark."""
    return " ".join([Path(sys.executable).name, *sys.argv])


def write_json(path: str | Path, payload: dict[str, Any]) -> Path:
    """Write the benchmark's results with the machine and the command that made them."""
    from pporpe.io import atomic_write_json

    payload = {
        "command": payload_command(),
        "machine": machine_info(),
        **payload,
    }
    return atomic_write_json(path, payload)
