"""Stage 1's selection (issue 55, item 3) on synthetic scores worked by hand: the rule's
value of the normalised values pooled over tasks, the winner, a tie (the setting listed
first wins), the runner-up, a setting at the edge of its range, and an unfinished sweep
that selects nothing."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import pytest

from pporpe.experiments.reports.batch.results import METRICS
from pporpe.experiments.reports.sweep.results import (
    SweepCell,
    SweepRun,
    sweep_statistics,
    task_best,
)
from pporpe.experiments.reports.sweep.selection import Candidate, Rule, edges, parse_rule, select
from pporpe.experiments.reports.sweep.sensitivity import (
    lacking_markdown,
    selection_markdown,
    sensitivity_markdown,
    trust_markdown,
)
from pporpe.experiments.sweep_terms import DEFAULT_RULE, RULE_METRICS

EPS = [(("eps", 0.1),), (("eps", 0.2),), (("eps", 0.3),)]

# mean training return of seeds 0 and 1, per (method, eps) and task. Task A spans 0..100,
# task B 10..20, so a value normalises to (x - 0) / 100 on A and (x - 10) / 10 on B.
VALUES = {
    ("ppo", 0.1): {"A": (0.0, 100.0), "B": (10.0, 20.0)},  # 0, 1, 0, 1: IQM 0.5
    ("ppo", 0.2): {"A": (50.0, 50.0), "B": (15.0, 15.0)},  # 0.5 x 4: IQM 0.5, a tie
    ("ppo", 0.3): {"A": (20.0, 40.0), "B": (12.0, 14.0)},  # .2 .4 .2 .4: IQM 0.3
    ("rpe", 0.1): {"A": (10.0, 30.0), "B": (11.0, 13.0)},  # .1 .3 .1 .3: IQM 0.2
    ("rpe", 0.2): {"A": (60.0, 80.0), "B": (16.0, 18.0)},  # .6 .8 .6 .8: IQM 0.7
    ("rpe", 0.3): {"A": (90.0, 70.0), "B": (19.0, 20.0)},  # .9 .7 .9 1.0: IQM 0.9
}
KL = {0.1: 0.01, 0.2: 0.02, 0.3: 0.03}


def run(seed: int, value: float, eps: float) -> SweepRun:
    values = {"score": value, "last100": value, "mean_return": value}
    trust = {"approx_kl": KL[eps], "ratio_dev": 10 * KL[eps], "past_threshold": 0.5}
    return SweepRun(seed, values, trust)


def cells(missing: dict[tuple[str, str, float], int] | None = None) -> list[SweepCell]:
    """The sweep's cells (task, then method, then setting, as a grid.json orders them);
    ``missing``: a seed without a finished run in a cell."""
    out = []
    for env in ("A", "B"):
        for (method, eps), per_task in VALUES.items():
            lost = (missing or {}).get((env, method, eps))
            runs = tuple(run(s, v, eps) for s, v in enumerate(per_task[env]) if s != lost)
            out.append(SweepCell(env, method, (("eps", eps),), runs,
                                 () if lost is None else (lost,)))  # fmt: skip
    return out


def grid(rule: str = "iqm:mean_return") -> dict[str, Any]:
    return {"sweep": {"stage": 1, "select": rule}}


def test_rules_parse_and_bad_ones_name_what_is_allowed() -> None:
    assert parse_rule("iqm:mean_return") == Rule("iqm", "mean_return")
    assert parse_rule("mean:score").metric_name == "test score"
    for bad in ("iqm", "median:score", "iqm:return", "iqm:score:x", 3):
        with pytest.raises(ValueError, match="'<statistic>:<metric>' with a statistic of"):
            parse_rule(bad)
    assert Rule("iqm", "score").value([0.0, 1.0, 2.0, 100.0, math.nan]) == 1.5
    assert Rule("mean", "score").value([0.0, 1.0, 2.0, 9.0]) == 3.0
    assert math.isnan(Rule("iqm", "score").value([math.nan]))


def test_the_pooled_iqm_of_normalised_values_by_hand() -> None:
    stats = sweep_statistics(grid(), cells())
    got = {(p.method, p.setting[0][1]): p.value.value for p in stats.pooled if p.value}
    want = {("ppo", 0.1): 0.5, ("ppo", 0.2): 0.5, ("ppo", 0.3): 0.3,
            ("rpe", 0.1): 0.2, ("rpe", 0.2): 0.7, ("rpe", 0.3): 0.9}  # fmt: skip
    assert got == pytest.approx(want)
    # an independent float64 reference: normalise, pool, drop a quarter at each end, mean
    lo = {"A": 0.0, "B": 10.0}
    span = {"A": 100.0, "B": 10.0}
    for key, per_task in VALUES.items():
        pooled = np.sort([(v - lo[t]) / span[t] for t in "AB" for v in per_task[t]])
        assert got[key] == pytest.approx(float(pooled[1:3].mean()))
    by_mean = sweep_statistics(grid("mean:mean_return"), cells()).pooled
    means = {(p.method, p.setting[0][1]): p.value.value for p in by_mean if p.value}
    assert means[("rpe", 0.3)] == pytest.approx((0.9 + 0.7 + 0.9 + 1.0) / 4)
    for p in stats.pooled:  # the trust region: the mean over the setting's runs
        assert p.trust["approx_kl"] == pytest.approx(KL[p.setting[0][1]]) and p.runs == 4


def test_the_highest_wins_a_tie_goes_to_the_first_listed_and_edges_are_named() -> None:
    stats = sweep_statistics(grid(), cells())
    ppo, rpe = stats.selections["ppo"], stats.selections["rpe"]
    # PPO: eps 0.1 and 0.2 tie at 0.5; eps 0.1 is listed first. It is the smallest eps.
    assert ppo.best.setting == (("eps", 0.1),) and ppo.best.value == pytest.approx(0.5)
    assert ppo.runner_up is not None and ppo.runner_up.setting == (("eps", 0.2),)
    assert [c.setting for c in ppo.tied] == [(("eps", 0.2),)]
    assert ppo.edges == ("eps = 0.1 is the smallest eps swept",)
    # PPO-RPE: eps 0.3 (0.9) ahead of eps 0.2 (0.7); the largest eps swept.
    assert rpe.best.setting == (("eps", 0.3),) and rpe.best.value == pytest.approx(0.9)
    assert rpe.runner_up is not None and rpe.runner_up.value == pytest.approx(0.7)
    assert rpe.tied == () and rpe.edges == ("eps = 0.3 is the largest eps swept",)
    text = "\n".join(selection_markdown(stats, "iqm:mean_return", [0, 1]))
    assert (
        '(`select = "iqm:mean_return"`): the highest IQM, over the tasks, of the min-max '
        "normalised mean training return of the tuning seeds" in text
    )
    assert "| PPO | **eps 0.1** | 0.500 [" in text and "| eps 0.2 | 0.500 [" in text
    assert "| PPO-RPE | **eps 0.3** | 0.900 [" in text
    assert "eps = 0.3 is the largest eps swept |" in text
    assert "- PPO: eps 0.2 ties with the selected eps 0.1 (0.500); the setting listed first" \
        in text  # fmt: skip
    assert "the best may lie beyond the range" in text


def test_the_sensitivity_table_marks_the_selection_and_each_tasks_best() -> None:
    stats = sweep_statistics(grid(), cells())
    assert task_best(stats.cells, "A", "rpe", "mean_return") == (("eps", 0.3),)  # 80 > 70
    assert task_best(stats.cells, "B", "rpe", "mean_return") == (("eps", 0.3),)  # 19.5
    assert task_best(stats.cells, "A", "ppo", "mean_return") == (("eps", 0.1),)  # 50 = 50
    assert task_best(stats.cells, "C", "ppo", "mean_return") is None
    rows = sensitivity_markdown(stats)
    assert rows[0] == "| method | setting | pooled: IQM, normalised [95% CI] | A | B | runs |"
    rpe3 = next(r for r in rows if r.startswith("| PPO-RPE | eps 0.3 (selected)"))
    assert "**80.0 (70.0 to 90.0)**" in rpe3 and "**19.5 (19.0 to 20.0)**" in rpe3
    assert rpe3.endswith("| 4/4 |")
    assert any(r.startswith("| PPO-RPE | eps 0.2 (runner-up) |") for r in rows)
    trust = trust_markdown(stats)
    kls = [r.split(" | ")[3] for r in trust[2:8]]
    assert kls == ["0.01", "0.01", "0.02", "0.02", "0.03", "0.03"]  # sorted by KL


def test_an_unfinished_sweep_selects_nothing_and_counts_what_each_setting_lacks() -> None:
    stats = sweep_statistics(grid(), cells({("A", "rpe", 0.2): 1, ("B", "rpe", 0.2): 0}))
    assert not stats.complete and stats.selections == {}
    lacking = "\n".join(lacking_markdown(stats))
    assert "**Nothing selected**: 2 of 24 runs of the sweep are unfinished" in lacking
    assert "| PPO-RPE | eps 0.2 | 2 | 2 |" in lacking
    assert "| PPO | eps 0.1 |" not in lacking  # a finished setting is not listed


def test_select_on_bare_candidates() -> None:
    def cands(*values: float) -> list[Candidate]:
        return [Candidate((("eps", 0.1 * (i + 1)),), v, 2) for i, v in enumerate(values)]

    got = select("ppo", cands(0.5, 0.7, 0.7 + 1e-14, math.nan, 0.2))
    assert got is not None and got.best.value == 0.7 and got.runner_up is not None
    assert got.runner_up.value == 0.7 + 1e-14 and len(got.tied) == 1  # equal to 1e-12
    got = select("ppo", cands(0.5, 0.7 + 1e-14, 0.7))  # the first listed, not the last bit
    assert got is not None and got.best.value == 0.7 + 1e-14 and len(got.tied) == 1
    got = select("ppo", cands(0.5, 0.6, 0.9))
    assert got is not None and got.best.value == 0.9 and got.tied == ()
    assert got.runner_up is not None and got.runner_up.value == 0.6
    alone = select("ppo", cands(0.4))
    assert alone is not None and alone.runner_up is None and alone.edges == ()
    assert select("ppo", cands(math.nan, math.nan)) is None


def test_edges_of_numeric_fields_swept_over_two_values_or_more() -> None:
    grid8 = [Candidate((("eps", e), ("lr", lr), ("act", "tanh")), 0.0, 1)
             for e in (0.1, 0.2, 0.3, 0.5) for lr in (3e-4, 1e-3)]  # fmt: skip
    top = (("eps", 0.5), ("lr", 3e-4), ("act", "tanh"))
    assert edges(top, grid8) == ("eps = 0.5 is the largest eps swept",
                                 "lr = 0.0003 is the smallest lr swept")  # fmt: skip
    assert edges((("eps", 0.2), ("lr", 1e-3), ("act", "tanh")), grid8) == (
        "lr = 0.001 is the largest lr swept",
    )
    single = [Candidate((("eps", 0.2),), 0.0, 1)]
    assert edges((("eps", 0.2),), single) == ()


def test_spo_is_named_spo_in_a_sweeps_tables() -> None:
    """A sweep of SPO (PPO's cells under its name) reports it as SPO, as every report does
    (``METHOD_LABELS``), in the selection, the sensitivity and the trust-region tables."""
    spo = [dataclasses.replace(c, method="spo") if c.method == "ppo" else c for c in cells()]
    stats = sweep_statistics(grid(), spo)
    assert set(stats.selections) == {"spo", "rpe"}
    text = "\n".join(selection_markdown(stats, "iqm:mean_return", [0, 1]))
    assert "| SPO | **eps 0.1** | 0.500 [" in text and "| spo |" not in text
    assert any(r.startswith("| SPO | eps 0.1 (selected)") for r in sensitivity_markdown(stats))
    assert any(r.startswith("| SPO |") for r in trust_markdown(stats))


def test_the_rules_metrics_are_the_batch_reports_numbers() -> None:
    """The words a spec's rule may use (checked on the grids' side, which cannot import the
    reports) are the keys of the numbers the reports compute per run."""
    assert RULE_METRICS == tuple(m.key for m in METRICS)
    assert DEFAULT_RULE == "iqm:mean_return" and parse_rule(DEFAULT_RULE).metric in RULE_METRICS
