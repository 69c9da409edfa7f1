"""The two stages of a sweep end to end (issue 55, items 2, 3 and 5): a tiny tuning sweep
(2 methods x 2 settings x 1 task x 2 seeds of batch PPO) trained, reported and selected;
its ``selected.toml`` run on other seeds and reported with the grid's report; the refusals
of a stage-2 spec; and a sweep's cell killed, or stopped as by Ctrl-C, and resumed."""

from __future__ import annotations

import io
import json
import math
import os
import shutil
import signal
import time
from contextlib import redirect_stdout
from pathlib import Path

import numpy as np
import pytest
import warm_process
from repo_scripts import load_script
from test_grid import _launch, records_of

from pporpe.cli import main
from pporpe.experiments.grids.reproduce import reproduce
from pporpe.experiments.grids.spec import GridSpec, load_spec
from pporpe.experiments.reports.report import write_report
from pporpe.runs.logger import read_records

STAGE1 = """
name = "tinysweep"
kind = "batch"
methods = ["ppo", "rpe"]
seeds = [5, 6]
eval_episodes = 1
checkpoint_every = 100

[learner]
n_envs = 1
n_steps = 64
batch_size = 32
n_epochs = 2
layers = 1
units = 8

[[tasks]]
env = "Pendulum-v1"
steps = 256

[sweep]
evaluation_seeds = 2

[sweep.ppo]
lr = [1e-4, 3e-2]

[sweep.rpe]
lr = [1e-4, 3e-2]
"""
LRS = (1e-4, 3e-2)


@pytest.fixture(scope="module")
def stage1(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tuning sweep trained and reported (by the command) into ``ROOT/tinysweep``."""
    root = tmp_path_factory.mktemp("sweep")
    (root / "tinysweep.toml").write_text(STAGE1)
    out = root / "tinysweep"
    assert reproduce(load_spec(root / "tinysweep.toml"), out, workers=1, progress=False).ok
    with redirect_stdout(io.StringIO()):
        assert main(["report", str(out)]) == 0
    return out


def mean_training_return(run: Path) -> float:
    """sum(return x length) / sum(length) over the run's episodes, read here."""
    records = read_records(run / "episodes.csv")
    return sum(r.ret * r.length for r in records) / sum(r.length for r in records)


def expected_selection(out: Path) -> dict[str, float]:
    """Each method's lr by the default rule, worked here: every run's mean training return
    normalised by min-max over the task's 8 runs; per setting the IQM of its 2 seeds (their
    mean); the highest, the first listed among equals."""
    values = {(m, lr, s): mean_training_return(out / f"Pendulum-v1/{m}-lr{lr!r}/seed{s}")
              for m in ("ppo", "rpe") for lr in LRS for s in (5, 6)}  # fmt: skip
    lo, hi = min(values.values()), max(values.values())
    chosen = {}
    for m in ("ppo", "rpe"):
        iqms = [np.mean([(values[(m, lr, s)] - lo) / (hi - lo) for s in (5, 6)]) for lr in LRS]
        chosen[m] = LRS[int(np.argmax(iqms))]  # argmax: the first among equals
    return chosen


@pytest.mark.xdist_group("tinysweep")  # one worker trains the sweep once
def test_stage_1_reports_the_sensitivity_and_writes_the_stage_2_spec(stage1: Path) -> None:
    assert sorted(p.name for p in (stage1 / "Pendulum-v1").iterdir()) == [
        "ppo-lr0.0001", "ppo-lr0.03", "rpe-lr0.0001", "rpe-lr0.03"
    ]  # fmt: skip
    report = (stage1 / "REPORT.md").read_text()
    for part in ("(stage 1: a tuning sweep)", "## The selection", '`select = "iqm:mean_return"`',
                 "Tuning seeds: 5, 6.", "| runner-up |", "lr = ", "swept",
                 "## Sensitivity", "| Pendulum-v1 |", "## Matched trust regions",
                 "mean approximate KL", "![sensitivity](fig_sensitivity.png)",
                 "`selected.toml` holds stage 2", "evaluation seeds [0, 1]",
                 "8/8 runs finished", "256 steps per run"):  # fmt: skip
        assert part in report, part
    for name in ("fig_sensitivity.png", "fig_sensitivity.pdf", "fig_trust_region.png",
                 "fig_trust_region.pdf", "sensitivity.csv", "trust_region.csv"):  # fmt: skip
        assert (stage1 / name).stat().st_size > 0
    trust = (stage1 / "trust_region.csv").read_text().splitlines()
    assert trust[0].startswith("task,method,setting,seed,approx_kl,ratio_dev,past_threshold")
    assert len(trust) == 1 + 8
    for row in trust[1:]:  # a batch run logs its updates: every run has a trust region
        kl = float(row.split(",")[4])
        assert math.isfinite(kl) and kl >= 0
    # the selection, against the rule worked independently from the runs' episodes
    stage2 = load_spec(stage1 / "selected.toml")
    assert stage2.sweep is not None and stage2.sweep.stage == 2
    chosen = {m: dict(s[0])["lr"] for m, s in stage2.sweep.settings.items()}
    assert chosen == expected_selection(stage1)
    assert stage2.name == "tinysweep-eval" and stage2.sweep.tuning_seeds == (5, 6)
    assert sorted({r.seed for r in stage2.runs}) == [0, 1] and len(stage2.runs) == 4
    assert stage2.sweep.stage1 == "tinysweep"
    one = load_spec(stage1.parent / "tinysweep.toml")
    for run in stage2.runs:  # every other setting as in stage 1
        first = next(r for r in one.runs if (r.method, r.setting) == (run.method, run.setting))
        assert run.config == type(run.config)(**{**vars(first.config), "seed": run.seed})


@pytest.mark.xdist_group("tinysweep")  # one worker trains the sweep once
def test_stage_2_runs_the_selection_on_fresh_seeds_and_gets_the_grids_report(
    stage1: Path,
) -> None:
    stage2 = load_spec(stage1 / "selected.toml")
    out = stage1.parent / "tinysweep-eval"
    assert reproduce(stage2, out, workers=1, progress=False).ok
    write_report(out)
    grid = json.loads((out / "grid.json").read_text())
    assert grid["sweep"]["stage"] == 2 and grid["sweep"]["tuning_seeds"] == [5, 6]
    report = (out / "REPORT.md").read_text()
    for part in ("(batch PPO)", "## The answer", "## Over the tasks", "## Per task",
                 "P(PPO-RPE > rival)", "too few seeds (n = 2",
                 "## Each method's setting (stage 2 of a sweep)",
                 "(`tinysweep`, tuning seeds [5, 6])", "## Matched trust regions",
                 "![trust region](fig_trust_region.png)"):  # fmt: skip
        assert part in report, part
    chosen = expected_selection(stage1)
    for method, label in (("ppo", "PPO"), ("rpe", "PPO-RPE")):
        assert f"| {label} | lr {chosen[method]!r} |" in report
    for name in ("fig_aggregate.png", "fig_trust_region.png", "runs.csv", "trust_region.csv"):
        assert (out / name).stat().st_size > 0
    assert not (out / "selected.toml").exists()


@pytest.mark.xdist_group("tinysweep")  # one worker trains the sweep once
def test_a_sweeps_runs_are_collected_and_found_as_committed_runs(
    stage1: Path, tmp_path: Path
) -> None:
    """experiments/collect.py copies a sweep's finished runs (their folders named after
    their settings), and tests/test_committed_results.py's glob finds every one of them."""
    collect = load_script("experiments/collect.py", "collect")
    results = tmp_path / "results"
    assert collect.collect(stage1, results / "tinysweep") == (8, 0)
    found = sorted(p.parent for p in results.glob("*/*/*/seed*/done.json"))
    keys = [r["key"] for r in json.loads((stage1 / "grid.json").read_text())["runs"]]
    assert found == sorted(results / "tinysweep" / k for k in keys)
    assert all((run / "updates.csv").is_file() for run in found)


def stage2_text(stage1: Path) -> str:
    return (stage1 / "selected.toml").read_text()


def refusal(spec: Path) -> str:
    with pytest.raises(ValueError) as info:
        load_spec(spec)
    assert "\n" not in str(info.value)
    return str(info.value)


@pytest.mark.xdist_group("tinysweep")  # one worker trains the sweep once
def test_a_stage_2_spec_is_refused_without_a_finished_stage_1_or_with_its_seeds(
    stage1: Path, tmp_path: Path
) -> None:
    text = stage2_text(stage1)
    spec = tmp_path / "eval.toml"
    spec.write_text(text)  # stage1 = "." is now tmp_path: no grid there
    assert refusal(spec) == (f"{spec}: sweep.stage1: {tmp_path}: holds no grid (no "
                             "grid.json): run stage 1 into it first")  # fmt: skip
    (tmp_path / "grid.json").write_text(json.dumps({"name": "g", "runs": []}))
    assert refusal(spec).startswith(f"{spec}: sweep.stage1: {tmp_path}: not a stage-1 sweep")
    overlap = stage1 / "overlap.toml"
    overlap.write_text(text.replace("seeds = [0, 1]", "seeds = [1, 5]"))
    assert refusal(overlap) == (f"{overlap}: seeds: seeds [5] are tuning seeds of the stage-1 "
                                f"folder {stage1}: evaluation seeds must be fresh")  # fmt: skip
    two = stage1 / "two.toml"
    two.write_text(text.replace("lr = [", "lr = [0.5, "))
    assert refusal(two).startswith(f"{two}: sweep.ppo: a stage-2 spec gives each method one")
    chooses = stage1 / "chooses.toml"
    chooses.write_text(text.replace('\nstage1 = "."\n', '\nstage1 = "."\nselect = "iqm:score"\n'))
    assert refusal(chooses).startswith(f"{chooses}: sweep.select: belongs to stage 1")
    # the command: one line, exit 2, nothing written
    out = tmp_path / "eval-out"
    proc = warm_process.run(["reproduce", str(overlap), "--out", str(out)], timeout=120)
    assert proc.returncode == 2 and not out.exists()
    assert proc.stderr.strip().splitlines() == [f"pporpe reproduce: error: {refusal(overlap)}"]


@pytest.mark.xdist_group("tinysweep")  # one worker trains the sweep once
def test_an_unfinished_stage_1_selects_nothing_and_refuses_its_stage_2(
    stage1: Path, tmp_path: Path
) -> None:
    copy = tmp_path / "tinysweep"
    shutil.copytree(stage1, copy, ignore=shutil.ignore_patterns("*.toml", "populations"))
    (copy / "Pendulum-v1/rpe-lr0.03/seed6/done.json").unlink()
    write_report(copy)
    report = (copy / "REPORT.md").read_text()
    assert "**Nothing selected**: 1 of 8 runs of the sweep are unfinished" in report
    assert "| PPO-RPE | lr 0.03 | 1 | 1 |" in report
    assert "| PPO | lr 0.0001 | " not in report.split("## What ran")[0]
    assert not (copy / "selected.toml").exists()
    assert (copy / "fig_sensitivity.png").exists()  # the curves so far
    spec = copy / "selected.toml"
    spec.write_text(stage2_text(stage1))
    assert refusal(spec) == (f"{spec}: sweep.stage1: {copy}: stage 1 is unfinished: 1 of 8 "
                             "runs not done (finish it, then `pporpe report` it and use its "
                             "selected.toml)")  # fmt: skip


KILL_SWEEP = """
name = "killsweep"
kind = "batch"
methods = ["rpe"]
seeds = [0]
eval_episodes = 1
checkpoint_every = 2

[learner]
n_envs = 2
n_steps = 32
batch_size = 16
n_epochs = 2
layers = 1
units = 16

[[tasks]]
env = "pendulum"
steps = 1280

[sweep.rpe]
eps = [0.1, 0.3]
"""


@pytest.fixture(scope="module")
def kill_reference(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The sweep's spec and its runs trained without interruption."""
    root = tmp_path_factory.mktemp("killsweep")
    spec = root / "kill.toml"
    spec.write_text(KILL_SWEEP)
    assert reproduce(load_spec(spec), root / "ref", workers=1, population=1, progress=False).ok
    return spec, root / "ref"


def first_checkpoint(out: Path) -> bool:
    """Whether a cell of the sweep in ``out`` has a checkpoint and is not done."""
    ckpts = list(out.glob("pendulum/rpe-*/seed0/checkpoint.pt"))
    return bool(ckpts) and not all((c.parent / "done.json").exists() for c in ckpts)


def assert_same_as_uninterrupted(spec: GridSpec, out: Path, ref: Path) -> None:
    for run in spec.runs:
        got = records_of(out, run.key)
        assert [r.episode for r in got] == list(range(len(got)))
        assert got == records_of(ref, run.key)
        assert (out / run.key / "updates.csv").read_text().count("\n") == 1 + 20  # 20 updates


@pytest.mark.xdist_group("killsweep")  # one worker, one reference
def test_a_sweep_cell_killed_mid_run_resumes_with_complete_identical_records(
    kill_reference: tuple[Path, Path], tmp_path: Path
) -> None:
    """Every process killed (SIGKILL) once a cell has a checkpoint, then the command run
    again: every cell's records are complete and equal to the uninterrupted sweep's."""
    spec_path, ref = kill_reference
    spec = load_spec(spec_path)
    assert [r.key for r in spec.runs] == ["pendulum/rpe-eps0.1/seed0", "pendulum/rpe-eps0.3/seed0"]
    out = tmp_path / "out"
    proc = _launch(spec_path, out)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not first_checkpoint(out):
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    time.sleep(0.5)  # workers die with their parent
    unfinished = [r.key for r in spec.runs if not (out / r.key / "done.json").exists()]
    assert unfinished, "the kill came too late to test resuming"
    proc = _launch(spec_path, out)
    assert proc.wait(timeout=300) == 0
    assert_same_as_uninterrupted(spec, out, ref)


@pytest.mark.xdist_group("killsweep")  # one worker, one reference
def test_a_sweep_stopped_as_by_ctrl_c_resumes_with_complete_identical_records(
    kill_reference: tuple[Path, Path], tmp_path: Path
) -> None:
    """The stop request of Ctrl-C (what ``pporpe reproduce`` passes on SIGINT), asked from
    the first poll: the cells are interrupted at their next step, not failed, and the same
    call again finishes them with the uninterrupted sweep's records."""
    spec_path, ref = kill_reference
    spec = load_spec(spec_path)
    out = tmp_path / "out"
    stopped = reproduce(spec, out, workers=1, population=1, progress=False, stop=lambda: True)
    assert stopped.interrupted and not stopped.failed and not stopped.ok
    assert not any((out / key / "error.txt").exists() for key in stopped.interrupted)
    again = reproduce(spec, out, workers=1, population=1, progress=False)
    assert again.ok and sorted(again.done) == sorted(r.key for r in spec.runs)
    assert_same_as_uninterrupted(spec, out, ref)
