"""A step's statistics as one array per step (what the run loop keeps per member) give
the same tensors, and so the same episode diagnostics, as the per-member tensors; a
checkpoint written with the older per-step lists resumes to the same columns."""

from __future__ import annotations

import numpy as np
import torch

from pporpe.online import OnlineConfig, StepStats
from pporpe.online.kind import _columns, _rows, episode_diagnostics


def _random_steps(n: int, K: int, seed: int) -> list[StepStats]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        values = rng.normal(1.0, 0.3, (5, K)).astype(np.float32)
        values[1, 0] = np.float32(np.inf) if rng.random() < 0.1 else values[1, 0]
        out.append(StepStats(*torch.from_numpy(values)))
    return out


def test_table_holds_the_fields_in_order() -> None:
    st = StepStats(*(torch.tensor([i + 0.5, -i], dtype=torch.float32) for i in range(5)))
    table = st.table()
    assert table.dtype == np.float32 and table.shape == (5, 2)
    assert table[:, 0].tolist() == [0.5, 1.5, 2.5, 3.5, 4.5]
    assert table[3, 1] == -3.0


def test_columns_side_by_side_equal_stacked_members() -> None:
    steps = _random_steps(40, K=3, seed=0)
    for k in range(3):
        columns = [s.table()[:, k].copy() for s in steps]
        ours = StepStats.from_table(_rows(columns))
        theirs = StepStats.stack([s.member(k) for s in steps])
        for a, b in zip(ours.__dict__.values(), theirs.__dict__.values(), strict=True):
            assert a.dtype == b.dtype and torch.equal(a.isnan(), b.isnan())
            assert torch.equal(torch.nan_to_num(a), torch.nan_to_num(b))


def test_episode_diagnostics_are_the_same_either_way() -> None:
    steps = _random_steps(200, K=2, seed=1)
    learner = OnlineConfig(method="rpe")
    columns = [s.table()[:, 1].copy() for s in steps]
    ours = episode_diagnostics(StepStats.from_table(_rows(columns)), learner)
    theirs = episode_diagnostics(StepStats.stack([s.member(1) for s in steps]), learner)
    assert ours == theirs


def test_older_checkpoint_steps_resume_to_the_same_columns() -> None:
    steps = _random_steps(7, K=2, seed=2)
    columns = [s.table()[:, 0].copy() for s in steps]
    names = ("delta", "adv", "ratio", "divergence", "trace_decay")
    older = [[getattr(s.member(0), f) for s in steps] for f in names]  # 0-dim tensors
    newer = [torch.from_numpy(row.copy()) for row in _rows(columns)]
    for saved in (older, newer):
        back = _columns(saved)
        assert len(back) == 7 and all(c.dtype == np.float32 for c in back)
        assert all(np.array_equal(a, b) for a, b in zip(back, columns, strict=True))
    assert _columns([[] for _ in names]) == [] and _rows([]).shape == (5, 0)
