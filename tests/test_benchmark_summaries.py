"""The summaries the benchmarks print: hand-worked cases, no training."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import ablation  # noqa: E402
import pendulum_behaviour  # noqa: E402
import test_suite  # noqa: E402

import pporpe.online  # noqa: E402


def _row(variant: str, method: str, scores: list[float]) -> dict[str, Any]:
    return {"variant": variant, "task": "swingup", "method": method, "scores": scores}


def test_versus_pools_the_three_methods_and_skips_incomplete_variants() -> None:
    rows = [_row("baseline", m, [1.0, 3.0]) for m in ablation.METHODS]  # 6 runs: 1,1,1,3,3,3
    rows += [_row("amsgrad", m, [2.0]) for m in ablation.METHODS]  # 3 runs of 2
    rows += [_row("critic", m, [5.0]) for m in ("ppo", "rb")]  # PPO-RPE not finished
    table = ablation.versus(rows, "baseline")
    assert [(v["variant"], v["runs"], v["reference_runs"]) for v in table] == [("amsgrad", 3, 6)]
    # 2 beats each 1 and loses to each 3: P = (3 * 3) / (3 * 6) = 0.5
    assert table[0]["p_above"]["value"] == pytest.approx(0.5)
    against_amsgrad = ablation.versus(rows, "amsgrad")
    assert [v["variant"] for v in against_amsgrad] == ["baseline"]
    assert against_amsgrad[0]["p_above"]["value"] == pytest.approx(0.5)
    rows += [_row("trace_kl", m, [4.0, 4.0]) for m in ablation.METHODS]  # above every baseline run
    top = {v["variant"]: v["p_above"]["value"] for v in ablation.versus(rows, "baseline")}
    assert top == {"amsgrad": pytest.approx(0.5), "trace_kl": pytest.approx(1.0)}
    assert ablation.versus(rows, "all") == []  # no reference runs: nothing to compare


def test_versus_both_averages_the_tasks_and_needs_every_method_on_both() -> None:
    def row(variant: str, task: str, method: str, scores: list[float]) -> dict[str, Any]:
        return {"variant": variant, "task": task, "method": method, "scores": scores}

    rows = [row("baseline", t, m, [1.0]) for t in ablation.THRESHOLD for m in ablation.METHODS]
    # amsgrad beats the baseline on pendulum (P = 1) and loses on swingup (P = 0): 0.5
    rows += [row("amsgrad", "pendulum", m, [2.0, 3.0]) for m in ablation.METHODS]
    rows += [row("amsgrad", "swingup", m, [0.0]) for m in ablation.METHODS]
    rows += [row("critic", "pendulum", m, [5.0]) for m in ablation.METHODS]  # no swingup
    (entry,) = ablation.versus_both(rows, "baseline")
    assert entry["variant"] == "amsgrad" and entry["tasks"] == ["pendulum", "swingup"]
    assert entry["p_above"]["value"] == pytest.approx(0.5)
    assert (entry["runs"], entry["reference_runs"]) == ([6, 3], [3, 3])
    assert ablation.versus_both(rows, "critic") == []  # the reference lacks a task


def test_all_but_entropy_is_the_authors_choices_with_the_bounded_actions_density() -> None:
    expected = {**pporpe.online.AUTHOR_CHOICES, "entropy_density": "action"}
    assert ablation.VARIANTS["all_but_entropy"] == expected
    # pporpe 0.4's defaults: the author's choices but the critic signal and the density
    defaults = ablation.variant_settings("trace_kl+layer_norm+amsgrad+td_units")
    assert defaults == dict(pporpe.online.DEFAULT_CHOICES)
    assert {k for k in defaults if defaults[k] != pporpe.online.AUTHOR_CHOICES[k]} == {
        "critic_signal",
        "entropy_density",
    }
    assert pporpe.online.BASELINE_CHOICES["entropy_density"] == "action"
    assert ablation.VARIANTS["critic"] == {
        **pporpe.online.BASELINE_CHOICES,
        **ablation.AUTHOR["critic"],
    }


def test_a_combination_of_changes_is_the_baseline_with_those_changes() -> None:
    settings = ablation.variant_settings("amsgrad+td_units")
    assert settings == {
        **pporpe.online.BASELINE_CHOICES,
        "amsgrad_max": "raw",
        "amsgrad_decay": 0.99999,
        "td_units": "unscaled",
    }
    assert settings["critic_signal"] == "td"  # the changes not named keep pporpe 0.2's choice
    # every change joined is all six, and a named variant is itself
    assert ablation.variant_settings("+".join(ablation.AUTHOR)) == ablation.VARIANTS["all"]
    assert ablation.variant_settings("critic") == ablation.VARIANTS["critic"]
    assert ablation.canonical("trace_kl+amsgrad") == "amsgrad+trace_kl"  # one folder per set
    assert ablation.canonical("critic") == "critic"
    for bad in ("amsgrad+nope", "amsgrad+amsgrad", "nope", "amsgrad+"):
        with pytest.raises(ValueError, match=r"variant must be one of .* joined by '\+'"):
            ablation.variant_settings(bad)


def test_the_test_beds_weights_are_its_weight_and_balance_per_term() -> None:
    """The test bed folds both regularisers into its TD error with one weight w = 0.1 and
    a balance b = 0.5: reward (1 - gamma)(1 - w b) r, then + (1 - gamma) w b times
    -(b delta_raw^2 + (1 - b) log pi). pporpe's signal is delta - (1 - gamma)(beta_TD
    delta_raw^2 + beta_DE log pi), so beta_TD = w b b and beta_DE = w b (1 - b)."""
    w, b, gamma = 0.1, 0.5, 0.99
    weights = ablation.TESTBED["weights"]
    assert weights["beta_td"] == pytest.approx(w * b * b)
    assert weights["beta_de"] == pytest.approx(w * b * (1 - b))
    assert weights["reward_scale"] == pytest.approx((1 - gamma) * (1 - w * b))
    # a diagnostic change combines like the author's, after them in the folder name, and
    # leaves "all" the author's six
    name = ablation.canonical("weights+trace_kl+td_units+amsgrad+layer_norm")
    assert name == "td_units+amsgrad+layer_norm+trace_kl+weights"
    assert ablation.variant_settings(name) == {**pporpe.online.DEFAULT_CHOICES, **weights}
    assert ablation.VARIANTS["all"] == dict(pporpe.online.AUTHOR_CHOICES)
    assert "weights" not in ablation.VARIANTS and "lr_width" not in ablation.VARIANTS
    config = pporpe.online.OnlineConfig(**ablation.variant_settings("amsgrad+lr_width"))
    assert (config.lr, config.units, config.beta_td) == (1e-4, 128, 0.01)


def test_a_combinations_runs_are_summarised_from_disk(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    source = ROOT / "benchmarks" / "results" / "ablation"
    combo = "amsgrad+trace_kl"
    for variant, copy_as in (("baseline", "baseline"), ("amsgrad", combo)):
        for method in ablation.METHODS:
            run = Path("pendulum") / method / "seed0"
            shutil.copytree(source / variant / run, tmp_path / copy_as / run)
    (tmp_path / "not+a+variant").mkdir()  # a stray folder is not a variant
    (tmp_path / "trace_kl+amsgrad").mkdir()  # nor one in another order
    out, md = tmp_path / "ablation.json", tmp_path / "ablation.md"
    argv = ["ablation.py", "--summarize", "--variants", combo, "--tasks", "pendulum"]
    monkeypatch.setattr(
        sys, "argv", [*argv, "--out", str(tmp_path), "--json", str(out), "--markdown", str(md)]
    )
    ablation.main()
    payload = json.loads(out.read_text())
    assert payload["variants"][combo] == ablation.variant_settings(combo)
    assert set(payload["variants"]) == {*ablation.VARIANTS, combo}
    assert {r["variant"] for r in payload["rows"]} == {"baseline", combo}
    (entry,) = payload["versus"]["baseline"]
    assert (entry["variant"], entry["runs"]) == (combo, 3)
    assert combo in capsys.readouterr().out
    assert f"| {combo} | " in md.read_text()
    monkeypatch.setattr(sys, "argv", ["ablation.py", "--variants", "amsgrad+nope"])
    with pytest.raises(SystemExit):
        ablation.main()
    assert "variant must be one of" in capsys.readouterr().err


def test_markdown_tables_by_hand() -> None:
    def row(variant: str, method: str, task: str, mean: float, reaching: int) -> dict[str, Any]:
        ci = {"value": mean, "low": mean - 10.4, "high": mean + 20.6}
        return {"variant": variant, "task": task, "method": method, "seeds": 10,
                "mean": ci, "seeds_reaching": reaching}  # fmt: skip

    rows = [row("baseline", m, "swingup", 300.0, 1) for m in ablation.METHODS]
    rows += [row("amsgrad", m, "swingup", 450.2, 3) for m in ("ppo", "rb")]
    p = {"value": 0.583, "low": 0.4249, "high": 0.7251}
    comparisons = {
        "baseline": [{"variant": "amsgrad", "task": "swingup", "p_above": p}],
        "all": [],
    }
    both = {"baseline": [{"variant": "amsgrad", "p_above": {**p, "value": 0.61}}], "all": []}
    text = ablation.markdown(rows, comparisons, both)
    lines = text.splitlines()
    # the summary: both tasks on one line per variant, a task not run says so
    assert lines[2] == "| baseline | not run |  | 300 / 300 / 300 (1/10, 1/10, 1/10) |  |  |  |"
    assert lines[3] == (
        "| amsgrad | not run |  | 450 / 450 / - (3/10, 3/10, -) | 0.58 [0.42, 0.73] | "
        "0.61 [0.42, 0.73] |  |"
    )
    lines = lines[5:]
    assert lines[0] == "Swingup (mean score [95% CI], seeds >= 800):"  # no pendulum rows
    assert "| baseline | 300 [290, 321], 1/10 | 300 [290, 321], 1/10 |" in text
    assert lines[-1] == "| amsgrad | 450 [440, 471], 3/10 | 450 [440, 471], 3/10 | not run | " \
        "0.58 [0.42, 0.73] |  |"  # fmt: skip
    assert text.endswith("|\n")


def test_a_chunks_summary_json_keeps_every_variant_on_disk(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    source = ROOT / "benchmarks" / "results" / "ablation"
    for variant in ("baseline", "amsgrad"):
        for method in ablation.METHODS:
            run = Path(variant) / "pendulum" / method / "seed0"
            shutil.copytree(source / run, tmp_path / run)
    out, md = tmp_path / "ablation.json", tmp_path / "ablation.md"
    argv = ["ablation.py", "--summarize", "--variants", "amsgrad", "--tasks", "pendulum"]
    monkeypatch.setattr(
        sys, "argv", [*argv, "--out", str(tmp_path), "--json", str(out), "--markdown", str(md)]
    )
    ablation.main()
    payload = json.loads(out.read_text())
    assert {(r["variant"], r["method"]) for r in payload["rows"]} == {
        (v, m) for v in ("baseline", "amsgrad") for m in ablation.METHODS
    }
    (entry,) = payload["versus"]["baseline"]
    assert (entry["variant"], entry["runs"], entry["reference_runs"]) == ("amsgrad", 3, 3)
    printed = capsys.readouterr().out
    assert "amsgrad " in printed and "baseline " not in printed.split("P(variant")[0]


def test_versus_names_the_references_and_refuses_an_unknown_one(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    source = ROOT / "benchmarks" / "results" / "ablation"
    for variant in ("baseline", "amsgrad"):
        for method in ablation.METHODS:
            run = Path(variant) / "pendulum" / method / "seed0"
            shutil.copytree(source / run, tmp_path / run)
    out, md = tmp_path / "ablation.json", tmp_path / "ablation.md"
    files = ["--out", str(tmp_path), "--json", str(out), "--markdown", str(md)]
    argv = ["ablation.py", "--summarize", "--variants", "baseline", "--tasks", "pendulum"]
    monkeypatch.setattr(sys, "argv", [*argv, *files])
    ablation.main()  # the default references: baseline, all and the optimiser change alone
    payload = json.loads(out.read_text())
    assert list(payload["versus"]) == list(ablation.REFERENCES)
    (entry,) = payload["versus"]["amsgrad"]
    assert (entry["variant"], entry["task"], entry["runs"]) == ("baseline", "pendulum", 3)
    rows = ablation.summarize(tmp_path, ["baseline", "amsgrad"], ["pendulum"])
    assert entry["p_above"] == ablation.versus(rows, "amsgrad")[0]["p_above"]
    assert "P(variant > amsgrad)" in capsys.readouterr().out
    monkeypatch.setattr(sys, "argv", [*argv, *files, "--versus", "amsgrad"])
    ablation.main()
    assert list(json.loads(out.read_text())["versus"]) == ["amsgrad"]
    monkeypatch.setattr(sys, "argv", [*argv, *files, "--versus", "nope"])
    with pytest.raises(SystemExit):
        ablation.main()
    assert "variant must be one of" in capsys.readouterr().err


def test_episode_stats_by_hand() -> None:
    # Four steps: the first half hangs down, the second half is upright (0 and 0.1 rad).
    angles = np.array([np.pi, -np.pi + 0.1, 0.0, 0.1])
    actions = np.array([1.0, 1.0, 0.96, 0.5])
    stats = pendulum_behaviour.episode_stats(angles, actions, ret=1.5)
    assert stats["upright"] == 1.0  # cos(0) and cos(0.1) are above 0.9
    assert stats["mean_abs_action"] == pytest.approx(0.73)  # (0.96 + 0.5) / 2
    assert stats["saturated"] == 0.5  # 0.96 is past 0.95, 0.5 is not
    assert stats["return"] == 1.5 and stats["length"] == 4
    # Unwrapped, theta runs pi, pi + 0.1, 2 pi, 2 pi + 0.1: a net (pi + 0.1) / (2 pi) turn.
    assert stats["turns"] == pytest.approx((np.pi + 0.1) / (2 * np.pi))
    spin = np.angle(np.exp(1j * np.linspace(0.0, 4 * np.pi, 401)))  # two turns, wrapped
    assert pendulum_behaviour.episode_stats(spin, np.zeros(401), 0.0)["turns"] == pytest.approx(2)


def test_find_runs_checks_every_task_before_any_episode(tmp_path: Path) -> None:
    paper = ROOT / "results" / "paper"
    for task, seed in (("swingup", 0), ("halfcheetah", 1)):
        run = tmp_path / task / f"seed{seed}"
        run.mkdir(parents=True)
        shutil.copy(paper / task / "rpe" / f"seed{seed}" / "config.json", run / "config.json")
        (run / "done.json").write_text(json.dumps({"total_steps": 1}))
    assert pendulum_behaviour.find_runs([tmp_path / "swingup"]) == [tmp_path / "swingup/seed0"]
    with pytest.raises(ValueError, match=r"env must be one of \('pendulum', 'swingup'\)"):
        pendulum_behaviour.find_runs([tmp_path])
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no finished run folder"):
        pendulum_behaviour.find_runs([tmp_path / "empty"])


def test_merged_keeps_the_groups_this_call_does_not_measure() -> None:
    previous = {
        "command": "python old.py",
        "groups": [{"group": "v/swingup/ppo", "runs": 2}, {"group": "w/swingup/ppo", "runs": 1}],
        "runs": [
            {"run": "v/swingup/ppo/seed0"},
            {"run": "v/swingup/ppo/seed1"},
            {"run": "w/swingup/ppo/seed0"},
        ],
    }
    groups = [{"group": "w/swingup/ppo", "command": "python new.py", "runs": 1}]
    rows = [{"run": "w/swingup/ppo/seed0", "upright": 0.5}]
    got_groups, got_rows = pendulum_behaviour.merged(previous, groups, rows)
    assert got_groups == [
        {"command": "python old.py", "group": "v/swingup/ppo", "runs": 2},  # kept, its command
        groups[0],  # re-measured: the new one replaces the old
    ]
    assert [r["run"] for r in got_rows] == [
        "v/swingup/ppo/seed0",
        "v/swingup/ppo/seed1",
        "w/swingup/ppo/seed0",
    ]
    assert got_rows[-1] == rows[0]


def test_merge_refuses_a_file_measured_with_other_settings(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "behaviour.json"
    out.write_text(json.dumps({"episodes": 3, "groups": [], "runs": []}))  # no seed: the default
    argv = ["pendulum_behaviour.py", str(tmp_path), "--json", str(out), "--merge"]
    monkeypatch.setattr(sys, "argv", [*argv, "--episodes", "2"])
    with pytest.raises(SystemExit):
        pendulum_behaviour.main()
    err = capsys.readouterr().err
    assert "was measured with --episodes 3 --seed 10000; got --episodes 2 --seed 10000" in err
    assert json.loads(out.read_text())["episodes"] == 3  # untouched


def _tables(text: str) -> list[str]:
    """The Markdown table rows of a text, their indentation stripped, in order."""
    return [line.strip() for line in text.splitlines() if line.strip().startswith("|")]


def test_committed_ablation_tables_are_the_committed_runs_and_the_docs_page_shows_them(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """benchmarks/results/ablation.md is what --summarize writes from the committed run
    folders today, and the generated docs page docs/results/ablation.md shows every one of
    its tables, in order: a run added or a table edited by hand without the other fails
    here (``python docs/generate.py`` rewrites the page)."""
    md, runs = tmp_path / "ablation.md", ROOT / "benchmarks" / "results" / "ablation"
    argv = ["ablation.py", "--summarize", "--out", str(runs), "--json", str(tmp_path / "a.json")]
    monkeypatch.setattr(sys, "argv", [*argv, "--markdown", str(md)])
    ablation.main()
    capsys.readouterr()
    recomputed = _tables(md.read_text())
    committed = _tables((ROOT / "benchmarks" / "results" / "ablation.md").read_text())
    assert recomputed == committed
    per_task = "| variant | PPO | PPO-RB | PPO-RPE | P(> baseline) | P(> all) |"
    summary = committed[: committed.index(per_task)]
    finished = {row["variant"] for row in json.loads((tmp_path / "a.json").read_text())["rows"]}
    in_order = [v for v in ablation.variants_on_disk(runs) if v in finished]
    assert [row.split(" | ")[0].removeprefix("| ") for row in summary[2:]] == in_order
    page = _tables((ROOT / "docs" / "results" / "ablation.md").read_text())
    start = page.index(summary[0])
    assert page[start : start + len(committed)] == committed
    assert summary[0] not in _tables((ROOT / "README.md").read_text())  # a front page now


def _testbed_modules() -> tuple[Any, Any]:
    import testbed
    import testbed_worker

    return testbed, testbed_worker


def test_testbed_paper_settings_are_what_the_test_beds_constructor_receives() -> None:
    """pporpe's ``paper`` settings follow from the arguments the reference worker passes to
    the test bed's AC: per-term weights w b^2 and w b (1 - b), reward (1 - gamma)(1 - w b)."""
    testbed, worker = _testbed_modules()
    ac = worker.CONFIGS["paper"]
    ours = testbed.settings_for("paper")
    w, b, gamma = ac["reg_weight"], ac["reg_balance"], ours["gamma"]
    assert ours["beta_td"] == pytest.approx(w * b * b)
    assert ours["beta_de"] == pytest.approx(w * b * (1 - b))
    assert ours["beta_td"] == pytest.approx(0.01)  # the paper's Table I
    assert ours["reward_scale"] == pytest.approx((1 - gamma) * (1 - w * b))
    assert ours["lr"] == ac["opt_params"]["lr"]
    assert [ours["units"]] * ours["layers"] == ac["fc_params"]["h_dims"]
    assert ours["lambdas"] == (ac["lambda1"], ac["lambda2"])
    assert ours["kappa"] == ac["div_weight"] and ours["eps"] == ac["ppo_threshold"]
    tb = worker.CONFIGS["testbed"]
    own = testbed.settings_for("testbed")
    assert own["lambdas"] == (tb["lambda1"], tb["lambda2"]) and own["kappa"] == tb["div_weight"]


def test_testbed_config_names_canonical_and_refused() -> None:
    testbed, _ = _testbed_modules()
    assert testbed.canonical_config("testbed+width+lr") == "testbed+lr+width"
    s = testbed.settings_for("testbed+traces+clip")
    assert (s["lambdas"], s["kappa"], s["policy_gradient"]) == ((0.5, 0.95), 10.0, "surrogate")
    assert s["lr"] == 1e-4  # untouched groups keep the test bed's values
    for bad in ("testbed+lr+lr", "paper+lr", "testbed+speed", "tb"):
        with pytest.raises(ValueError, match="config must be"):
            testbed.settings_for(bad)


def test_testbed_pporpe_configs_of_one_shape_share_a_population(tmp_path: Path) -> None:
    """Several --config values: the 128-unit ones form one group (one population), the
    width group its own; every run has its folder under its config, its seed and its
    settings."""
    testbed, _ = _testbed_modules()
    args = testbed.build_parser().parse_args(
        ["pporpe", "--task", "swingup", "--config", "testbed+lr", "testbed+width",
         "testbed+target", "--seeds", "1", "2", "--root", str(tmp_path)]
    )  # fmt: skip
    groups = testbed.pporpe_groups(args)
    assert [configs for configs, _ in groups] == [["testbed+lr", "testbed+target"],
                                                   ["testbed+width"]]  # fmt: skip
    shared, width = groups[0][1], groups[1][1]
    assert [Path(d).relative_to(tmp_path / "pporpe_runs").parts[0] for d, _ in shared] == [
        "testbed+lr",
        "testbed+lr",
        "testbed+target",
        "testbed+target",
    ]
    assert {Path(d).name for d, _ in width} == {"seed1", "seed2"}
    lrs = [cfg["learner"]["lr"] for _, cfg in shared]
    taus = [cfg["learner"]["tau"] for _, cfg in shared]
    assert lrs == [3e-4, 3e-4, 1e-4, 1e-4] and taus == [1.0, 1.0, 0.3, 0.3]
    assert {cfg["learner"]["units"] for _, cfg in width} == {100}
    with pytest.raises(SystemExit):  # argparse names the option and what it allows
        testbed.build_parser().parse_args(
            ["pporpe", "--task", "swingup", "--config", "testbed+speed", "--seeds", "1"]
        )


def test_testbed_summary_from_result_files(tmp_path: Path) -> None:
    """Hand-made result files: the first-50 mean, the median score, P(pporpe > test bed)
    and the episodes whose bands are apart."""
    testbed, _ = _testbed_modules()
    env = testbed.TASKS["pendulum"]
    for impl, offset in (("pporpe", 0.0), ("testbed", 1000.0)):
        for seed in (1, 2, 3):
            returns = [offset + seed + e for e in range(60)]
            path = testbed.result_path(impl, "testbed", "pendulum", seed, tmp_path)
            path.parent.mkdir(parents=True, exist_ok=True)
            data = {"env": env, "seed": seed, "config": "testbed", "returns": returns,
                    "test_returns": [offset + seed, 0.0, offset + 2 * seed]}  # fmt: skip
            path.write_text(json.dumps(data))
    records = testbed.load_results(tmp_path)
    assert len(records) == 6
    first = testbed.select(records, implementation="pporpe", seed=2)[0]
    assert first["first50_mean"] == pytest.approx(2 + 24.5) and first["score"] == 2.0
    row = testbed.side_by_side(records, "pendulum", "testbed")
    assert row["p_pporpe_better_score"]["value"] == 0.0  # the test bed ahead in every pair
    assert row["bands"]["apart"] == list(range(1, 61))
    assert testbed.side_by_side(records, "pendulum", "paper") is None


def test_testbed_path_rows_compare_each_config_with_the_baseline_of_its_engine() -> None:
    """A config run by the fused engine is held to testbed+fused, testbed+fused to the
    torch engine's testbed (the engine check), a torch config to testbed."""
    testbed, _ = _testbed_modules()
    assert testbed.settings_for("testbed")["engine"] == "torch"
    assert testbed.settings_for("testbed+lr+fused")["engine"] == "fused"
    assert testbed.baseline_of("testbed+lr+fused") == "testbed+fused"
    assert testbed.baseline_of("testbed+fused") == testbed.baseline_of("testbed+lr") == "testbed"
    score = {"testbed": 0.0, "testbed+lr": 1.0, "testbed+fused": 5.0, "testbed+lr+fused": 2.0}
    records = [
        {"implementation": "pporpe", "task": "swingup", "config": c, "seed": seed,
         "first50_mean": 0.0, "score": s + 0.1 * seed}
        for c, s in score.items() for seed in range(3)
    ]  # fmt: skip
    rows = {r["config"]: r for r in testbed.path_rows(records, "swingup")}
    assert "p_better_than_testbed" not in rows["testbed"]
    assert rows["testbed+lr"]["p_better_than_testbed"]["value"] == 1.0  # above testbed
    assert rows["testbed+fused"]["p_better_than_testbed"]["value"] == 1.0  # above testbed
    # below testbed+fused, though above the torch engine's testbed
    assert rows["testbed+lr+fused"]["baseline"] == "testbed+fused"
    assert rows["testbed+lr+fused"]["p_better_than_testbed"]["value"] == 0.0


def _engine_shadow() -> Any:
    import engine_shadow

    return engine_shadow


def test_engine_shadow_discrepancy_by_hand() -> None:
    """Two members of a [2, K, 1, 2] buffer and a [K] scalar: the change and the
    discrepancy in units of the larger of the two engines' sizes after the step."""
    import torch

    es = _engine_shadow()
    before = {"params": torch.zeros(2, 2, 1, 2), "decay": torch.tensor([1.0, 0.5])}
    fused = {"params": before["params"].clone(), "decay": torch.tensor([0.5, 0.5])}
    fused["params"][0, 0, 0] = torch.tensor([1.0, -2.0])  # member 0 moved, member 1 not
    torch_ = {"params": fused["params"].clone(), "decay": torch.tensor([0.25, 0.5])}
    torch_["params"][1, 0, 0, 1] = 4.0  # the torch engine moved one more element
    out = es.change_discrepancy(before, fused, torch_)
    np.testing.assert_allclose(out["params"][:, 0], [2.0 / 4.0, 4.0 / 4.0])
    np.testing.assert_allclose(out["params"][:, 1], [0.0, 0.0])
    np.testing.assert_allclose(out["decay"][:, 0], [0.5 / 0.5, 0.25 / 0.5])
    np.testing.assert_allclose(out["decay"][:, 1], [0.0, 0.0])


def test_engine_shadow_agrees_to_rounding_on_its_first_steps() -> None:
    """The fused engine and the torch engine fed its state, step by step for 40 steps of
    the test bed's learner on InvertedPendulum: parameters' discrepancy at float32
    rounding of their size (rarely 1e-5, where rounding flips the sign of a trace
    element near 0), far below the step's change, and the same ratio."""
    es = _engine_shadow()
    run = es.Shadowed("pendulum", "testbed", [1, 2], compile_update=False)
    records = [run.step(compare=True) for _ in range(40)]
    change = np.array([r["buffers"]["params"][0] for r in records])
    gap = np.array([r["buffers"]["params"][1] for r in records])
    assert np.median(gap) < 1e-6 and gap.max() < 1e-4  # a sign flip of a trace: ~1e-5
    assert np.median(change) > 100 * np.median(gap)
    ratio = [abs(r["torch"][2] - r["fused"][2]).max() for r in records]
    assert max(ratio) < 1e-5
    summary = es.summarise(records, windows=1, episodes=1000)
    assert summary["windows"][0]["compared"] == 80
    run.close()


def test_engine_shadow_leaves_the_lead_on_its_own_path() -> None:
    """The shadow, loaded with the lead's state every step, never changes the lead: after
    30 compared steps the lead's parameters and actions are bit for bit those of a fused
    population run alone from the same seeds (:class:`lockstep.EngineRun`)."""
    es = _engine_shadow()
    import lockstep

    shadowed = es.Shadowed("pendulum", "testbed", [1, 2], compile_update=False)
    alone = lockstep.EngineRun.start("fused", "pendulum", "testbed", [1, 2])
    start = alone.params()
    for _ in range(30):
        shadowed.step(compare=True)
        alone.step()
    np.testing.assert_array_equal(shadowed.lead.params(), alone.params())
    np.testing.assert_array_equal(shadowed.lead.actions, alone.actions)
    assert not np.array_equal(alone.params(), start)  # it learned: the test can fail
    shadowed.close()
    alone.close()


def test_engine_shadow_sign_flips_by_hand() -> None:
    """Member 0: one element of r apart by half its size with e of opposite signs, one
    apart with e of one sign; member 1: apart by 1e-4 of its size only (not counted)."""
    import torch

    es = _engine_shadow()
    e_f = torch.tensor([[1e-9, 0.5, 0.3], [0.2, 0.1, 0.4]]).view(1, 2, 1, 3)
    r_f = torch.tensor([[1.0, 0.5, 0.3], [1.0, 0.1, 0.4]]).view(1, 2, 1, 3)
    e_t, r_t = e_f.clone(), r_f.clone()
    e_t[0, 0, 0, 0] = -1e-9
    r_t[0, 0, 0, 0] = 0.5
    r_t[0, 0, 0, 1] = 0.2
    r_t[0, 1, 0, 1] = 0.1 + 1e-4
    out = es.sign_flips({"trace_e": e_f, "trace_r": r_f}, {"trace_e": e_t, "trace_r": r_t})
    np.testing.assert_array_equal(out, [[2, 0], [1, 0]])


@pytest.mark.parametrize(
    ("argv", "named"),
    [
        (["--config", "testbed+nope"], "--config"),
        (["--seeds", "0"], "--seeds"),
        (["--every", "0"], "--every"),
    ],
)
def test_engine_shadow_refuses_bad_input_before_any_work(
    argv: list[str], named: str, capsys: pytest.CaptureFixture[str]
) -> None:
    es = _engine_shadow()
    with pytest.raises(SystemExit):
        es.main(argv)
    assert named in capsys.readouterr().err


def test_cleanrl_output_is_read_and_summed_as_cleanrl_does() -> None:
    """benchmarks/cleanrl.py reads the episodic returns and steps/s that CleanRL's script
    prints, and its metric is the mean of the last 100 training episodes."""
    import cleanrl

    text = ("global_step=21, episodic_return=[12.5]\nSPS: 900\nnoise\n"
            "global_step=60, episodic_return=[-3.25]\nglobal_step=99, episodic_return=7\n"
            "SPS: 1043\n")  # fmt: skip
    parsed = cleanrl.parse_cleanrl_output(text)
    assert parsed == {"episode_steps": [21, 60, 99], "returns": [12.5, -3.25, 7.0],
                      "steps_per_s": 1043.0}  # fmt: skip
    returns = list(range(150))
    assert cleanrl.last_mean(returns) == pytest.approx(np.mean(range(50, 150)))  # 99.5
    assert cleanrl.last_mean([4.0, 6.0]) == 5.0
    with pytest.raises(ValueError):
        cleanrl.last_mean([])
    run = {"episode_steps": [10, 20, 30], "returns": [1.0, 3.0, 8.0]}
    got = cleanrl.curve(run, np.array([5, 10, 25, 30, 40]))
    assert np.isnan(got[0])
    assert got[1:].tolist() == [1.0, 2.0, 4.0, 4.0]  # the mean of the episodes ended by then


def test_cleanrl_side_by_side_needs_pporpe_and_gives_p(tmp_path: Path) -> None:
    import cleanrl

    def run(impl: str, seed: int, value: float) -> dict[str, Any]:
        cpu = 1000.0 + seed if impl == "pporpe" else None  # CleanRL's: not recorded
        return {"implementation": impl, "task": "Hopper-v4", "seed": seed,
                "last100_mean": value, "steps_per_s": 1000.0, "steps_per_cpu_s": cpu}  # fmt: skip

    assert cleanrl.task_row([run("cleanrl", 1, 5.0)], "Hopper-v4") is None
    runs = [run("pporpe", s, v) for s, v in enumerate([3.0, 4.0, 6.0])]
    alone = cleanrl.task_row(runs, "Hopper-v4")  # a task of the study CleanRL did not run
    assert alone is not None and alone["seeds"] == {"pporpe": 3}
    assert "p_pporpe_better" not in alone and "cleanrl" not in alone
    assert "| 3 / 0 / 0 | 4 [" in cleanrl.summary_lines([alone])[2]
    assert "| - | - | - | - | 1001 / - / - |" in cleanrl.summary_lines([alone])[2]
    runs += [run("cleanrl", s, v) for s, v in enumerate([2.0, 5.0])]
    row = cleanrl.task_row(runs, "Hopper-v4")
    assert row is not None and row["seeds"] == {"pporpe": 3, "cleanrl": 2}
    # pairs won: 3>2, 4>2, 6>2, 6>5: 4 of 6
    assert row["p_pporpe_better"]["value"] == pytest.approx(4 / 6)
    assert row["pporpe"]["value"] == pytest.approx(13 / 3)
    line = cleanrl.summary_lines([row])[2]
    assert "p_pporpe_better_sb3" not in row and "| - | - | 1001 / - / - |" in line
    one = cleanrl.task_row([*runs, run("sb3", 0, 4.0)], "Hopper-v4")
    assert one is not None and "p_pporpe_better_sb3" not in one  # one seed: no P
    runs += [run("sb3", s, v) for s, v in enumerate([4.0, 4.0, 7.0])]
    row = cleanrl.task_row(runs, "Hopper-v4")
    assert row is not None and row["seeds"] == {"pporpe": 3, "cleanrl": 2, "sb3": 3}
    # pporpe 3, 4, 6 against SB3 4, 4, 7: wins 6>4 twice, ties 4=4 twice (half each): 3 of 9
    assert row["p_pporpe_better_sb3"]["value"] == pytest.approx(3 / 9)
    assert "| 3 / 2 / 3 |" in cleanrl.summary_lines([row])[2]


def _engine_divergence() -> Any:
    import engine_divergence

    return engine_divergence


def test_engine_divergence_growth_jump_and_crossings_by_hand() -> None:
    """A gap of 10^(-7 + 2t/1000): 2 decades per 1000 steps, crossing 1e-5 after step 1000
    (1-based step 1002, the first above) and 1e-2 after step 2500; a factor-50 jump at one
    step below 1e-3 is the largest, one above 1e-3 is not counted."""
    ed = _engine_divergence()
    t = np.arange(4000)
    gap = 10.0 ** (-7 + 2 * t / 1000)
    assert ed.first_index(gap > 1e-5) == 1002
    assert ed.first_index(gap > 1e-2) == 2502
    assert ed.first_index(gap > 1e3) is None
    assert ed.growth_rate(gap) == pytest.approx(2.0)
    assert ed.growth_rate(np.full(100, 1e-7)) is None  # never reaches the fitted range
    jumpy = gap.copy()
    jumpy[300:] *= 50  # at index 300: step 301
    jumpy[3000:] *= 1000  # above 1e-3 already: not a jump that counts
    jump = ed.largest_jump(jumpy)
    assert jump["step"] == 301 and jump["factor"] == pytest.approx(50 * 10 ** (2 / 1000))
    assert jump["gap_before"] == pytest.approx(gap[299])


def test_engine_divergence_control_starts_one_ulp_away_and_parts_slowly() -> None:
    """The control twin: every parameter exactly one float32 step from the fused engine's
    (the value network's target moved with it), so its first gap is at most float32's
    relative rounding; over 30 steps of InvertedPendulum with the test bed's learner both
    twins stay within 1e-3 of the fused engine's parameters (they part by amplification,
    not at once) and no discrete event differs while the gap is below 1e-4."""
    import torch

    ed = _engine_divergence()
    lead = ed.EngineRun.start("fused", "pendulum", "testbed", [1, 2])
    twin = ed.EngineRun.start("fused", "pendulum", "testbed", [1, 2])
    before = twin.learner.state.params.clone()
    twin.nudge(0)
    after = twin.learner.state.params
    up = torch.nextafter(before, torch.full_like(before, np.inf))
    down = torch.nextafter(before, torch.full_like(before, -np.inf))
    assert bool(((after == up) | (after == down)).all()) and bool((after != before).all())
    np.testing.assert_array_equal((after[1] == up[1]).numpy(), (after[2] == up[2]).numpy())
    pf, pt = lead.params(), twin.params()
    first = np.abs(pt - pf).max(1) / np.abs(pf).max(1)
    assert (first > 0).all() and (first <= 2.0**-23).all()
    traces = [ed.SeedTrace(1), ed.SeedTrace(2)]
    for step in range(1, 31):
        events = (*lead.step(), *twin.step())
        ed.compare(lead, lead.params(), twin, traces, step, 0.1, events)
    for tr in traces:
        assert max(tr.gap) < 1e-3
        assert tr.first_event is None or tr.first_event["gap_before"] > 1e-4
    lead.close()
    twin.close()


@pytest.mark.parametrize(
    ("argv", "named"),
    [
        (["--episodes", "0"], "--episodes"),
        (["--seeds", "0"], "--seeds"),
        (["--against", "numpy"], "--against"),
    ],
)
def test_engine_divergence_refuses_bad_input_before_any_work(
    argv: list[str], named: str, capsys: pytest.CaptureFixture[str]
) -> None:
    ed = _engine_divergence()
    with pytest.raises(SystemExit):
        ed.main(argv)
    assert named in capsys.readouterr().err


def test_the_committed_test_suite_page_is_its_json_rendered() -> None:
    """benchmarks/results/test_suite.md is what ``python benchmarks/test_suite.py render``
    writes from the committed JSON, and each study's ratio line holds its numbers."""
    data = json.loads(test_suite.JSON_PATH.read_text())
    assert test_suite.PAGE_PATH.read_text() == test_suite.render(data)
    before = {"label": "A", "install_s": 40.0, "wall_s": 400.0, "cpu_s": 800.0}
    after = {"label": "B", "install_s": 40.0, "wall_s": 200.0, "cpu_s": 400.0}
    study = {"trials": [before, after]}
    assert test_suite._ratio_line(study, "B", "A") == (
        "B / A (means of their trials): install 1.00, make test 0.50, CPU 0.50, "
        "install and make test 0.55."
    )


def test_the_pytest_summary_and_slowest_tests_are_read_from_its_output() -> None:
    text = (
        "======= slowest 15 durations =======\n"
        "97.31s call     tests/test_fused.py::test_compiled\n"
        "25.63s setup    tests/test_sweep_stages.py::test_stage_2@tinysweep\n"
        "=========================== short test summary info ============================\n"
        "SKIPPED [1] tests/test_inputs.py:364: running as root\n"
        "2151 passed, 1 skipped, 8 warnings in 768.75s (0:12:48)\n"
    )
    line, seconds, slow = test_suite.pytest_summary(text)
    assert (line, seconds) == ("2151 passed, 1 skipped, 8 warnings", 768.75)
    assert [(d["s"], d["when"], d["test"]) for d in slow] == [
        (97.31, "call", "tests/test_fused.py::test_compiled"),
        (25.63, "setup", "tests/test_sweep_stages.py::test_stage_2@tinysweep"),
    ]
