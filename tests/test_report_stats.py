"""The report's statistics against hand computations on a small fixture (issue 11)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from pporpe.experiments.reports.report import write_report
from pporpe.experiments.reports.results import load_results
from pporpe.experiments.reports.stats import (
    average_probability_of_improvement_ci,
    bootstrap_ci,
    iqm,
    probability_of_improvement,
    probability_of_improvement_ci,
)
from pporpe.runs.kinds import SurrogateDiagnostics
from pporpe.runs.logger import EpisodeRecord, records_to_csv

# Four seeds per method: scores (median test return), the return of every one of the
# first 50 training episodes, and the regularisation amount of every episode.
SCORES = {"rpe": [10.0, 20.0, 30.0, 100.0], "ppo": [0.0, 5.0, 40.0, 50.0]}
EARLY = {"rpe": [1.0, 2.0, 3.0, 4.0], "ppo": [1.0, 1.0, 1.0, 1.0]}
REG = {"rpe": [0.2, 0.3, 0.4, 0.5], "ppo": [0.0, 0.0, 0.1, 0.1]}
# Per method, (first 50 episodes, last 10) of the share of updates past the threshold and of
# mean abs(rho - 1). The first 50 episodes have 10 steps, the last 10 have 40: weighted by
# updates, ppo's share is 400 * 0.09 / 900 = 4%, rpe's 500 * 0.009 / 900 = 0.5%, and the
# mean abs(rho - 1) is 500 * 0.018 / 900 = 1% (ppo) and 400 * 0.0045 / 900 = 0.2% (rpe).
PAST = {"ppo": (0.0, 0.09), "rpe": (0.009, 0.0)}
RATIO_DEV = {"ppo": (0.018, 0.0), "rpe": (0.0, 0.0045)}


def test_hand_worked_statistics() -> None:
    # IQM: scipy trims int(0.25 n) from each end.
    assert iqm(np.arange(1.0, 9.0)) == 4.5  # mean(3, 4, 5, 6)
    assert iqm(np.arange(1.0, 11.0)) == 5.5  # mean(3..8)
    assert iqm(np.asarray(SCORES["rpe"])) == 25.0  # mean(20, 30)
    # P(X > Y) + P(X = Y)/2 over all 4 pairs: 3>1, 3=3 (half), 4>1, 4>3.
    assert probability_of_improvement([3.0, 4.0], [1.0, 3.0]) == 0.875
    # rpe vs ppo: 10 and 20 and 30 beat 2 each, 100 beats 4: 10 of 16 pairs.
    assert probability_of_improvement(SCORES["rpe"], SCORES["ppo"]) == 0.625
    assert probability_of_improvement([1.0], [1.0]) == 0.5
    assert probability_of_improvement(SCORES["ppo"], SCORES["rpe"]) == 1 - 0.625


def test_intervals_are_scipys_bootstrap_and_degenerate_cases_are_points() -> None:
    data = np.asarray([3.0, 1.0, 4.0, 1.0, 5.0, 9.0, 2.0, 6.0, 5.0, 3.0])
    est = bootstrap_ci(list(data))
    ref = stats.bootstrap((data,), np.mean, n_resamples=10_000, method="BCa",
                          rng=np.random.default_rng(0)).confidence_interval  # fmt: skip
    assert (est.value, est.low, est.high) == (data.mean(), ref.low, ref.high)
    assert est.low < est.value < est.high
    assert bootstrap_ci([7.0, 7.0, 7.0]).as_dict() == {"value": 7.0, "low": 7.0, "high": 7.0}
    assert bootstrap_ci([7.0]).low == 7.0
    poi = probability_of_improvement_ci(SCORES["rpe"], SCORES["ppo"])
    assert poi.value == 0.625 and 0.0 <= poi.low <= 0.625 <= poi.high <= 1.0
    assert probability_of_improvement_ci([2.0, 2.0], [2.0, 2.0]).as_dict()["high"] == 0.5
    # Separated samples: every resample says X is ahead.
    far = probability_of_improvement_ci([10.0, 11.0, 12.0], [0.0, 1.0, 2.0])
    assert (far.value, far.low, far.high) == (1.0, 1.0, 1.0)
    with pytest.raises(ValueError, match="non-empty 1-D"):
        bootstrap_ci([])


def test_average_probability_of_improvement_over_tasks() -> None:
    # By hand: task 1 P = 0.625 (above), task 2 every X below every Y (P = 0): mean 0.3125.
    pairs = [(SCORES["rpe"], SCORES["ppo"]), ([0.0, 1.0, 2.0], [5.0, 6.0])]
    est = average_probability_of_improvement_ci(pairs)
    assert est.value == pytest.approx(0.3125)
    assert 0.0 <= est.low <= est.value <= est.high <= 0.5  # task 2 is 0 in every resample
    # Each task weighs the same, whatever its seeds: not the pooled 36-pair statistic.
    pooled = probability_of_improvement(SCORES["rpe"] + [0.0, 1.0, 2.0], SCORES["ppo"] + [5.0, 6.0])
    assert est.value != pytest.approx(pooled)
    # One task is probability_of_improvement_ci itself, interval included.
    one = average_probability_of_improvement_ci([(SCORES["rpe"], SCORES["ppo"])])
    assert one.as_dict() == probability_of_improvement_ci(SCORES["rpe"], SCORES["ppo"]).as_dict()
    # An independent float64 reference of the interval: scipy's BCa over four samples.
    rng = np.random.default_rng(7)
    data = [rng.normal(m, 1.0, 10) for m in (0.5, 0.0, 0.0, 0.2)]

    def reference(
        a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray, axis: int
    ) -> np.ndarray:
        p1 = (a[..., :, None] > b[..., None, :]) + 0.5 * (a[..., :, None] == b[..., None, :])
        p2 = (c[..., :, None] > d[..., None, :]) + 0.5 * (c[..., :, None] == d[..., None, :])
        return (p1.mean(axis=(-1, -2)) + p2.mean(axis=(-1, -2))) / 2

    ref = stats.bootstrap(tuple(data), reference, n_resamples=10_000, method="BCa",
                          rng=np.random.default_rng(0)).confidence_interval  # fmt: skip
    got = average_probability_of_improvement_ci([(data[0], data[1]), (data[2], data[3])])
    assert (got.low, got.high) == pytest.approx((ref.low, ref.high))
    assert got.value == pytest.approx(float(reference(*data, axis=-1)))
    with pytest.raises(ValueError, match="one \\(x, y\\) pair"):
        average_probability_of_improvement_ci([([1.0], [])])
    with pytest.raises(ValueError, match="one \\(x, y\\) pair"):
        average_probability_of_improvement_ci([])


def write_fixture(root: Path) -> None:
    runs = []
    for method in ("ppo", "rpe"):
        for seed in range(4):
            key = f"pendulum/{method}/seed{seed}"
            run = root / key
            run.mkdir(parents=True)
            records = [
                EpisodeRecord(
                    episode=e,
                    total_steps=10 * (e + 1),
                    ret=EARLY[method][seed] if e < 50 else 1000.0,  # later episodes differ
                    length=10 if e < 50 else 40,
                    wall_time=float(e),
                    diagnostics=SurrogateDiagnostics(
                        reg_amount=REG[method][seed],
                        past_threshold=PAST[method][e >= 50],
                        ratio_dev=RATIO_DEV[method][e >= 50],
                        trace_decay=0.5,
                    ),
                )
                for e in range(60)
            ]
            (run / "episodes.csv").write_text(records_to_csv(records))
            (run / "evaluation.json").write_text(
                json.dumps({"median": SCORES[method][seed], "returns": [SCORES[method][seed]]})
            )
            (run / "done.json").write_text("{}")
            config = {"env": "pendulum", "seed": seed, "episodes": 60}
            runs.append({"key": key, "method": method, "env": "pendulum", "seed": seed,
                         "config": config})  # fmt: skip
    (root / "grid.json").write_text(json.dumps({"name": "fixture", "runs": runs}))


def test_report_tables_and_verdicts_match_hand_computation(tmp_path: Path) -> None:
    write_fixture(tmp_path)
    assert {c.method: sorted(c.scores.values()) for c in load_results(tmp_path)} == {
        m: sorted(v) for m, v in SCORES.items()
    }
    write_report(tmp_path)
    summary = (tmp_path / "summary.md").read_text()
    report = (tmp_path / "REPORT.md").read_text()
    rpe_row = next(line for line in summary.splitlines() if line.startswith("| pendulum | PPO-RPE"))
    cells = [c.strip() for c in rpe_row.split("|")[1:-1]]
    assert cells[2] == "4"
    assert cells[3].startswith("40.0 [")  # mean(10, 20, 30, 100)
    assert cells[4].startswith("25.0 [")  # IQM: mean(20, 30)
    assert cells[5].startswith("2.5 [")  # first 50 episodes: mean(1, 2, 3, 4)
    assert cells[6].startswith("0.350 [")  # regularisation: mean(0.2 .. 0.5)
    ppo_row = next(line for line in summary.splitlines() if line.startswith("| pendulum | PPO |"))
    assert "| 1.0 [1.0, 1.0] |" in ppo_row  # every PPO seed's first 50 returns are 1
    # Updates past the threshold and abs(rho - 1), in %, weighted by updates (all seeds equal).
    moves = [line for line in summary.splitlines() if line.count("|") == 5]
    assert "| pendulum | PPO | 4.00 [4.00, 4.00] | 1.00 [1.00, 1.00] |" in moves
    assert "| pendulum | PPO-RPE | 0.50 [0.50, 0.50] | 0.20 [0.20, 0.20] |" in moves
    poi_row = next(line for line in summary.splitlines() if "| vs PPO |" in line)
    poi = [c.strip() for c in poi_row.split("|")[1:-1]]
    assert poi[2].startswith("0.62 [")  # 10 of 16 pairs
    # first 50: 1 ties all 4 of PPO's (2 halves), 2, 3, 4 beat all: (2 + 12) / 16
    assert poi[3].startswith("0.88 [")
    assert poi[4].startswith("1.00 [1.00, 1.00]")  # every rpe reg > every ppo reg
    # Four seeds: below the minimum for a verdict (tests/test_report_verdicts.py has more).
    # Mean difference of the regularisation: 0.35 - mean(0, 0, 0.1, 0.1) = 0.3.
    reg_row = next(line for line in report.splitlines() if line.startswith("| regularisation"))
    assert reg_row.startswith("| regularisation | pendulum | PPO | 1.00 [1.00, 1.00] | 0.3000 [")
    assert reg_row.endswith("| too few seeds (n = 4; a verdict needs 5) | - |")
    assert "| final performance | pendulum | PPO | 0.62 [" in report
    assert "supported" not in report.split("The paper's claims")[1].split("Verdicts, from")[0]
    ran = "- pendulum: 60 training episodes per run, 8/8 runs finished; episodes run per"
    assert f"{ran} finished run: 60-60" in report
    (tmp_path / "notes.md").write_text("Hand-written context.")
    write_report(tmp_path)
    assert "Hand-written context." in (tmp_path / "REPORT.md").read_text()


def test_what_ran_names_a_batch_grids_step_budget(tmp_path: Path) -> None:
    write_fixture(tmp_path)
    grid = json.loads((tmp_path / "grid.json").read_text())
    for run in grid["runs"]:  # batch runs: their budget is total_steps
        run["config"] = {"env": "pendulum", "seed": run["seed"], "total_steps": 4096}
    (tmp_path / "grid.json").write_text(json.dumps(grid))
    write_report(tmp_path)
    assert (
        "- pendulum: 4096 training steps per run, 8/8 runs finished"
        in (tmp_path / "REPORT.md").read_text()
    )


def test_the_compute_line_sums_what_the_finished_runs_record(tmp_path: Path) -> None:
    """CPU hours of training and of the test episodes, summed over the
    finished runs whose done.json records CPU time; the others counted apart; no line
    when none records it (an older grid's report is unchanged)."""
    from pporpe.experiments.reports.results import compute_line

    runs = [{"key": f"t/ppo/seed{i}"} for i in range(4)]
    grid = {"runs": runs}
    done = [
        {"cpu_time": 3600.0, "eval_cpu_time": 360.0, "train_time": 7200.0},
        {"cpu_time": 1800.0, "eval_cpu_time": 0.0, "train_time": 1800.0, "cpu_time_since": 4},
        {"train_time": 900.0},  # finished before CPU time was recorded
    ]  # the fourth run has not finished
    assert compute_line(tmp_path, grid) is None
    for run, d in zip(runs, done, strict=False):
        (tmp_path / run["key"]).mkdir(parents=True)
        (tmp_path / run["key"] / "done.json").write_text(json.dumps(d))
    line = compute_line(tmp_path, grid)
    assert line is not None
    assert line.startswith("- Compute: 1.60 CPU hours over the 2 finished runs that record it")
    assert "(1.50 training, 0.10 test episodes; 1 of these runs" in line
    assert "; 1 of these runs counted from a resume part-way" in line
    assert "; 1 other finished run without the record)" in line
    assert compute_line(tmp_path, {"runs": runs[2:]}) is None


def test_a_row_of_one_seed_shows_its_value_without_an_interval() -> None:
    """The bootstrap of one value is that value: ``[x, x]`` would read as certainty, so a
    row of one seed (a method's, or a comparison where either method has one) gives the
    value alone; two seeds and rows without a seed count keep their interval, NaN stays
    n/a."""
    from pporpe.experiments.reports.tables import fmt_ci

    one = {"seeds": 1, "boot_value": 806.6, "boot_low": 806.6, "boot_high": 806.6}
    assert fmt_ci(one, "boot") == "806.6 (1 seed, no CI)"
    two = {**one, "seeds": 2, "boot_low": 504.0, "boot_high": 807.0}
    assert fmt_ci(two, "boot") == "806.6 [504.0, 807.0]"
    p = {"score_value": 0.5, "score_low": 0.25, "score_high": 0.75}
    assert fmt_ci(p, "score", 2) == "0.50 [0.25, 0.75]"  # no count of seeds: as it is
    compared = {**p, "score_n": (2, 3), "score_diff_value": 4.0, "score_diff_low": -1.0,
                "score_diff_high": 9.0}  # fmt: skip
    assert fmt_ci(compared, "score_diff") == "4.0 [-1.0, 9.0]"
    alone = {**compared, "score_n": (1, 3), "score_diff_low": 4.0, "score_diff_high": 4.0}
    assert fmt_ci(alone, "score", 2) == "0.50 (1 seed, no CI)"
    assert fmt_ci(alone, "score_diff") == "4.0 (1 seed, no CI)"
    assert fmt_ci({"seeds": 1, "past_value": 0.0006, "past_low": 0.0006,
                   "past_high": 0.0006}, "past", 2, 100.0) == "0.06 (1 seed, no CI)"  # fmt: skip
    assert fmt_ci({**one, "boot_value": float("nan")}, "boot") == "n/a"


def test_a_fourth_method_gets_its_rows_rival_column_and_legend(tmp_path: Path) -> None:
    """SPO's runs (here a copy of PPO's) appear as a method of their own: rows, a rival
    of PPO-RPE, and a fourth surrogate in the legend; a grid without it keeps the text."""
    import shutil

    write_fixture(tmp_path / "three")
    write_report(tmp_path / "three")
    legend = (
        "How much the three surrogates can differ: the share of a run's updates whose ratio "
        "rho was past the threshold (where PPO's clip, PPO-RB's rollback or PPO-RPE's "
        "stronger pull act)"
    )
    assert legend in (tmp_path / "three" / "summary.md").read_text()
    root = tmp_path / "four"
    write_fixture(root)
    grid = json.loads((root / "grid.json").read_text())
    for run in [r for r in grid["runs"] if r["method"] == "ppo"]:
        key = run["key"].replace("/ppo/", "/spo/")
        shutil.copytree(root / run["key"], root / key)
        grid["runs"].append({**run, "key": key, "method": "spo"})
    (root / "grid.json").write_text(json.dumps(grid))
    write_report(root)
    summary = (root / "summary.md").read_text()
    assert "| pendulum | SPO | 4.00 [4.00, 4.00] | 1.00 [1.00, 1.00] |" in summary
    spo_row = next(line for line in summary.splitlines() if "| vs SPO |" in line)
    ppo_row = next(line for line in summary.splitlines() if "| vs PPO |" in line)
    assert spo_row.replace("SPO", "PPO") == ppo_row  # the same numbers: the same runs
    assert (
        "How much the four surrogates can differ: the share of a run's updates whose ratio "
        "rho was past the threshold (where PPO's clip, PPO-RB's rollback, PPO-RPE's "
        "stronger pull or SPO's reversed gradient act)"
    ) in summary
    assert "| final performance | pendulum | SPO | 0.62 [" in (root / "REPORT.md").read_text()


def test_probability_of_improvement_is_the_pair_count_bit_for_bit_over_resamples() -> None:
    """Vectorised over a leading axis (as the bootstrap calls it), against a plain count of
    the pairs: the same float, bit for bit, with ties (scores rounded to one decimal)."""
    rng = np.random.default_rng(5)
    x = np.round(rng.normal(size=(200, 7)), 1)
    y = np.round(rng.normal(size=(200, 4)), 1)
    got = probability_of_improvement(x, y)
    for row, (a, b) in enumerate(zip(x, y, strict=True)):
        pairs = [1.0 if u > v else 0.5 if u == v else 0.0 for u in a for v in b]
        assert got[row] == sum(pairs) / len(pairs)
    assert got.shape == (200,) and np.any(got != np.round(got))
