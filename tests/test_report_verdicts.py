"""The report's verdicts (issue 39 item 3, issue 41 item 2), the mean difference beside P,
and the surrogate diagnostics by quarter of training (issue 39 item 4)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from pporpe.experiments.reports.online.claims import claims_markdown
from pporpe.experiments.reports.online.summary import improvement_rows, quarter_rows
from pporpe.experiments.reports.report import write_report
from pporpe.experiments.reports.results import Cell, load_results, quarter_means
from pporpe.experiments.reports.stats import (
    mean_difference,
    mean_difference_ci,
    probability_of_improvement_ci,
)
from pporpe.experiments.reports.tables import quarter_markdown
from pporpe.experiments.reports.verdicts import (
    EQUIVALENCE_BOUNDS,
    MIN_SEEDS,
    SETTLE_CAP,
    seeds_to_settle,
    settle_text,
    short_verdict,
    verdict,
)
from pporpe.runs.kinds import SurrogateDiagnostics
from pporpe.runs.logger import EpisodeRecord, records_to_csv

TEN = (10, 10)


# --- verdict() on CIs ------------------------------------------------------------------


def test_each_verdict_from_its_interval() -> None:
    assert verdict(0.55, 0.90, TEN) == "supported (PPO-RPE ahead)"
    assert verdict(0.10, 0.45, TEN) == "contradicted (PPO-RPE behind)"
    assert verdict(0.40, 0.60, TEN).startswith("equivalent (")
    assert verdict(0.30, 0.60, TEN).startswith("cannot tell at 10 seeds (")
    assert verdict(0.40, 0.70, TEN).startswith("cannot tell at 10 seeds (")
    # Above 0.5 and inside the bounds: ahead, by less than a medium effect.
    assert verdict(0.52, 0.60, TEN) == "supported (PPO-RPE ahead, by less than a medium effect)"
    assert verdict(0.40, 0.48, TEN) == "contradicted (PPO-RPE behind, by less than a medium effect)"
    assert verdict(math.nan, math.nan, (0, 10)) == "no data"


def test_a_ci_that_touches_a_bound_is_not_past_it() -> None:
    low, high = EQUIVALENCE_BOUNDS
    assert (low, high) == (0.36, 0.64)
    # With 10 seeds each P is a multiple of 1/100 (ties: 1/200), and so are the bootstrap's
    # ends: 36/100 and 64/100 are the bounds themselves.
    assert verdict(36 / 100, 0.60, TEN).startswith("cannot tell")
    assert verdict(0.40, 64 / 100, TEN).startswith("cannot tell")
    assert verdict(0.40, 0.64 - 1e-12, TEN).startswith("cannot tell")  # float rounding
    assert verdict(0.3601, 0.6399, TEN).startswith("equivalent")
    # 0.5 is a bound too: a CI starting at 0.5 is not above it.
    assert verdict(0.50, 0.90, TEN).startswith("cannot tell")
    assert verdict(0.10, 0.50, TEN).startswith("cannot tell")
    assert verdict(0.5 + 1e-6, 0.90, TEN).startswith("supported")


# --- seeds_to_settle(): the projection beside "cannot tell" ----------------------------


def test_seeds_to_settle_by_hand() -> None:
    # P 0.61 [0.34, 0.84] at 10 seeds: the lower arm 0.27 must shrink below 0.61 - 0.5 = 0.11,
    # 10 * (0.27 / 0.11)**2 = 60.25 seeds, so 61; equivalence needs the upper arm 0.23 below
    # 0.64 - 0.61 = 0.03, 10 * (0.23 / 0.03)**2 = 587.8 seeds: clearing 0.5 comes first.
    assert seeds_to_settle(0.61, 0.34, 0.84, 10) == (61, "supported")
    # P 0.53 [0.25, 0.79]: above 0.5 needs 10 * (0.28 / 0.03)**2 = 871.1; equivalence needs
    # max(10 * (0.28 / 0.17)**2, 10 * (0.26 / 0.11)**2) = max(27.1, 55.9): 56 seeds.
    assert seeds_to_settle(0.53, 0.25, 0.79, 10) == (56, "equivalent")
    # Exactly 0.5: only equivalence can come, 10 * (0.2 / 0.14)**2 = 20.4 -> 21.
    assert seeds_to_settle(0.5, 0.3, 0.7, 10) == (21, "equivalent")
    # Outside the bounds: no equivalence; below 0.5, contradicted. 10 * (0.2 / 0.2)**2 = 10,
    # and a CI that only touches 0.5 is not past it: 11.
    assert seeds_to_settle(0.3, 0.1, 0.5, 10) == (11, "contradicted")
    # A tie: 10 * (0.2 / 0.07)**2 = 81.6 seeds both clear 0.5 and fit the upper arm inside
    # 0.64; verdict() then reads "supported (..., by less than a medium effect)".
    assert seeds_to_settle(0.57, 0.37, 0.77, 10) == (82, "supported")
    assert seeds_to_settle(0.43, 0.23, 0.63, 10) == (82, "contradicted")
    assert settle_text(0.61, 0.34, 0.84, 10) == "about 61 (supported)"
    # P 0.505 [0.05, 0.95] at 100 seeds: equivalence needs 100 * (0.445 / 0.135)**2 = 1086.6.
    assert settle_text(0.505, 0.05, 0.95, 100) == f"over {SETTLE_CAP} (equivalent)"


def test_nothing_to_settle_where_a_verdict_is_given() -> None:
    assert seeds_to_settle(0.7, 0.55, 0.90, 10) is None  # supported
    assert seeds_to_settle(0.2, 0.10, 0.45, 10) is None  # contradicted
    assert seeds_to_settle(0.5, 0.40, 0.60, 10) is None  # equivalent
    assert seeds_to_settle(0.6, 0.30, 0.90, 4) is None  # too few seeds for any verdict
    assert seeds_to_settle(math.nan, math.nan, math.nan, 10) is None
    assert settle_text(0.7, 0.55, 0.90, 10) == "-"


def _scaled_verdict(value: float, low: float, high: float, n: int, m: int) -> str:
    """The verdict of the CI at ``m`` seeds with its arms scaled by sqrt(n / m)."""
    s = math.sqrt(n / m)
    return short_verdict(verdict(value - s * (value - low), value + s * (high - value), (m, m)))


def test_seeds_to_settle_against_a_search_over_seeds() -> None:
    # An independent reference: scale the CI's arms seed count by seed count and ask verdict()
    # itself; the projection is the first count with a verdict, and that verdict.
    rng = np.random.default_rng(3)
    checked = 0
    while checked < 2000:
        value = rng.uniform(0.2, 0.8)
        low, high = value - rng.uniform(0.05, 0.4), value + rng.uniform(0.05, 0.4)
        n = int(rng.integers(5, 40))
        got = seeds_to_settle(value, low, high, n)
        if not short_verdict(verdict(low, high, (n, n))).startswith("cannot tell"):
            assert got is None
            continue
        m = n + 1
        while _scaled_verdict(value, low, high, n, m).startswith("cannot tell"):
            m += 1
        assert got == (m, _scaled_verdict(value, low, high, n, m))
        checked += 1


def test_seeds_to_settle_is_symmetric_about_one_half() -> None:
    # Swapping the two methods maps P to 1 - P and [low, high] to [1 - high, 1 - low]:
    # the same seeds, supported and contradicted exchanged.
    swap = {"supported": "contradicted", "contradicted": "supported", "equivalent": "equivalent"}
    cases = ((0.61, 0.34, 0.84), (0.53, 0.25, 0.79), (0.7, 0.45, 0.9), (0.57, 0.37, 0.77))
    for value, low, high in cases:
        seeds, said = seeds_to_settle(value, low, high, 10) or (0, "")
        assert seeds_to_settle(1 - value, 1 - high, 1 - low, 10) == (seeds, swap[said])


def test_no_verdict_from_too_few_seeds_and_seeds_left_out_are_said() -> None:
    assert MIN_SEEDS == 5
    assert verdict(1.0, 1.0, (1, 1)) == "too few seeds (n = 1; a verdict needs 5)"
    assert verdict(0.9, 1.0, (10, 4)).startswith("too few seeds (n = 4;")
    assert verdict(0.9, 1.0, (5, 5)) == "supported (PPO-RPE ahead)"
    assert verdict(0.9, 1.0, TEN, left_out=3) == (
        "supported (PPO-RPE ahead), on the 10 seeds both finished (3 other runs left out)"
    )
    assert verdict(0.4, 0.6, TEN, left_out=1).startswith("equivalent (")


# --- verdicts on constructed data --------------------------------------------------------


def verdict_of(x: list[float], y: list[float]) -> str:
    est = probability_of_improvement_ci(x, y)
    return verdict(est.low, est.high, (len(x), len(y)))


def test_each_verdict_on_constructed_scores() -> None:
    low_half, high_half = [float(v) for v in range(10)], [float(v) for v in range(10, 20)]
    assert verdict_of(high_half, low_half) == "supported (PPO-RPE ahead)"  # P = 1 [1, 1]
    assert verdict_of(low_half, high_half) == "contradicted (PPO-RPE behind)"
    # Interleaved at 10 seeds: P = 0.45, a CI far wider than the bounds.
    evens, odds = [2.0 * k for k in range(10)], [2.0 * k + 1 for k in range(10)]
    assert verdict_of(evens, odds).startswith("cannot tell at 10 seeds")
    # The same 40 spread values for both: P = 0.5 and a CI inside the bounds.
    spread = np.round(np.linspace(0.0, 10.0, 40), 1).tolist()
    same = probability_of_improvement_ci(spread, spread)
    assert same.value == 0.5 and 0.36 < same.low < 0.5 < same.high < 0.64
    assert verdict_of(spread, spread).startswith("equivalent")
    # Every seed tied: the CI is the point 0.5, inside the bounds.
    assert verdict_of([3.0] * 5, [3.0] * 5).startswith("equivalent")


def test_the_edge_on_constructed_scores() -> None:
    # 40 seeds each; the rival 0.2 lower. The bootstrap's upper end is exactly 0.64
    # (1024 of the 1600 pairs): it touches the bound, so no equivalence.
    values = np.round(np.linspace(0.0, 10.0, 40), 1)
    x = values.tolist()
    est = probability_of_improvement_ci(x, np.round(values - 0.2, 1).tolist())
    assert est.high == 0.64 and 0.36 < est.low < 0.5
    assert verdict(est.low, est.high, (40, 40)).startswith("cannot tell at 40 seeds")
    # 0.1 lower: the CI stays clear of 0.64.
    near = probability_of_improvement_ci(x, np.round(values - 0.1, 1).tolist())
    assert 0.36 < near.low and near.high < 0.64
    assert verdict(near.low, near.high, (40, 40)).startswith("equivalent")


# --- the mean difference ------------------------------------------------------------------


def test_mean_difference_and_its_interval() -> None:
    # By hand: mean(1, 2, 6) = 3, mean(0, 1) = 0.5.
    assert mean_difference(np.array([1.0, 2.0, 6.0]), np.array([0.0, 1.0])) == 2.5
    assert mean_difference_ci([1.0, 2.0, 6.0], [0.0, 1.0]).value == 2.5
    # Degenerate: one value, or each sample constant: the interval is the point.
    point = {"value": 2.0, "low": 2.0, "high": 2.0}
    assert mean_difference_ci([4.0], [1.0, 3.0]).as_dict() == point
    assert mean_difference_ci([4.0, 4.0], [1.0, 1.0, 1.0]).low == 3.0
    rng = np.random.default_rng(3)
    x, y = rng.normal(1.0, 1.0, 12), rng.normal(0.0, 2.0, 9)
    got = mean_difference_ci(x.tolist(), y.tolist())
    # scipy's BCa with the same generator seed, statistic written out here.
    ref = stats.bootstrap((x, y), lambda a, b, axis: a.mean(axis) - b.mean(axis),
                          n_resamples=10_000, method="BCa",
                          rng=np.random.default_rng(0)).confidence_interval  # fmt: skip
    assert (got.low, got.high) == pytest.approx((ref.low, ref.high))
    assert got.value == pytest.approx(x.mean() - y.mean())
    # Independent of the bootstrap: with many seeds it agrees with Welch's t interval.
    x, y = rng.normal(1.0, 1.0, 300), rng.normal(0.0, 2.0, 300)
    welch = stats.ttest_ind(x, y, equal_var=False).confidence_interval(0.95)
    big = mean_difference_ci(x.tolist(), y.tolist())
    assert (big.low, big.high) == pytest.approx((welch.low, welch.high), abs=0.03)
    with pytest.raises(ValueError, match="non-empty 1-D"):
        mean_difference_ci([], [1.0])


# --- partial grids -------------------------------------------------------------------------


def write_grid(root: Path, scores: dict[str, dict[int, float]], unfinished: int = 0) -> None:
    """A grid folder of one task (pendulum): per method, finished runs with these per-seed
    scores (60 training episodes, first-50 return = the score / 10) and ``unfinished`` more
    runs per method without a done.json."""
    runs = []
    for method, by_seed in scores.items():
        seeds = [*by_seed, *range(100, 100 + unfinished)]
        for seed in seeds:
            key = f"pendulum/{method}/seed{seed}"
            (root / key).mkdir(parents=True)
            runs.append({"key": key, "method": method, "env": "pendulum", "seed": seed,
                         "config": {"env": "pendulum", "seed": seed, "episodes": 60}})  # fmt: skip
            if seed not in by_seed:
                continue
            score = by_seed[seed]
            reg = 0.1 * score
            records = [
                EpisodeRecord(e, 10 * (e + 1), score / 10, 10, float(e),
                              SurrogateDiagnostics(reg, 0.01, 0.02, 0.5))
                for e in range(60)
            ]  # fmt: skip
            (root / key / "episodes.csv").write_text(records_to_csv(records))
            (root / key / "evaluation.json").write_text(json.dumps({"median": score}))
            (root / key / "done.json").write_text("{}")
    (root / "grid.json").write_text(json.dumps({"name": "partial", "runs": runs}))


def claim_rows(root: Path) -> list[str]:
    return [
        line for line in claims_markdown(load_results(root)).splitlines()
        if line.startswith("| final performance |")
    ]  # fmt: skip


def test_partial_grid_one_seed_per_method_has_no_verdict(tmp_path: Path) -> None:
    # 3 of 30 runs: one seed of each method finished, PPO-RPE's best.
    write_grid(tmp_path, {"ppo": {0: 10.0}, "rb": {0: 20.0}, "rpe": {0: 30.0}}, unfinished=9)
    rows = claim_rows(tmp_path)
    assert len(rows) == 2
    for row in rows:
        assert "| 1.00 (1 seed, no CI) |" in row  # P itself is still shown, without a CI
        assert row.endswith("| too few seeds (n = 1; a verdict needs 5) | - |")
        assert "supported" not in row
    # The mean difference beside P: 30 - 10 and 30 - 20.
    assert "| 20.0 (1 seed, no CI) |" in rows[0] and "| 10.0 (1 seed, no CI) |" in rows[1]


def test_a_partial_grid_compares_the_seeds_both_methods_finished(tmp_path: Path) -> None:
    rpe = {s: 100.0 + s for s in range(6)}  # seeds 0-5
    ppo = {s: float(s) for s in (0, 1, 2, 3, 4, 7)}  # seeds 0-4 and 7
    write_grid(tmp_path, {"ppo": ppo, "rpe": rpe})
    (row,) = claim_rows(tmp_path)
    (imp,) = improvement_rows(load_results(tmp_path))
    assert imp["score_seeds"] == ((0, 1, 2, 3, 4), (0, 1, 2, 3, 4))
    assert imp["score_n"] == (5, 5) and imp["score_left_out"] == 2  # rpe's 5, ppo's 7
    # On seeds 0-4: P = 1, mean difference mean(100..104) - mean(0..4) = 100.
    assert "| 1.00 [1.00, 1.00] | 100.0 [" in row
    assert row.endswith(  # and no seeds to settle a verdict given
        "| supported (PPO-RPE ahead), on the 5 seeds both finished (2 other runs left out) "
        "| - |"
    )
    # The same seeds: the verdict alone, nothing left out.
    del ppo[7]
    ppo[5] = 5.0
    other = tmp_path / "same"
    other.mkdir()
    write_grid(other, {"ppo": ppo, "rpe": rpe})
    (row,) = claim_rows(other)
    # Mean difference by hand: mean(100..105) - mean(0..5) = 100.
    assert "| 1.00 [1.00, 1.00] | 100.0 [" in row
    assert row.endswith("| supported (PPO-RPE ahead) | - |")


# --- where the surrogates act --------------------------------------------------------------


def episodes(lengths: list[int], past: list[float], dev: list[float]) -> list[EpisodeRecord]:
    return [
        EpisodeRecord(e, 0, 0.0, n, 0.0, SurrogateDiagnostics(0.0, p, d))
        for e, (n, p, d) in enumerate(zip(lengths, past, dev, strict=True))
    ]


# Seed 0: 8 episodes, two per quarter. Weighted by length (updates):
#   Q1 (10 * 0.1 + 30 * 0) / 40 = 0.025; Q2 (20 * 0.05 + 20 * 0.15) / 40 = 0.1;
#   Q3 (5 * 0.2 + 15 * 0) / 20 = 0.05;  Q4 (40 * 0.01) / 40 = 0.01 (a 0-step episode has no
#   update). abs(rho - 1) is twice the share, episode by episode.
SEED0 = episodes([10, 30, 20, 20, 5, 15, 40, 0], [0.1, 0.0, 0.05, 0.15, 0.2, 0.0, 0.01, 0.5],
                 [0.2, 0.0, 0.1, 0.3, 0.4, 0.0, 0.02, 1.0])  # fmt: skip
# Seed 1: 6 episodes of 10 steps; quarters [0:1], [1:3], [3:4], [4:6]:
#   Q1 0.3; Q2 (0.1 + 0.2) / 2 = 0.15; Q3 0.0; Q4 (0.04 + 0.06) / 2 = 0.05.
SEED1 = episodes([10] * 6, [0.3, 0.1, 0.2, 0.0, 0.04, 0.06], [0.6, 0.2, 0.4, 0.0, 0.08, 0.12])


def test_quarter_means_by_hand() -> None:
    assert quarter_means(SEED0, "past_threshold") == pytest.approx((0.025, 0.1, 0.05, 0.01))
    assert quarter_means(SEED0, "ratio_dev") == pytest.approx((0.05, 0.2, 0.1, 0.02))
    assert quarter_means(SEED1, "past_threshold") == pytest.approx((0.3, 0.15, 0.0, 0.05))
    # Three episodes: quarters [0:0], [0:1], [1:2], [2:3]; the first is empty.
    q = quarter_means(SEED1[:3], "past_threshold")
    assert math.isnan(q[0]) and q[1:] == pytest.approx((0.3, 0.1, 0.2))


def test_quarter_table_averages_over_seeds() -> None:
    cells = [Cell("pendulum", "rpe", {}, {0: SEED0, 1: SEED1}, []),
             Cell("pendulum", "ppo", {}, {0: SEED1[:3]}, [1])]  # fmt: skip
    rpe, ppo = quarter_rows(cells)
    # Means over the two seeds: (0.025 + 0.3) / 2, (0.1 + 0.15) / 2, (0.05 + 0) / 2, ...
    assert rpe.past == pytest.approx((0.1625, 0.125, 0.025, 0.03))
    assert rpe.ratio_dev == pytest.approx((0.325, 0.25, 0.05, 0.06))
    assert (rpe.method, rpe.seeds, ppo.seeds) == ("PPO-RPE", 2, 1)
    lines = quarter_markdown([rpe, ppo])
    assert lines[0].count("|") == 11
    assert lines[2] == (
        "| pendulum | PPO-RPE | 16.25 | 12.50 | 2.50 | 3.00 | 32.50 | 25.00 | 5.00 | 6.00 |"
    )
    # One seed of 3 episodes: no first quarter.
    assert lines[3] == (
        "| pendulum | PPO | n/a | 30.00 | 10.00 | 20.00 | n/a | 60.00 | 20.00 | 40.00 |"
    )


def test_report_has_the_new_tables(tmp_path: Path) -> None:
    write_grid(tmp_path, {"ppo": {s: float(s) for s in range(5)},
                          "rpe": {s: 10.0 + s for s in range(5)}})  # fmt: skip
    write_report(tmp_path)
    report = (tmp_path / "REPORT.md").read_text()
    quarters = "| 1.00 | 1.00 | 1.00 | 1.00 | 2.00 | 2.00 | 2.00 | 2.00 |"
    assert f"| pendulum | PPO-RPE {quarters}" in report and f"| pendulum | PPO {quarters}" in report
    # Regularisation 0.1 * score: mean(1.0 .. 1.4) - mean(0 .. 0.4) = 1.
    assert "| regularisation | pendulum | PPO | 1.00 [1.00, 1.00] | 1.0000 [" in report
    assert "strictly inside 0.36-0.64" in report
    assert "| verdict | seeds to settle it |" in report and "**Seeds to settle it**" in report
