"""The one sink that writes a run's logs: the per-episode CSV, the per-update CSV and
TensorBoard scalars.

The CSVs are the authoritative record. ``episodes.csv`` is rewritten atomically from the
list of records that the checkpoint also holds, so after a crash and resume it has no gap
and no duplicate episode. A learner that reports statistics per update (batch PPO: the
approximate KL, the share of samples past the threshold, the losses, ...) gets
``updates.csv`` the same way, a row per update. TensorBoard scalars are written live.
"""

from __future__ import annotations

import csv
import io
import itertools
import operator
from collections.abc import Callable, Iterator, Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, TypeVar

from ..io import atomic_write_text
from ..limits import MAX_CSV_BYTES
from ..run_files import read_regular_file
from .kinds import SurrogateDiagnostics

T = TypeVar("T")

__all__ = [
    "COLUMNS",
    "EpisodeRecord",
    "LoggedUpdate",
    "RunLogger",
    "read_records",
    "read_updates",
]

COLUMNS: tuple[str, ...] = (
    "episode",
    "total_steps",
    "ret",
    "length",
    "reg_amount",
    "past_threshold",
    "trace_decay",
    "ratio_dev",
    "wall_time",
)
"""The columns of ``episodes.csv``, in order: an :class:`EpisodeRecord`'s own numbers and
the four of its :class:`~pporpe.runs.kinds.SurrogateDiagnostics` (empty cells where the
record has none)."""

_DIAGNOSTIC_COLUMNS = ("reg_amount", "past_threshold", "ratio_dev", "trace_decay")


@dataclass(frozen=True)
class EpisodeRecord:
    """One training episode, as logged: one row of ``episodes.csv`` (:data:`COLUMNS`).

    Holds what every learner has; what is particular to a learner kind travels in
    :attr:`diagnostics`.
    """

    episode: int
    """Episode index, from 0."""
    total_steps: int
    """Environment steps taken by the end of this episode."""
    ret: float
    """Undiscounted return of the episode (unscaled rewards)."""
    length: int
    """Steps in the episode."""
    wall_time: float
    """Seconds since the start of training (over all resumed segments)."""
    diagnostics: SurrogateDiagnostics | None = None
    """The learner's surrogate diagnostics of the episode's updates (None for a learner
    that reports none)."""

    def row(self) -> dict[str, Any]:
        """The record as one flat row keyed by :data:`COLUMNS`, in their order, None where
        it has no value (a batch run's ``trace_decay``). The form a checkpoint stores."""
        d = self.diagnostics
        diag = dict.fromkeys(_DIAGNOSTIC_COLUMNS) if d is None else asdict(d)
        return {name: diag[name] if name in diag else getattr(self, name) for name in COLUMNS}

    @classmethod
    def from_row(cls, row: Mapping[str, Any]) -> EpisodeRecord:
        """The record of a flat row keyed by :data:`COLUMNS` (:meth:`row`, or a record of a
        checkpoint, which has always held this form). No diagnostics when all four of them
        are None; ``trace_decay`` None when it alone is (``ValueError`` when another one
        alone is missing; ``KeyError`` for a missing column)."""
        reg, past, dev, trace = (row[name] for name in _DIAGNOSTIC_COLUMNS)
        return cls(
            episode=int(row["episode"]),
            total_steps=int(row["total_steps"]),
            ret=float(row["ret"]),
            length=int(row["length"]),
            wall_time=float(row["wall_time"]),
            diagnostics=_diagnostics(reg, past, dev, trace),
        )


def _diagnostics(reg: Any, past: Any, dev: Any, trace: Any) -> SurrogateDiagnostics | None:
    """A record's diagnostics from its four cells: None when all four are None;
    ``trace_decay`` None when it alone is; ``ValueError`` when another one alone is."""
    if (reg, past, dev) != (None, None, None):
        if None in (reg, past, dev):
            raise ValueError("reg_amount, past_threshold and ratio_dev go together")
        return SurrogateDiagnostics(
            reg_amount=float(reg),
            past_threshold=float(past),
            ratio_dev=float(dev),
            trace_decay=None if trace is None else float(trace),
        )
    if trace is not None:
        raise ValueError("a trace_decay without reg_amount, past_threshold, ratio_dev")
    return None


def records_to_csv(records: list[EpisodeRecord]) -> str:
    """The CSV text of a list of records (header row first; a value the record lacks is
    an empty cell)."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=COLUMNS, lineterminator="\n")
    writer.writeheader()
    for rec in records:
        writer.writerow(rec.row())
    return buf.getvalue()


def _count(text: str) -> int:
    """An int cell: in [0, 2**62] (a count of episodes or steps; the report turns it into
    a float)."""
    value = int(text)
    if not 0 <= value <= 2**62:
        raise ValueError(f"a count out of range: {text[:30]}")
    return value


def read_records(path: str | Path) -> list[EpisodeRecord]:
    """Read a per-episode CSV written by :class:`RunLogger` (``ValueError`` naming the file
    if it is missing a column or holds a value that is not a number).

    An empty diagnostic cell reads as None: a batch run's ``trace_decay`` (batch PPO has
    no eligibility traces). Batch run folders written while batch runs filled that cell
    with 1.0 read 1.0, as written (see :mod:`pporpe.runs.migrate`).
    """
    return _read_rows(path, "episodes.csv", _records)


def _records(header: list[str], rows: Iterator[list[str]]) -> list[EpisodeRecord]:
    """The records of the rows of an ``episodes.csv`` under its ``header`` (``KeyError`` for
    a missing column, ``ValueError`` for a short row or a cell that is no number), each
    row's cells read in the order of :data:`COLUMNS`."""
    first = next(rows, None)
    if first is None:
        return []
    at = {name: i for i, name in enumerate(header)}  # the last of a repeated name, as csv's
    where = [at[name] for name in COLUMNS]
    cells_of, last = operator.itemgetter(*where), max(where)
    out = []
    for row in itertools.chain([first], rows):
        if len(row) <= last:  # csv.DictReader would fill the cells missing with None
            short = next(name for name, i in zip(COLUMNS, where, strict=True) if i >= len(row))
            raise ValueError(f"the row has no {short} cell")
        ep, steps, ret, length, reg, past, trace, dev, wall = cells_of(row)
        episode, total_steps, ret_value, length_value = (
            _count(ep), _count(steps), float(ret), _count(length)
        )  # fmt: skip
        reg_v, past_v, trace_v, dev_v = (
            None if reg == "" else float(reg), None if past == "" else float(past),
            None if trace == "" else float(trace), None if dev == "" else float(dev),
        )  # fmt: skip
        diagnostics = _diagnostics(reg_v, past_v, dev_v, trace_v)
        out.append(EpisodeRecord(
            episode, total_steps, ret_value, length_value, float(wall), diagnostics
        ))  # fmt: skip
    return out


def _read_rows(
    path: str | Path, what: str, parse: Callable[[list[str], Iterator[list[str]]], list[T]]
) -> list[T]:
    """The rows of the CSV file ``path`` read by ``parse`` (given the header and the other
    rows, blank lines skipped, as ``csv.DictReader`` does); ``ValueError`` naming the file
    as not readable as ``what`` (missing, torn, not a regular file, larger than
    :data:`~pporpe.limits.MAX_CSV_BYTES`, a missing column, a cell that is no number)."""
    remedy = "a resumed run rewrites it from its checkpoint"
    raw = read_regular_file(path, MAX_CSV_BYTES, remedy)
    try:
        rows = csv.reader(io.StringIO(raw.decode("utf-8"), newline=""))
        header = next(rows, None)
        return [] if header is None else parse(header, (row for row in rows if row))
    except (UnicodeDecodeError, csv.Error, KeyError, TypeError, ValueError) as exc:
        raise ValueError(
            f"{path} cannot be read as an {what} ({type(exc).__name__}: {exc}); {remedy}"
        ) from None


UPDATE_COLUMNS: tuple[str, str] = ("update", "total_steps")
"""The first columns of ``updates.csv``; the learner's statistics follow, in the order it
reports them, and ``wall_time`` last."""


@dataclass(frozen=True)
class LoggedUpdate:
    """One update of a learner that reports statistics per update: one row of
    ``updates.csv``."""

    update: int
    """Update index, from 0."""
    total_steps: int
    """Environment steps taken by the run when the update was made."""
    values: dict[str, float]
    """The learner's statistics of the update by name (a batch update's
    :class:`~pporpe.batch.UpdateStats`), in the order it reports them."""
    wall_time: float
    """Seconds since the start of training (over all resumed segments)."""

    def row(self) -> dict[str, Any]:
        """The update as one flat row: ``update``, ``total_steps``, the values, ``wall_time``
        (the form a checkpoint stores)."""
        return {"update": self.update, "total_steps": self.total_steps, **self.values,
                "wall_time": self.wall_time}  # fmt: skip

    @classmethod
    def from_row(cls, row: Mapping[str, Any]) -> LoggedUpdate:
        """The update of a flat row (:meth:`row`, or a row of ``updates.csv``)."""
        values = {k: float(v) for k, v in row.items() if k not in (*UPDATE_COLUMNS, "wall_time")}
        update, steps = (_count(str(row[k])) for k in UPDATE_COLUMNS)
        return cls(update, steps, values, float(row["wall_time"]))


def updates_to_csv(updates: list[LoggedUpdate]) -> str:
    """The CSV text of a list of logged updates (header row first); ``ValueError`` if they do
    not all report the same statistics."""
    names = list(updates[0].row()) if updates else [*UPDATE_COLUMNS, "wall_time"]
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=names, lineterminator="\n")
    writer.writeheader()
    for u in updates:
        row = u.row()
        if list(row) != names:
            raise ValueError(f"update {u.update} reports {list(row)}, the first {names}")
        writer.writerow(row)
    return buf.getvalue()


def read_updates(path: str | Path) -> list[LoggedUpdate]:
    """Read an ``updates.csv`` written by :class:`RunLogger` (``ValueError`` naming the file
    if a required column is missing or a cell is not a number). An empty cell reads as NaN
    (a statistic an update could not compute)."""
    return _read_rows(path, "updates.csv", _updates)


def _updates(header: list[str], rows: Iterator[list[str]]) -> list[LoggedUpdate]:
    """The logged updates of the rows of an ``updates.csv`` under its ``header``."""
    out = []
    for row in rows:
        if len(row) != len(header):
            raise ValueError(f"a row of {len(row)} cells under a header of {len(header)}")
        cells = {k: "nan" if v == "" else v for k, v in zip(header, row, strict=True)}
        out.append(LoggedUpdate.from_row(cells))
    return out


class RunLogger:
    """Writes ``episodes.csv``, ``updates.csv`` and TensorBoard scalars under a run folder."""

    def __init__(self, run_dir: str | Path, tensorboard: bool = True) -> None:
        self.run_dir = Path(run_dir)
        self.csv_path = self.run_dir / "episodes.csv"
        self.updates_path = self.run_dir / "updates.csv"
        self._tb: Any = None
        if tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            self._tb = SummaryWriter(log_dir=str(self.run_dir / "tensorboard"))

    def episode(self, rec: EpisodeRecord) -> None:
        """Log one episode's scalars to TensorBoard (x axis: total environment steps)."""
        if self._tb is None:
            return
        row = rec.row()
        for name in ("ret", "length", "reg_amount", "past_threshold", "trace_decay", "ratio_dev"):
            if row[name] is not None:  # a value the record lacks is not plotted
                self._tb.add_scalar(f"train/{name}", row[name], rec.total_steps)

    def scalars(self, prefix: str, values: dict[str, float], step: int) -> None:
        """Log other scalars (e.g. a batch update's statistics) as ``prefix/name``."""
        if self._tb is None:
            return
        for name, value in values.items():
            self._tb.add_scalar(f"{prefix}/{name}", value, step)

    def write_records(self, records: list[EpisodeRecord]) -> None:
        """Rewrite the per-episode CSV atomically from the full list of records."""
        atomic_write_text(self.csv_path, records_to_csv(records))

    def write_updates(self, updates: list[LoggedUpdate]) -> None:
        """Rewrite the per-update CSV atomically from the full list of logged updates (no
        file for a learner that reports none)."""
        if updates:
            atomic_write_text(self.updates_path, updates_to_csv(updates))

    def close(self) -> None:
        """Flush and close TensorBoard."""
        if self._tb is not None:
            self._tb.flush()
            self._tb.close()
            self._tb = None
