"""Runs: the one run loop every learner kind plugs into, the run folder, and the one log
sink. See :func:`train`, :mod:`pporpe.runs.kinds` and :mod:`pporpe.runs.folder`."""

from .folder import CHECKPOINT, open_run_dir, read_config, save_checkpoint
from .kinds import (
    Episode,
    LearnerKind,
    NonFiniteError,
    Progress,
    SurrogateDiagnostics,
    Trainer,
    get_kind,
    kind_of,
    kinds,
    register_kind,
)
from .logger import EpisodeRecord, RunLogger, read_records
from .loop import RunResult, load_policy, train

__all__ = [
    "CHECKPOINT",
    "Episode",
    "EpisodeRecord",
    "LearnerKind",
    "NonFiniteError",
    "Progress",
    "RunLogger",
    "RunResult",
    "SurrogateDiagnostics",
    "Trainer",
    "get_kind",
    "kind_of",
    "kinds",
    "load_policy",
    "open_run_dir",
    "read_config",
    "read_records",
    "register_kind",
    "save_checkpoint",
    "train",
]
