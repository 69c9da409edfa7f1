"""The report of a grid of batch runs (issue 40, item 5): its per-run numbers by hand, the
aggregate over tasks against independent computations, and a tiny real grid end to end."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from repo_scripts import docs_generator
from scipy import stats as sps

from pporpe.experiments.grids.reproduce import reproduce
from pporpe.experiments.grids.spec import load_spec
from pporpe.experiments.reports.batch.aggregate import (
    Aggregate,
    PooledImprovement,
    aggregate,
    normalised,
    pooled_improvement,
    task_ranges,
)
from pporpe.experiments.reports.batch.results import (
    BatchCell,
    BatchRun,
    QuarterDiagnostics,
    is_batch_grid,
    last_return,
    quarters_by_steps,
    step_mean_return,
)
from pporpe.experiments.reports.batch.summary import BatchStatistics, Comparison, quarter_rows
from pporpe.experiments.reports.batch.tables import answer_markdown
from pporpe.experiments.reports.report import write_report
from pporpe.experiments.reports.stats import Estimate, iqm, stratified_iqm_ci
from pporpe.experiments.reports.verdicts import short_verdict
from pporpe.experiments.reports.verdicts import verdict as verdict_of
from pporpe.runs.logger import EpisodeRecord, LoggedUpdate

ROOT = Path(__file__).resolve().parents[1]
NAN4 = (math.nan,) * 4


def _records(returns: list[float], lengths: list[int]) -> list[EpisodeRecord]:
    steps = np.cumsum(lengths).tolist()
    return [EpisodeRecord(i, int(s), float(g), int(n), 0.0)
            for i, (g, n, s) in enumerate(zip(returns, lengths, steps, strict=True))]  # fmt: skip


def _update(i: int, steps: int, **values: float) -> LoggedUpdate:
    return LoggedUpdate(i, steps, dict(values), 0.0)


def test_last_100_and_the_mean_over_steps_by_hand() -> None:
    recs = _records([float(g) for g in range(1, 151)], [10] * 150)
    assert last_return(recs) == 100.5  # mean(51..150)
    assert last_return(recs[:40]) == 20.5  # fewer than 100: all of them, mean(1..40)
    assert last_return(recs, episodes=1) == 150.0
    assert math.isnan(last_return([]))
    # Weighted by length: (10 * 1 + 20 * 3) / 4 steps, not the mean of the episodes (15).
    assert step_mean_return(_records([10.0, 20.0], [1, 3])) == 17.5
    assert math.isnan(step_mean_return([]))


def test_quarters_by_steps_by_hand() -> None:
    # 16 updates of 128 steps, the value its index: quarters hold updates 0-3, 4-7, ...
    ups = [_update(i, 128 * (i + 1), past_threshold=float(i)) for i in range(16)]
    assert quarters_by_steps(ups, "past_threshold") == (1.5, 5.5, 9.5, 13.5)
    # Uneven: of 1000 steps, step 250 ends Q1 and 251 starts Q2; 600 is in Q3, 1000 in Q4.
    ups = [_update(0, 250, x=1.0), _update(1, 251, x=2.0), _update(2, 600, x=3.0),
           _update(3, 1000, x=4.0), _update(4, 1000, x=math.nan)]  # fmt: skip
    assert quarters_by_steps(ups, "x") == (1.0, 2.0, 3.0, 4.0)
    got = quarters_by_steps([_update(0, 600, x=3.0), _update(1, 1000, x=5.0)], "x")
    assert math.isnan(got[0]) and math.isnan(got[1]) and got[2:] == (3.0, 5.0)
    assert all(math.isnan(v) for v in quarters_by_steps(ups, "absent"))
    assert all(math.isnan(v) for v in quarters_by_steps([], "x"))


def _run(seed: int, score: float, quarters: QuarterDiagnostics | None = None) -> BatchRun:
    q = quarters or QuarterDiagnostics(NAN4, NAN4, NAN4)
    return BatchRun(seed, score, score, score, (1,), (score,), q)


def _cells(scores: dict[tuple[str, str], list[float]]) -> list[BatchCell]:
    return [BatchCell(env, method, tuple(_run(s, v) for s, v in enumerate(vals)), ())
            for (env, method), vals in scores.items()]  # fmt: skip


RNG = np.random.default_rng(3)
SCORES = {
    (env, method): (RNG.normal(shift, scale, 6) + (40.0 if method == "rpe" else 0.0)).tolist()
    for env, shift, scale in (("a", 0.0, 50.0), ("b", 3000.0, 400.0), ("c", -50.0, 5.0))
    for method in ("ppo", "rb", "rpe")
}


def test_pooled_probability_is_the_mean_of_the_per_task_mann_whitney() -> None:
    cells = _cells(SCORES)
    got = pooled_improvement(cells, "score", "ppo")
    assert got is not None and got.tasks == 3 and got.n == (6, 6) and got.left_out == 0
    per_task = [
        sps.mannwhitneyu(SCORES[(t, "rpe")], SCORES[(t, "ppo")]).statistic / 36 for t in "abc"
    ]
    assert got.p.value == pytest.approx(np.mean(per_task), abs=1e-12)
    # An independent stratified percentile bootstrap (each method's seeds resampled within
    # each task) gives nearly the same interval as the BCa one.
    rng = np.random.default_rng(0)
    boot = []
    for _ in range(4000):
        ps = []
        for t in "abc":
            x = rng.choice(SCORES[(t, "rpe")], 6)
            y = rng.choice(SCORES[(t, "ppo")], 6)
            ps.append(((x[:, None] > y) + 0.5 * (x[:, None] == y)).mean())
        boot.append(np.mean(ps))
    lo, hi = np.percentile(boot, [2.5, 97.5])
    assert got.p.low == pytest.approx(lo, abs=0.06) and got.p.high == pytest.approx(hi, abs=0.06)
    assert got.p.low <= got.p.value <= got.p.high


def test_normalised_iqm_is_invariant_to_an_affine_change_of_a_task() -> None:
    before = aggregate(_cells(SCORES))
    moved = {k: [3.0 * v - 700.0 for v in vals] if k[0] == "b" else vals
             for k, vals in SCORES.items()}  # fmt: skip
    after = aggregate(_cells(moved))
    pairs = [(x.iqm, y.iqm) for x, y in zip(before.iqms, after.iqms, strict=True)]
    pairs += [(x.p, y.p) for x, y in zip(before.improvements, after.improvements, strict=True)]
    assert len(pairs) == 3 * 3 + 3 * 2
    for x, y in pairs:  # the same up to rounding (BCa's interpolation amplifies it)
        assert (x.value, x.low, x.high) == pytest.approx((y.value, y.low, y.high), abs=1e-4)
    # One task: the IQM of the normalised scores is the normalised IQM of the raw ones, and
    # each task's runs span [0, 1] (its worst run 0, its best 1).
    one = _cells({k: v for k, v in SCORES.items() if k[0] == "a"})
    lo, hi = task_ranges(one, "score")["a"]
    assert (lo, hi) == (min(min(v) for k, v in SCORES.items() if k[0] == "a"),
                        max(max(v) for k, v in SCORES.items() if k[0] == "a"))  # fmt: skip
    rpe = next(a for a in aggregate(one).iqms if a.method == "rpe" and a.metric == "score")
    assert rpe.iqm.value == pytest.approx(normalised(float(iqm(np.asarray(SCORES[("a", "rpe")]))),
                                                     lo, hi))  # fmt: skip
    assert normalised(5.0, 5.0, 5.0) == 0.5


def test_stratified_iqm_pools_the_tasks_and_resamples_within_each() -> None:
    est = stratified_iqm_ci([[0.0, 0.1, 0.2, 0.3], [0.6, 0.7, 0.8, 0.9]])
    assert est.value == pytest.approx(iqm(np.asarray([0.0, 0.1, 0.2, 0.3, 0.6, 0.7, 0.8, 0.9])))
    assert 0.0 <= est.low <= est.value <= est.high <= 0.9
    assert stratified_iqm_ci([[0.5], [0.5, 0.5]]) == Estimate(0.5, 0.5, 0.5)
    with pytest.raises(ValueError):
        stratified_iqm_ci([[1.0], []])


def test_verdicts_of_the_pooled_and_per_task_comparisons_at_their_edges() -> None:
    cells = _cells(SCORES)
    base = pooled_improvement(cells, "score", "ppo")
    assert base is not None
    ahead = replace(base, p=Estimate(0.7, 0.5 + 1e-6, 0.9))
    assert ahead.verdict.startswith("supported")
    assert replace(base, p=Estimate(0.7, 0.5, 0.9)).verdict.startswith("cannot tell at 6 seeds")
    assert replace(base, p=Estimate(0.3, 0.1, 0.5 - 1e-6)).verdict.startswith("contradicted")
    assert replace(base, p=Estimate(0.5, 0.37, 0.63)).verdict.startswith("equivalent")
    assert replace(base, p=Estimate(0.5, 0.36, 0.63)).verdict.startswith("cannot tell")
    assert replace(ahead, n=(4, 6)).verdict.startswith("too few seeds (n = 4")
    assert replace(ahead, left_out=2).verdict.endswith(
        ", on the 6 seeds both finished (2 other runs left out)"
    )
    missing = Comparison("score", "a", "rpe", "ppo", (0, 6), 0, None, None)
    assert missing.verdict == "no data"
    # A seed missing on one task of the rival: that task compares the 5 seeds both have.
    partial = [c if (c.env, c.method) != ("b", "ppo") else replace(c, runs=c.runs[1:])
               for c in cells]  # fmt: skip
    got = pooled_improvement(partial, "score", "ppo")
    assert got is not None and got.n == (5, 5) and got.left_out == 1


def test_the_answer_groups_the_tasks_by_verdict_and_adds_the_pooled_one() -> None:
    """The report's answer in words: per claim and rival, the tasks with the same verdict
    together, then the pooled verdict (only over more than one task)."""

    def comp(task: str, low: float, high: float, rival: str = "ppo") -> Comparison:
        return Comparison("score", task, "rpe", rival, (10, 10), 0,
                          Estimate((low + high) / 2, low, high), None)  # fmt: skip

    comparisons = (comp("A", 0.55, 0.9), comp("B", 0.3, 0.7), comp("C", 0.2, 0.7),
                   comp("A", 0.4, 0.6, "rb"))  # fmt: skip
    pooled = (PooledImprovement("score", "rpe", "ppo", 3, (10, 10), 0, Estimate(0.6, 0.52, 0.7)),
              PooledImprovement("score", "rpe", "rb", 1, (10, 10), 0, Estimate(0.5, 0.4, 0.6)))
    stats = BatchStatistics((), comparisons, (), Aggregate((), pooled))
    lines = answer_markdown(stats)
    assert lines[0] == (
        "- **test score**, against PPO: supported on A; cannot tell at 10 seeds on B, C; "
        "pooled over the 3 tasks, supported."
    )
    assert lines[1] == "- **test score**, against PPO-RB: equivalent on A."  # one task: no pool
    assert "Does PPO-RPE beat PPO and PPO-RB" in lines[2]
    assert answer_markdown(BatchStatistics((), (), (), Aggregate((), ()))) == []
    # the short form drops the reason and the seeds left out
    assert short_verdict(verdict_of(0.52, 0.7, (9, 10), left_out=1)) == "supported"
    assert short_verdict(verdict_of(0.3, 0.7, (10, 10))) == "cannot tell at 10 seeds"


def test_the_answer_names_every_rival_of_the_grid() -> None:
    """A fourth method is one more rival: its own lines and its name in the question."""
    comparisons = tuple(
        Comparison("score", "A", "rpe", rival, (10, 10), 0, Estimate(0.5, 0.2, 0.7), None)
        for rival in ("ppo", "rb", "spo")
    )
    lines = answer_markdown(BatchStatistics((), comparisons, (), Aggregate((), ())))
    assert lines[2] == "- **test score**, against SPO: cannot tell at 10 seeds on A."
    assert "Does PPO-RPE beat PPO, PPO-RB and SPO in batch PPO?" in lines[3]
    one = answer_markdown(BatchStatistics((), comparisons[2:], (), Aggregate((), ())))
    assert "Does PPO-RPE beat SPO in batch PPO?" in one[1]


def test_quarter_rows_average_the_seeds() -> None:
    q1 = QuarterDiagnostics((0.1, 0.2, 0.3, 0.4), (1.0,) * 4, (0.01, math.nan, 0.03, 0.04))
    q2 = QuarterDiagnostics((0.3, 0.4, 0.5, 0.6), (3.0,) * 4, (0.03, math.nan, 0.05, 0.06))
    (row,) = quarter_rows([BatchCell("a", "rpe", (_run(0, 1.0, q1), _run(1, 2.0, q2)), ())])
    assert row.past == pytest.approx((0.2, 0.3, 0.4, 0.5)) and row.ratio_dev == (2.0,) * 4
    assert row.approx_kl is not None and math.isnan(row.approx_kl[1])
    assert row.approx_kl[0] == pytest.approx(0.02) and row.method == "PPO-RPE"


TINY_SPEC = """
name = "tinybatch"
kind = "batch"
methods = ["ppo", "rb", "rpe"]
seeds = 2
eval_episodes = 2
checkpoint_every = 100

[learner]
n_envs = 1
n_steps = 64
batch_size = 32
n_epochs = 1
layers = 1
units = 8

[[tasks]]
env = "pendulum"
steps = 512

[[tasks]]
env = "Pendulum-v1"
steps = 640
"""


@pytest.fixture(scope="module")
def tiny_grid(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A real batch grid (3 methods x 2 tasks x 2 seeds, a few hundred steps) and its
    report, in ``results/batch-mujoco`` of a scratch root."""
    root = tmp_path_factory.mktemp("batch")
    (root / "tiny.toml").write_text(TINY_SPEC)
    out = root / "results" / "batch-mujoco"
    assert reproduce(load_spec(root / "tiny.toml"), out, workers=1, progress=False).ok
    write_report(out)
    return root


@pytest.mark.xdist_group("tiny-batch-grid")  # one worker trains it once
def test_a_tiny_batch_grid_reports_by_steps_and_over_tasks(tiny_grid: Path) -> None:
    out = tiny_grid / "results" / "batch-mujoco"
    assert is_batch_grid(out) and not is_batch_grid(ROOT / "results" / "paper")
    report = (out / "REPORT.md").read_text()
    for part in ("(batch PPO)", "## The answer", "against PPO: too few seeds on",
                 "## Over the tasks", "IQM of the normalised values",
                 "P(PPO-RPE > rival), mean over tasks", "## Per task", "last 100 episodes",
                 "mean training return", "approx. KL Q4", "by quarter of steps",
                 "min-max over all the task's finished runs", "pporpe reproduce",
                 "n_steps=64", "too few seeds (n = 2",
                 "![aggregate](fig_aggregate.png)"):  # fmt: skip
        assert part in report, part
    for verdict in ("| supported", "| contradicted", "| equivalent", "| cannot tell"):
        assert verdict not in report  # 2 seeds: no verdict
    for name in ("fig_learning.png", "fig_learning.pdf", "fig_summary.png", "runs.csv",
                 "fig_aggregate.png", "fig_aggregate.pdf", "summary.csv",
                 "summary.md"):  # fmt: skip
        assert (out / name).stat().st_size > 0
    runs = (out / "runs.csv").read_text().splitlines()
    assert runs[0].startswith("task,method,seed,episodes,steps,score,last100,mean_return")
    assert len(runs) == 1 + 12


@pytest.mark.xdist_group("tiny-batch-grid")  # one worker trains it once
def test_the_docs_page_and_readme_rows_of_the_batch_grid(tiny_grid: Path) -> None:
    gen = docs_generator()
    stub = gen.batch_mujoco_page(tiny_grid / "absent")
    assert "Not run yet" in stub
    page = gen.batch_mujoco_page(tiny_grid)
    assert "## Over the tasks" in page and "](../../results/batch-mujoco/fig_learning.png)" in page
    rows = gen.batch_readme_rows(tiny_grid)
    link = "](results/batch-mujoco/REPORT.md)"
    assert [r[0] for r in rows] == [f"[pendulum{link}", f"[Pendulum-v1{link}",
                                    f"[2 tasks, pooled{link}"]  # fmt: skip
    assert all(r[1] == gen.BATCH_LENGTH and r[6].startswith("too few seeds") for r in rows)
    assert [r[2] for r in rows] == ["2", "2", "2"]
    assert rows[-1][3].endswith("(IQM, normalised)")
    sentence = gen.batch_sentence(rows)
    assert sentence.startswith("- In batch PPO, its test score against PPO and PPO-RB: too few")
    assert sentence.endswith("on pendulum, Pendulum-v1; pooled over the 2 tasks, "
                             f"{rows[-1][6]} ([the study](results/batch-mujoco/REPORT.md)).")
    assert gen.batch_sentence(rows[:1]).endswith("on pendulum ([the study]"
                                                 "(results/batch-mujoco/REPORT.md)).")  # fmt: skip


SPO_SPEC = """
name = "tinyspo"
kind = "batch"
methods = ["rpe", "spo"]
seeds = 2
eval_episodes = 1
checkpoint_every = 100

[learner]
n_envs = 1
n_steps = 64
batch_size = 32
n_epochs = 1
layers = 1
units = 8

[[tasks]]
env = "pendulum"
steps = 256
"""


def test_a_batch_grid_with_spo_runs_and_reports_it_as_a_rival(tmp_path: Path) -> None:
    (tmp_path / "spo.toml").write_text(SPO_SPEC)
    spec = load_spec(tmp_path / "spo.toml")
    assert sorted(r.method for r in spec.runs) == ["rpe", "rpe", "spo", "spo"]
    out = tmp_path / "grid"
    assert reproduce(spec, out, workers=1, progress=False).ok
    write_report(out)
    report = (out / "REPORT.md").read_text()
    for part in ("Methods: PPO-RPE, SPO;", "against SPO: too few seeds on pendulum",
                 "Does PPO-RPE beat SPO in batch PPO?", "| pendulum | SPO | 2 |"):  # fmt: skip
        assert part in report, part
    runs = (out / "runs.csv").read_text().splitlines()
    assert sum(line.startswith("pendulum,spo,") for line in runs) == 2
    assert (out / "fig_aggregate.png").stat().st_size > 0
