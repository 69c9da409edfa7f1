"""The one sink that writes a run's logs: the per-episode CSV and TensorBoard scalars.

The CSV is the authoritative record. It is rewritten atomically from the list of
records that the checkpoint also holds, so after a crash and resume it has no gap and
no duplicate episode. TensorBoard scalars are written live, one point per episode.
"""

from __future__ import annotations

import csv
import io
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

from ..io import atomic_write_text

__all__ = ["EpisodeRecord", "RunLogger", "read_records"]


@dataclass(frozen=True)
class EpisodeRecord:
    """One training episode, as logged."""

    episode: int
    """Episode index, from 0."""
    total_steps: int
    """Environment steps taken by the end of this episode."""
    ret: float
    """Undiscounted return of the episode (unscaled rewards)."""
    length: int
    """Steps in the episode."""
    reg_amount: float
    """Mean over the episode's updates of sigma*(rho - rho_dagger)."""
    past_threshold: float
    """Fraction of the episode's updates whose ratio was past the threshold."""
    trace_decay: float
    """Mean adaptive trace decay over the episode."""
    ratio_dev: float
    """Mean |rho - 1| over the episode: how much one update changed the policy."""
    wall_time: float
    """Seconds since the start of training (over all resumed segments)."""


FIELDS = [f.name for f in fields(EpisodeRecord)]


def records_to_csv(records: list[EpisodeRecord]) -> str:
    """The CSV text of a list of records (header row first)."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=FIELDS, lineterminator="\n")
    writer.writeheader()
    for rec in records:
        writer.writerow(asdict(rec))
    return buf.getvalue()


def read_records(path: str | Path) -> list[EpisodeRecord]:
    """Read a per-episode CSV written by :class:`RunLogger` (``ValueError`` naming the file
    if it is missing a column or holds a value that is not a number)."""
    try:
        with open(path, newline="") as fh:
            rows = list(csv.DictReader(fh))
        out = []
        for row in rows:
            kw: dict[str, Any] = {}
            for f in fields(EpisodeRecord):
                kw[f.name] = int(row[f.name]) if f.type in ("int", int) else float(row[f.name])
            out.append(EpisodeRecord(**kw))
    except (OSError, UnicodeDecodeError, csv.Error, KeyError, TypeError, ValueError) as exc:
        raise ValueError(
            f"{path} cannot be read as an episodes.csv ({type(exc).__name__}: {exc}); "
            "a resumed run rewrites it from its checkpoint"
        ) from None
    return out


class RunLogger:
    """Writes ``episodes.csv`` and TensorBoard scalars under a run folder."""

    def __init__(self, run_dir: str | Path, tensorboard: bool = True) -> None:
        self.run_dir = Path(run_dir)
        self.csv_path = self.run_dir / "episodes.csv"
        self._tb: Any = None
        if tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            self._tb = SummaryWriter(log_dir=str(self.run_dir / "tensorboard"))

    def episode(self, rec: EpisodeRecord) -> None:
        """Log one episode's scalars to TensorBoard (x axis: total environment steps)."""
        if self._tb is None:
            return
        for name in ("ret", "length", "reg_amount", "past_threshold", "trace_decay", "ratio_dev"):
            self._tb.add_scalar(f"train/{name}", getattr(rec, name), rec.total_steps)

    def scalars(self, prefix: str, values: dict[str, float], step: int) -> None:
        """Log other scalars (e.g. a batch update's statistics) as ``prefix/name``."""
        if self._tb is None:
            return
        for name, value in values.items():
            self._tb.add_scalar(f"{prefix}/{name}", value, step)

    def write_records(self, records: list[EpisodeRecord]) -> None:
        """Rewrite the per-episode CSV atomically from the full list of records."""
        atomic_write_text(self.csv_path, records_to_csv(records))

    def close(self) -> None:
        """Flush and close TensorBoard."""
        if self._tb is not None:
            self._tb.flush()
            self._tb.close()
            self._tb = None
