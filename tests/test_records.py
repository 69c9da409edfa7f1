"""Episode records that fit every learner: what every learner has, and its surrogate
diagnostics as one named extra (batch PPO without a trace decay); episodes.csv and the
checkpoint's records in the form they always had."""

from __future__ import annotations

import csv
import io
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
import torch
from interrupt import Interrupted, at_episode
from tiny import tiny_learner

from pporpe.batch import BatchConfig
from pporpe.experiments.reports.results import diagnostic, record_value, update_mean
from pporpe.online.config import TrainConfig
from pporpe.runs import EpisodeRecord, SurrogateDiagnostics, read_records, train
from pporpe.runs.folder import CHECKPOINT, load_checkpoint, save_checkpoint
from pporpe.runs.logger import (
    LoggedUpdate,
    RunLogger,
    read_updates,
    records_to_csv,
    updates_to_csv,
)

FIXTURES = Path(__file__).parent / "fixtures"
HEADER = "episode,total_steps,ret,length,reg_amount,past_threshold,trace_decay,ratio_dev,wall_time"
OLD_KEYS = HEADER.split(",")
"""The fields of the flat record every checkpoint has held, in the order it held them."""


def batch(**kw: Any) -> BatchConfig:
    base: dict[str, Any] = dict(
        env="pendulum", seed=3, n_envs=2, n_steps=32, batch_size=16, n_epochs=2,
        total_steps=256, layers=1, units=16, checkpoint_every=2, eval_episodes=0,
    )  # fmt: skip
    return BatchConfig(**{**base, **kw})


def online(**kw: Any) -> TrainConfig:
    base: dict[str, Any] = dict(
        env="pendulum", seed=3, episodes=3, checkpoint_every=1, eval_episodes=0,
        learner=tiny_learner(),
    )  # fmt: skip
    return TrainConfig(**{**base, **kw})


def csv_column(path: Path, name: str) -> list[str]:
    lines = path.read_text().splitlines()
    at = lines[0].split(",").index(name)
    return [line.split(",")[at] for line in lines[1:]]


def tensorboard_tags(run: Path) -> set[str]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(run / "tensorboard"))
    events.Reload()
    return set(events.Tags()["scalars"])


def record(episode: int, diagnostics: SurrogateDiagnostics | None) -> EpisodeRecord:
    return EpisodeRecord(episode, 10 * (episode + 1), 1.5 * episode, 10, 0.25 * episode,
                         diagnostics)  # fmt: skip


def test_batch_run_records_have_no_trace_decay(tmp_path: Path) -> None:
    result = train(batch(), tmp_path, progress=False)
    assert result.records
    for rec in result.records:
        assert rec.diagnostics is not None and rec.diagnostics.trace_decay is None
        assert rec.diagnostics.reg_amount >= 0.0 and 0.0 <= rec.diagnostics.past_threshold <= 1
    assert (tmp_path / "episodes.csv").read_text().splitlines()[0] == HEADER
    assert set(csv_column(tmp_path / "episodes.csv", "trace_decay")) == {""}
    assert "" not in csv_column(tmp_path / "episodes.csv", "ratio_dev")
    assert read_records(tmp_path / "episodes.csv") == result.records
    saved = load_checkpoint(tmp_path)["records"]
    assert [list(r) for r in saved] == [OLD_KEYS] * len(saved)  # flat, as always
    assert {r["trace_decay"] for r in saved} == {None}
    tags = tensorboard_tags(tmp_path)
    assert "train/reg_amount" in tags and "train/trace_decay" not in tags
    # the report's readers: no trace decay is NaN ("n/a"), never 1.0
    assert math.isnan(update_mean(result.records, "trace_decay"))
    assert math.isnan(diagnostic(result.records[0], "trace_decay"))
    assert math.isfinite(update_mean(result.records, "ratio_dev"))


def test_online_run_records_carry_all_four(tmp_path: Path) -> None:
    result = train(online(), tmp_path, progress=False)
    assert len(result.records) == 3
    for rec in result.records:
        d = rec.diagnostics
        assert d is not None and d.trace_decay is not None
        values = (d.reg_amount, d.past_threshold, d.ratio_dev, d.trace_decay)
        assert all(math.isfinite(v) for v in values) and 0.0 < d.trace_decay <= 1.0
    for name in ("reg_amount", "past_threshold", "trace_decay", "ratio_dev"):
        assert "" not in csv_column(tmp_path / "episodes.csv", name)
        assert f"train/{name}" in tensorboard_tags(tmp_path)
    assert read_records(tmp_path / "episodes.csv") == result.records
    assert 0.0 < update_mean(result.records, "trace_decay") <= 1.0
    assert record_value(result.records[1], "ret") == result.records[1].ret


def test_csv_round_trip_with_and_without_trace_decay(tmp_path: Path) -> None:
    records = [
        record(0, SurrogateDiagnostics(1e-4, 0.125, 0.01, trace_decay=0.9813588261604309)),
        record(1, SurrogateDiagnostics(2e-5, 0.0, 0.002)),  # a batch episode: no traces
        record(2, None),  # a learner that reports no diagnostics
        record(3, SurrogateDiagnostics(math.nan, 0.0, math.nan, trace_decay=1.0)),
    ]
    RunLogger(tmp_path, tensorboard=False).write_records(records)
    lines = (tmp_path / "episodes.csv").read_text().splitlines()
    assert lines == [
        HEADER,
        "0,10,0.0,10,0.0001,0.125,0.9813588261604309,0.01,0.0",
        "1,20,1.5,10,2e-05,0.0,,0.002,0.25",
        "2,30,3.0,10,,,,,0.5",
        "3,40,4.5,10,nan,0.0,1.0,nan,0.75",
    ]
    back = read_records(tmp_path / "episodes.csv")
    assert back[:3] == records[:3] and back[1].diagnostics is not None
    assert back[1].diagnostics.trace_decay is None and back[2].diagnostics is None
    assert back[3].diagnostics is not None and math.isnan(back[3].diagnostics.reg_amount)
    assert [EpisodeRecord.from_row(r.row()) for r in records[:3]] == records[:3]


@pytest.mark.parametrize(
    "row", ["0,10,0.0,10,,0.1,0.9,0.01,0.0", "0,10,0.0,10,,,0.9,,0.0", "0,10,,10,,,,,0.0"]
)
def test_a_missing_diagnostic_or_return_is_refused(row: str, tmp_path: Path) -> None:
    """An empty cell is a value the learner lacks: the trace decay alone, or all four
    diagnostics; never one of the others alone, nor a number every learner has."""
    path = tmp_path / "episodes.csv"
    path.write_text(f"{HEADER}\n{row}\n")
    with pytest.raises(ValueError, match=r"cannot be read as an episodes\.csv"):
        read_records(path)


def reference_records(text: str) -> list[EpisodeRecord]:
    """``episodes.csv`` read the plain way: csv.DictReader, an empty cell None, every
    number converted by the record's own constructor."""
    rows = csv.DictReader(io.StringIO(text, newline=""))
    cells = [{k: None if v == "" else v for k, v in row.items() if k in OLD_KEYS} for row in rows]
    return [EpisodeRecord.from_row(c) for c in cells]


@pytest.mark.parametrize(
    "layout", ["as written", "columns reordered", "a column more", "blank lines, CRLF"]
)
def test_the_reader_reads_what_a_dict_reader_reads(layout: str, tmp_path: Path) -> None:
    """read_records (a column index and a row at a time) against csv.DictReader and
    EpisodeRecord.from_row, on files laid out otherwise than RunLogger writes them."""
    lines = [
        HEADER,
        "0,10,0.5,10,0.1,0.2,,0.3,1.0",
        "1,25,-2.0,15,,,,,2.5",
        "2,31,1e3,6,1,0,0.5,2,3",
    ]
    rows = [line.split(",") for line in lines]
    if layout == "columns reordered":
        rows = [row[::-1] for row in rows]
    if layout == "a column more":
        rows = [[*row, "note" if i == 0 else "x"] for i, row in enumerate(rows)]
    end = "\r\n\r\n" if layout == "blank lines, CRLF" else "\n"
    text = end.join(",".join(row) for row in rows) + end
    (tmp_path / "episodes.csv").write_text(text, newline="")
    got = read_records(tmp_path / "episodes.csv")
    assert got == reference_records(text) and len(got) == 3
    assert got[0].diagnostics == SurrogateDiagnostics(0.1, 0.2, 0.3, None)
    assert got[1].diagnostics is None and got[2].ret == 1000.0


@pytest.mark.parametrize(("row", "why"), [
    ("0,10,0.5,10,0.1,0.2", "the row has no trace_decay cell"),
    ("0,10,x,10,,,,,1.0", "could not convert string to float: 'x'"),
    ("-1,10,0.5,10,,,,,1.0", "a count out of range: -1"),
])  # fmt: skip
def test_a_short_or_wrong_row_is_refused_naming_the_cell(
    row: str, why: str, tmp_path: Path
) -> None:
    path = tmp_path / "episodes.csv"
    path.write_text(f"{HEADER}\n{row}\n")
    with pytest.raises(
        ValueError, match=f"episodes\\.csv cannot be read as an episodes\\.csv .*{why}"
    ):
        read_records(path)
    path.write_text(HEADER.replace("ratio_dev", "ratio") + "\n0,10,0.5,10,,,,,1.0\n")
    with pytest.raises(ValueError, match="KeyError: 'ratio_dev'"):
        read_records(path)


@pytest.mark.parametrize("name", ["online", "batch"])
def test_old_flat_checkpoint_records_load(name: str) -> None:
    """The records of a checkpoint written by pporpe's first release (flat dicts, a batch
    run's trace decay 1.0) read as its episodes.csv does; a record's row is that form."""
    run = FIXTURES / f"run_v0_1_{name}"
    saved = torch.load(run / CHECKPOINT, weights_only=False)["records"]
    assert saved and all(list(r) == OLD_KEYS for r in saved)
    records = [EpisodeRecord.from_row(r) for r in saved]
    assert records == read_records(run / "episodes.csv")
    assert [r.row() for r in records] == saved
    decays = {r.diagnostics.trace_decay for r in records if r.diagnostics is not None}
    assert len(records) == len(saved) and (decays == {1.0}) == (name == "batch")


def test_old_flat_checkpoint_resumes(tmp_path: Path) -> None:
    """A batch run whose checkpoint holds records in the old form (trace decay 1.0)
    continues exactly: its old episodes keep their 1.0, as written; the new ones have
    none; every other number equals the uninterrupted run's."""
    cfg = batch(total_steps=384)
    full = train(cfg, tmp_path / "full", progress=False).records
    run = tmp_path / "old"
    with pytest.raises(Interrupted):
        train(cfg, run, progress=False, on_episode=at_episode(len(full) - 2))
    state = load_checkpoint(run)
    old = [{**r, "trace_decay": 1.0} for r in state["records"]]
    assert 0 < len(old) < len(full) - 2 and all(list(r) == OLD_KEYS for r in old)
    save_checkpoint(run / CHECKPOINT, {**state, "records": old})
    resumed = train(cfg, run, progress=False).records
    n = len(old)
    decays = [r.diagnostics.trace_decay if r.diagnostics else "-" for r in resumed]
    assert decays == [1.0] * n + [None] * (len(full) - n)
    assert csv_column(run / "episodes.csv", "trace_decay") == ["1.0"] * n + [""] * (len(full) - n)

    def numbers(records: list[EpisodeRecord]) -> list[EpisodeRecord]:
        return [
            replace(r, wall_time=0.0, diagnostics=replace(r.diagnostics, trace_decay=None))
            for r in records
            if r.diagnostics is not None
        ]

    assert numbers(resumed) == numbers(full) and len(numbers(full)) == len(full)


@pytest.mark.parametrize("name", ["online", "batch"])
def test_committed_episodes_csv_writes_back_byte_for_byte(name: str) -> None:
    """A committed run folder's episodes.csv reads unchanged: written back through
    today's writer, it is the same text."""
    path = FIXTURES / f"run_v0_1_{name}" / "episodes.csv"
    assert records_to_csv(read_records(path)) == path.read_text()


def test_a_batch_run_logs_every_update_and_an_online_run_none(tmp_path: Path) -> None:
    """updates.csv: one row per update (its index, steps, the learner's statistics, wall
    time), as the run's result reported them; none for the online learner."""
    result = train(batch(), tmp_path / "b", progress=False)
    updates = read_updates(tmp_path / "b" / "updates.csv")
    assert [u.update for u in updates] == list(range(result.chunks)) == list(range(4))
    assert [u.total_steps for u in updates] == [64, 128, 192, 256]
    assert updates[-1].values == pytest.approx(result.last_scalars, rel=1e-6)
    wall = [u.wall_time for u in updates]
    assert wall == sorted(wall) and wall[-1] <= result.train_time
    for name in ("approx_kl", "past_threshold", "ratio_dev", "policy_loss"):
        assert all(math.isfinite(u.values[name]) for u in updates)
    train(online(), tmp_path / "o", progress=False)
    assert not (tmp_path / "o" / "updates.csv").exists()


def test_updates_csv_round_trips_and_refuses_mixed_statistics(tmp_path: Path) -> None:
    logged = [
        LoggedUpdate(0, 64, {"approx_kl": 0.01, "lr": 3e-4}, 0.5),
        LoggedUpdate(1, 128, {"approx_kl": float("nan"), "lr": 1.5e-4}, 1.25),
    ]
    RunLogger(tmp_path, tensorboard=False).write_updates(logged)
    back = read_updates(tmp_path / "updates.csv")
    assert (tmp_path / "updates.csv").read_text().splitlines()[0] == (
        "update,total_steps,approx_kl,lr,wall_time"
    )
    assert back[0] == logged[0] and math.isnan(back[1].values["approx_kl"])
    assert back[1].values["lr"] == 1.5e-4 and back[1].wall_time == 1.25
    with pytest.raises(ValueError, match="update 1 reports"):
        updates_to_csv([logged[0], LoggedUpdate(1, 128, {"lr": 1.0}, 1.0)])
    (tmp_path / "bad.csv").write_text("update,total_steps,lr,wall_time\n0,64,x,1.0\n")
    with pytest.raises(ValueError, match=r"bad\.csv cannot be read as an updates\.csv"):
        read_updates(tmp_path / "bad.csv")


def test_a_batch_run_resumed_from_a_checkpoint_without_updates_numbers_them_on(
    tmp_path: Path,
) -> None:
    """A checkpoint written before updates were logged: the resumed run logs the updates
    it makes with their true indices, from the checkpoint's update on."""
    run = tmp_path / "b"
    cfg = batch()
    chunks: list[Any] = []

    def third_update(trainer: Any, report: Any, t: float) -> None:
        chunks.append(report)
        if len(chunks) == 3:  # after the checkpoint of update 2
            raise Interrupted

    with pytest.raises(Interrupted):
        train(cfg, run, progress=False, on_chunk=third_update)
    state = load_checkpoint(run)
    del state["updates"]
    save_checkpoint(run / CHECKPOINT, state)
    train(cfg, run, progress=False)
    assert [u.update for u in read_updates(run / "updates.csv")] == [2, 3]
