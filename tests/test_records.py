"""Episode records that fit every learner: what every learner has, and its surrogate
diagnostics as one named extra (batch PPO without a trace decay); episodes.csv and the
checkpoint's records in the form they always had."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
import torch
from interrupt import Interrupted, at_episode
from tiny import tiny_learner

from pporpe.batch import BatchConfig
from pporpe.experiments.results import diagnostic, record_value, update_mean
from pporpe.online.config import TrainConfig
from pporpe.runs import EpisodeRecord, SurrogateDiagnostics, read_records, train
from pporpe.runs.folder import CHECKPOINT, load_checkpoint, save_checkpoint
from pporpe.runs.logger import RunLogger, records_to_csv

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
