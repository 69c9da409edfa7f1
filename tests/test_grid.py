"""Grid specs, the local backend, kill-and-resume for real, and the report."""

from __future__ import annotations

import contextlib
import io
import json
import os
import signal
import time
from dataclasses import replace
from pathlib import Path

import pytest
import warm_process
from resume_points import checkpointed_records, resume_problems

from pporpe.batch import BatchConfig
from pporpe.cli import main
from pporpe.experiments.grids.progress import (
    RECENT_EPISODES,
    GridProgress,
    RunProgress,
    run_progress,
)
from pporpe.experiments.grids.reproduce import reproduce
from pporpe.experiments.grids.spec import load_spec, parse_spec, select_runs
from pporpe.experiments.reports.report import write_report
from pporpe.experiments.reports.stats import mean_ci
from pporpe.online import AUTHOR_CHOICES, DEFAULT_CHOICES, TESTBED, OnlineConfig
from pporpe.runs.folder import config_json, open_run_dir
from pporpe.runs.kinds import kind_of
from pporpe.runs.logger import read_records

ROOT = Path(__file__).resolve().parents[1]
PENDULUMS = ("pendulum", "swingup")

TINY_SPEC = """
name = "tiny"
methods = ["ppo", "rpe"]
seeds = [0, 1]
eval_episodes = 2
checkpoint_every = 1

[learner]
layers = 1
units = 8

[[tasks]]
env = "pendulum"
episodes = 4
"""


def write_spec(tmp_path: Path, text: str = TINY_SPEC, name: str = "tiny.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def records_of(out: Path, key: str) -> list:
    return [replace(r, wall_time=0.0) for r in read_records(out / key / "episodes.csv")]


# ------------------------------------------------------------------------------------
# Specs
# ------------------------------------------------------------------------------------
def test_repository_specs_parse() -> None:
    paper = load_spec(ROOT / "experiments" / "paper.toml")
    assert len(paper.runs) == 3 * 4 * 10
    assert paper.methods == ["ppo", "rb", "rpe"]
    assert paper.envs == ["pendulum", "swingup", "halfcheetah", "ant"]
    assert {r.config.episodes for r in paper.runs} == {200}
    assert all(r.config.eval_episodes == 50 for r in paper.runs)
    # results/paper was trained by the torch engine; a rerun resumes it as it was
    assert {r.config.learner.engine for r in paper.runs} == {"torch"}
    # The full-length spec is the same grid with HalfCheetah and Ant at 2000 episodes,
    # trained by the default (fused) engine.
    # Ant has 25 seeds (0-24: 15 more, pre-registered in results/paper-full/preregistration.md),
    # each configured as its seed 0 but for the seed.
    full = load_spec(ROOT / "experiments" / "paper-full.toml")
    extra_ant = [r for r in full.runs if r.env == "ant" and r.seed >= 10]
    assert [(r.seed, r.method) for r in extra_ant] == [
        (s, m) for s in range(10, 25) for m in ("ppo", "rb", "rpe")
    ]
    assert [r.key for r in full.runs if r not in extra_ant] == [r.key for r in paper.runs]
    for a, b in zip(paper.runs, [r for r in full.runs if r not in extra_ant], strict=True):
        long = a.env in ("halfcheetah", "ant")
        fused = replace(a.config, learner=replace(a.config.learner, engine="fused"))
        assert b.config == (replace(fused, episodes=2000) if long else fused)
    ant0 = {r.method: r.config for r in full.runs if r.env == "ant" and r.seed == 0}
    for run in extra_ant:
        assert run.config == replace(ant0[run.method], seed=run.seed)
    quick = load_spec(ROOT / "experiments" / "quick.toml")
    assert set(quick.methods) == {"ppo", "rb", "rpe"} and len(quick.runs) < len(paper.runs)
    # The paper's reproduction keeps the author's choices (those results/paper ran with),
    # the quick grid runs pporpe's defaults.
    for run in paper.runs:
        learner = run.config.learner
        assert {k: getattr(learner, k) for k in AUTHOR_CHOICES} == dict(AUTHOR_CHOICES)
    for run in quick.runs:
        learner = run.config.learner
        assert {k: getattr(learner, k) for k in DEFAULT_CHOICES} == dict(DEFAULT_CHOICES)
    # The paper's pendulum grid with the author's test bed settings: TESTBED for every
    # method, the paper's surrogate parameters, the paper's protocol.
    testbed = load_spec(ROOT / "experiments" / "paper-testbed.toml")
    assert [r.key for r in testbed.runs] == [r.key for r in paper.runs if r.env in PENDULUMS]
    for a, b in zip([r for r in paper.runs if r.env in PENDULUMS], testbed.runs, strict=True):
        want = OnlineConfig(**{**TESTBED, "method": a.config.learner.method, "beta": 0.5,
                               "eta": 0.3})  # fmt: skip
        assert b.config == replace(a.config, learner=want)
    # The pendulum tasks at 50 seeds: paper-full.toml's pendulum runs, seeds 0-49.
    fifty = load_spec(ROOT / "experiments" / "paper-50seeds.toml")
    assert len(fifty.runs) == 3 * 2 * 50
    full_pendulums = {r.key: r.config for r in full.runs if r.env in PENDULUMS}
    for run in fifty.runs:
        assert run.env in PENDULUMS and 0 <= run.config.seed < 50
        first = full_pendulums[run.key.replace(f"seed{run.config.seed}", "seed0")]
        assert run.config == replace(first, seed=run.config.seed)


CLEANRL_PPO_CONTINUOUS = {
    "n_envs": 1, "n_steps": 2048, "batch_size": 64, "n_epochs": 10, "lr": 3e-4,
    "lr_schedule": "linear", "adam_eps": 1e-5, "gamma": 0.99, "gae_lambda": 0.95, "eps": 0.2,
    "clip_vf": 0.2, "ent_coef": 0.0, "vf_coef": 0.5, "max_grad_norm": 0.5,
    "adv_norm": "minibatch", "normalize_obs": True, "normalize_reward": True, "clip_obs": 10.0,
    "clip_reward": 10.0, "bootstrap_truncated": False, "policy": "normal", "scale": "global",
    "log_std_init": 0.0, "action_bound": "clip", "layers": 2, "units": 64,
    "activation": "tanh", "layer_norm": False, "init": "orthogonal",
}  # fmt: skip
"""CleanRL's ppo_continuous_action.py (its defaults: 1 env, 2048 steps, 32 minibatches, 10
epochs, annealed lr, clipped value loss, next_done = terminations | truncations, ...) in
BatchConfig's fields."""


def test_the_batch_mujoco_study_runs_cleanrls_settings() -> None:
    """experiments/batch-mujoco.toml: 3 methods x 4 MuJoCo -v4 tasks x 10 seeds x 1M steps,
    every run with CleanRL's settings and the same eps; PPO-RB eta 0.3, PPO-RPE beta 0.5."""
    study = load_spec(ROOT / "experiments" / "batch-mujoco.toml")
    assert len(study.runs) == 3 * 4 * 10
    assert study.methods == ["ppo", "rb", "rpe"]
    assert study.envs == ["HalfCheetah-v4", "Hopper-v4", "Walker2d-v4", "Ant-v4"]
    for run in study.runs:
        cfg = run.config
        assert isinstance(cfg, BatchConfig)
        assert {k: getattr(cfg, k) for k in CLEANRL_PPO_CONTINUOUS} == CLEANRL_PPO_CONTINUOUS
        assert (cfg.total_steps, cfg.eta, cfg.beta, cfg.eval_episodes) == (1_000_000, 0.3, 0.5, 50)
        assert 0 <= cfg.seed < 10


def test_the_committed_reproduction_is_the_paper_specs_runs(tmp_path: Path) -> None:
    """Every run of experiments/paper.toml finds its committed folder's config.json equal
    to its own (so `make reproduce-paper` counts it done), whatever pporpe's defaults."""
    paper = load_spec(ROOT / "experiments" / "paper.toml")
    for run in paper.runs:
        copy = tmp_path / run.key
        copy.mkdir(parents=True)
        saved = ROOT / "results" / "paper" / run.key / "config.json"
        (copy / "config.json").write_text(saved.read_text())
        open_run_dir(copy, config_json(kind_of(run.config), run.config))  # raises if not


def test_a_task_can_have_its_own_seeds(tmp_path: Path) -> None:
    text = TINY_SPEC + "seeds = [3, 5]\n"
    spec = load_spec(write_spec(tmp_path, text))
    assert sorted({r.seed for r in spec.runs}) == [3, 5]
    assert [r.config.seed for r in spec.runs] == [r.seed for r in spec.runs]


def test_spec_overrides_reach_the_learner(tmp_path: Path) -> None:
    text = TINY_SPEC + "\n[tasks.learner]\nlr = 0.001\n"
    spec = load_spec(write_spec(tmp_path, text))
    assert {r.config.learner.lr for r in spec.runs} == {0.001}
    assert {r.config.learner.units for r in spec.runs} == {8}
    assert {r.config.learner.method for r in spec.runs} == {"ppo", "rpe"}
    assert [r.key for r in spec.runs][:2] == ["pendulum/ppo/seed0", "pendulum/rpe/seed0"]


BAD_SPECS = [
    ('methods = ["ppo", "trpo"]', "methods"),
    ("seeds = 0", "seeds"),
    ("seeds = [1, -2]", "seeds"),
    ('seeds = "3"', "seeds"),
    ("eval_episodes = -1", "eval_episodes"),
    ("colour = 3", "unknown field"),
]


@pytest.mark.parametrize(("line", "field"), BAD_SPECS)
def test_malformed_top_level_fields_are_rejected(tmp_path: Path, line: str, field: str) -> None:
    key = line.split("=")[0].strip()
    lines = [ln for ln in TINY_SPEC.splitlines() if not ln.startswith(f"{key} =")]
    text = line + "\n" + "\n".join(lines)
    path = write_spec(tmp_path, text)
    with pytest.raises(ValueError, match=field) as info:
        load_spec(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize(
    ("task", "message"),
    [
        ('env = "NoSuchEnv-v0"\nepisodes = 3', "pendulum"),
        ('env = "pendulum"\nepisodes = 0', "episodes"),
        ('env = "pendulum"\nepisodes = 3\nsteps = 3', "exactly one"),
        ('env = "pendulum"', "exactly one"),
        ('env = "pendulum"\nepisodes = 2.5', "episodes"),
        ('env = "pendulum"\nepisodes = 3\nspeed = 1', "unknown field"),
        ('env = "pendulum"\nepisodes = 3\nseeds = 0', "seeds"),
        ('env = "pendulum"\nepisodes = 3\nseeds = [1, 1]', "seeds"),
        ('env = "pendulum"\nepisodes = 3\n[tasks.learner]\neps = 2.0', "eps"),
        ('env = "pendulum"\nepisodes = 3\n[tasks.learner]\nwarp = 2.0', "warp"),
    ],
)
def test_malformed_tasks_are_rejected(tmp_path: Path, task: str, message: str) -> None:
    text = 'methods = ["rpe"]\nseeds = 1\n[[tasks]]\n' + task + "\n"
    with pytest.raises(ValueError, match=message) as info:
        load_spec(write_spec(tmp_path, text))
    assert "tasks[0]" in str(info.value)


def test_missing_field_and_bad_toml(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="missing field 'tasks'"):
        parse_spec({"methods": ["rpe"], "seeds": 1})
    with pytest.raises(ValueError, match="not valid TOML"):
        load_spec(write_spec(tmp_path, "methods = [", "bad.toml"))


def test_cli_rejects_bad_spec_before_any_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    spec = write_spec(tmp_path, TINY_SPEC.replace('"rpe"]', '"rpe", "sac"]'))
    out = tmp_path / "out"
    assert main(["reproduce", str(spec), "--out", str(out), "--quiet"]) == 2
    assert "methods" in capsys.readouterr().err
    assert not out.exists()


def test_cli_selects_a_chunk_and_refuses_an_unknown_task(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    spec = write_spec(tmp_path)
    out = tmp_path / "out"
    assert main(["reproduce", str(spec), "--out", str(out), "--tasks", "ant", "--quiet"]) == 2
    assert "--tasks ant: not in the spec" in capsys.readouterr().err
    assert not out.exists()
    args = ["reproduce", str(spec), "--out", str(out), "--methods", "rpe", "--seeds", "1"]
    assert main([*args, "--quiet"]) == 0
    assert "1 run done (0 were already done)" in capsys.readouterr().out
    assert sorted(p.name for p in (out / "pendulum").iterdir()) == ["rpe"]
    assert [p.name for p in (out / "pendulum" / "rpe").iterdir()] == ["seed1"]
    listed = [r["key"] for r in json.loads((out / "grid.json").read_text())["runs"]]
    assert len(listed) == 4  # the whole grid, so that the report counts the missing runs


# ------------------------------------------------------------------------------------
# Local backend, failures, report
# ------------------------------------------------------------------------------------
def test_local_backend_runs_grid_and_report(tmp_path: Path) -> None:
    spec = load_spec(write_spec(tmp_path))
    out = tmp_path / "out"
    outcome = reproduce(spec, out, workers=2, progress=False)
    assert outcome.ok and sorted(outcome.done) == sorted(r.key for r in spec.runs)
    for run in spec.runs:
        assert [r.episode for r in read_records(out / run.key / "episodes.csv")] == [0, 1, 2, 3]
        assert (out / run.key / "evaluation.json").exists()
    # same seeds in a second folder give the same records; a rerun skips everything
    again = reproduce(spec, out, workers=1, progress=False)
    assert sorted(again.skipped) == sorted(outcome.done)

    paths = write_report(out)
    names = {p.name for p in paths}
    assert {
        "summary.md",
        "summary.csv",
        "fig_summary.png",
        "fig_learning.pdf",
        "fig_regularization.png",
    } <= names
    table = (out / "summary.md").read_text()
    assert "| pendulum | PPO-RPE |" in table and "| pendulum | PPO |" in table
    scores = [
        json.loads((out / f"pendulum/ppo/seed{s}/evaluation.json").read_text())["median"]
        for s in (0, 1)
    ]
    mean, lo, hi = mean_ci(scores)
    assert f"| pendulum | PPO | 2 | {mean:.1f} [" in table  # seeds, then mean [bootstrap CI]
    assert lo <= mean <= hi


def test_mean_ci_matches_hand_computation() -> None:
    mean, lo, hi = mean_ci([1.0, 2.0, 3.0, 4.0])
    # sd = 1.2910, t(0.975, 3) = 3.1824: half width = 3.1824 * 1.2910 / 2 = 2.0543
    assert mean == 2.5
    assert hi - mean == pytest.approx(2.0543, abs=1e-3)
    assert mean - lo == pytest.approx(2.0543, abs=1e-3)


def test_failed_run_leaves_traceback_and_others_continue(tmp_path: Path) -> None:
    text = TINY_SPEC.replace('env = "pendulum"', 'env = "pporpe-test/HereOnly-v0"')
    import gymnasium as gym

    # registered in this process only: it builds here (so the grid's check of its tasks
    # passes) and is unknown in the workers, where every run fails
    pendulum = gym.envs.registry["Pendulum-v1"].entry_point
    gym.register("pporpe-test/HereOnly-v0", entry_point=pendulum)
    spec = load_spec(write_spec(tmp_path, text))
    outcome = reproduce(spec, tmp_path / "out", workers=1, backend="local", progress=False)
    assert len(outcome.failed) == len(spec.runs) and not outcome.ok
    for key in outcome.failed:
        assert "Traceback" in (tmp_path / "out" / key / "error.txt").read_text()
    status = json.loads((tmp_path / "out" / "status.json").read_text())
    assert sorted(status["failed"]) == sorted(outcome.failed)


# ------------------------------------------------------------------------------------
# Kill (SIGKILL) mid-grid and resume, for real
# ------------------------------------------------------------------------------------
KILL_SPEC = """
name = "killme"
methods = ["ppo", "rpe"]
seeds = [0]
eval_episodes = 1
checkpoint_every = 2

[learner]
layers = 1
units = 8

[[tasks]]
env = "pendulum"
episodes = 40
"""


def _launch(spec: Path, out: Path, *extra: str) -> warm_process.Started:
    """``pporpe reproduce`` as a job of its own (:func:`warm_process.start`)."""
    return warm_process.start(
        ["reproduce", str(spec), "--out", str(out), "--workers", "2", "--quiet", *extra]
    )


def test_sigkill_mid_grid_then_resume_gives_complete_identical_records(tmp_path: Path) -> None:
    spec_path = write_spec(tmp_path, KILL_SPEC, "kill.toml")
    spec = load_spec(spec_path)

    # reference: an uninterrupted grid
    ref = tmp_path / "ref"
    assert reproduce(spec, ref, workers=2, progress=False).ok

    out = tmp_path / "out"
    proc = _launch(spec_path, out)
    deadline = time.monotonic() + 120
    # wait until some run has a checkpoint but has not finished, then kill everything
    while time.monotonic() < deadline:
        ckpts = list(out.glob("pendulum/*/seed0/checkpoint.pt"))
        if ckpts and not all((c.parent / "done.json").exists() for c in ckpts):
            break
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    time.sleep(0.5)  # workers die with their parent (PR_SET_PDEATHSIG)
    unfinished = [r.key for r in spec.runs if not (out / r.key / "done.json").exists()]
    assert unfinished, "the kill came too late to test resuming"
    saved = checkpointed_records(out)

    proc = _launch(spec_path, out)
    assert proc.wait(timeout=300) == 0
    assert resume_problems(saved) == []  # resumed from the checkpoints, not started over
    for run in spec.runs:
        got = records_of(out, run.key)
        assert [r.episode for r in got] == list(range(40))  # no gap, no duplicate
        assert got == records_of(ref, run.key)  # and the same numbers as uninterrupted


POP_SPEC = KILL_SPEC.replace("seeds = [0]", "seeds = [0, 1]").replace(
    "episodes = 40", "episodes = 30"
)


@pytest.fixture(scope="module")
def population_reference(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``POP_SPEC``'s grid uninterrupted, through one worker's population of two slots: the
    records the tests that kill it compare with (trained once for them)."""
    folder = tmp_path_factory.mktemp("population-reference")
    spec = load_spec(write_spec(folder, POP_SPEC, "pop.toml"))
    assert reproduce(spec, folder / "ref", workers=1, population=2, progress=False).ok
    return folder / "ref"


@pytest.mark.xdist_group("population-reference")  # one worker, one reference
def test_sigkill_a_population_then_resume_gives_complete_identical_records(
    tmp_path: Path, population_reference: Path
) -> None:
    """Four runs through one worker's population of two slots (a slot is refilled when its
    run finishes): killed mid-way and restarted, every run's records are complete and
    equal to the uninterrupted grid's with the same packing."""
    spec_path = write_spec(tmp_path, POP_SPEC, "pop.toml")
    spec = load_spec(spec_path)
    ref = population_reference
    assert len(list((ref / "populations").glob("*/population.json"))) == 1
    args = ("--workers", "1", "--population", "2", "--checkpoint-seconds", "0")
    out = tmp_path / "out"
    proc = _launch(spec_path, out, *args)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:  # until a run has a checkpoint with 4+ episodes
        done = [r for r in spec.runs if (out / r.key / "done.json").exists()]
        csvs = []
        for c in out.glob("pendulum/*/seed*/episodes.csv"):
            with contextlib.suppress(ValueError):  # a CSV being replaced
                csvs.append(len(read_records(c)))
        if done or (csvs and max(csvs) >= 4):
            break
        time.sleep(0.02)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    time.sleep(0.5)
    unfinished = [r.key for r in spec.runs if not (out / r.key / "done.json").exists()]
    assert unfinished, "the kill came too late to test resuming"
    saved = checkpointed_records(out)
    proc = _launch(spec_path, out, *args)
    assert proc.wait(timeout=300) == 0
    assert resume_problems(saved) == []  # resumed from the checkpoints, not started over
    for run in spec.runs:
        got = records_of(out, run.key)
        assert [r.episode for r in got] == list(range(30))
        assert got == records_of(ref, run.key)


@pytest.mark.xdist_group("population-reference")
def test_a_grid_resumed_with_another_plan_continues_the_runs_in_flight(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], population_reference: Path
) -> None:
    """The population's home folder is named after the runs it packs, so a grid resumed
    with a filter (or after a run finished) plans a new home: the runs in flight in the
    old home's checkpoint must go on from there, not start again. Killed mid-way, then
    resumed with seed 0 alone (the seed of the two runs in the slots): it says so, their
    first records are the checkpoint's very rows (the same wall times), every record is
    there once, and the numbers are the uninterrupted grid's."""
    from pporpe.runs.folder import load_checkpoint

    spec_path = write_spec(tmp_path, POP_SPEC, "pop.toml")
    spec = load_spec(spec_path)
    ref = population_reference
    args = ("--workers", "1", "--population", "2", "--checkpoint-seconds", "0")
    out = tmp_path / "out"
    proc = _launch(spec_path, out, *args)
    deadline = time.monotonic() + 120
    old: list[Path] = []
    while time.monotonic() < deadline:  # until the population has a checkpoint
        old = list((out / "populations").glob("*/checkpoint.pt"))
        if old or any((out / r.key / "done.json").exists() for r in spec.runs):
            break
        time.sleep(0.02)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    time.sleep(0.5)
    assert len(old) == 1 and not any((out / r.key / "done.json").exists() for r in spec.runs)
    saved = load_checkpoint(old[0].parent)
    in_flight = {str((old[0].parent / n).resolve()): m for n, m in saved["members"].items()}
    assert sorted(Path(d).parent.name for d in in_flight) == ["ppo", "rpe"]
    assert {Path(d).name for d in in_flight} == {"seed0"}
    assert min(len(m["records"]) for m in in_flight.values()) >= 1
    capsys.readouterr()
    chunk = select_runs(spec, seeds=[0])
    assert reproduce(chunk, out, workers=1, population=2, whole=spec, checkpoint_seconds=0).ok
    assert "2 runs in flight in populations packed before" in capsys.readouterr().err
    homes = sorted(p.parent.name for p in (out / "populations").glob("*/population.json"))
    assert len(homes) == 2  # the old home, and the one the filtered grid planned
    for run_dir, member in in_flight.items():
        key = str(Path(run_dir).relative_to(out.resolve()))
        got = read_records(out / key / "episodes.csv")
        head = [r.wall_time for r in got[: len(member["records"])]]
        assert head == [float(r["wall_time"]) for r in member["records"]]
        assert [r.episode for r in got] == list(range(30))
        assert records_of(out, key) == records_of(ref, key)
    (old_home,) = [p.parent for p in old]
    assert (old_home / "checkpoint.pt").exists()  # its seed-1 runs are still to train
    assert reproduce(spec, out, workers=1, population=2, checkpoint_seconds=0).ok
    assert "removed the checkpoints of 1 population packed before" in capsys.readouterr().err
    assert not list((out / "populations").glob("*/checkpoint.pt"))
    assert (old_home / "population.json").exists()


def test_finished_homes_lists_old_populations_whose_runs_are_all_done(tmp_path: Path) -> None:
    """A population folder is finished when every run its population.json names has
    done.json; one without a checkpoint, with a run unfinished, or with an unreadable
    population.json is not listed."""
    from pporpe.runs.population_checkpoint import finished_homes

    pops = tmp_path / "out" / "populations"
    for name, done in (("a", True), ("b", True), ("c", False)):
        (tmp_path / "out" / "task" / name).mkdir(parents=True)
        if done:
            (tmp_path / "out" / "task" / name / "done.json").write_text("{}")
    homes = {"all-done": ["a", "b"], "one-left": ["a", "c"], "no-checkpoint": ["a"],
             "garbled": None, "empty": []}  # fmt: skip
    for home, runs in homes.items():
        (pops / home).mkdir(parents=True)
        if home != "no-checkpoint":
            (pops / home / "checkpoint.pt").write_bytes(b"")
        text = "{" if runs is None else json.dumps({"runs": [f"../../task/{r}" for r in runs]})
        (pops / home / "population.json").write_text(text)
    assert finished_homes(pops) == [pops / "all-done"]
    assert finished_homes(tmp_path / "missing") == []

    from pporpe.runs.population_checkpoint import discard_finished

    assert discard_finished(pops) == [pops / "all-done"]
    assert not (pops / "all-done" / "checkpoint.pt").exists()
    assert (pops / "all-done" / "population.json").exists()
    for home in ("one-left", "garbled", "empty"):
        assert (pops / home / "checkpoint.pt").exists(), home
    assert discard_finished(pops) == []  # nothing left to delete


def test_adopt_orphaned_states_hands_each_run_its_most_advanced_state(tmp_path: Path) -> None:
    """Two old populations hold run a (3 and 5 episodes) and run b (2); the planned home
    holds a at 9 and is not read; b's own checkpoint has 4 episodes, so only a is given a
    state, the 5-episode one. A run not asked for is left alone, and nothing is deleted."""
    from pporpe.runs.folder import load_checkpoint, save_checkpoint
    from pporpe.runs.population_checkpoint import adopt_orphaned_states

    def state(n: int) -> dict:
        return {"records": [{"episode": i} for i in range(n)], "updates": []}

    pops = tmp_path / "out" / "populations"
    runs = {name: tmp_path / "out" / "task" / name for name in ("a", "b", "c")}
    for run in runs.values():
        run.mkdir(parents=True)
    for home, members in (("old1", {"a": 3, "b": 2}), ("old2", {"a": 5, "c": 7}),
                          ("planned", {"a": 9})):  # fmt: skip
        (pops / home).mkdir(parents=True)
        held = {f"../../task/{k}": state(n) for k, n in members.items()}
        save_checkpoint(pops / home / "checkpoint.pt", {"members": held})
    save_checkpoint(runs["b"] / "checkpoint.pt", state(4))
    adopted = adopt_orphaned_states(pops, [pops / "planned"], [runs["a"], runs["b"]])
    assert adopted == [runs["a"]]
    assert len(load_checkpoint(runs["a"])["records"]) == 5
    assert len(load_checkpoint(runs["b"])["records"]) == 4
    assert not (runs["c"] / "checkpoint.pt").exists()
    assert all((pops / h / "checkpoint.pt").exists() for h in ("old1", "old2", "planned"))
    assert adopt_orphaned_states(pops, [], [runs["a"]]) == [runs["a"]]  # now the 9 of planned
    assert adopt_orphaned_states(tmp_path / "none", [], [runs["a"]]) == []
    (pops / "old1" / "checkpoint.pt").write_bytes(b"not a checkpoint")  # read only when needed
    assert adopt_orphaned_states(pops, [], []) == []
    with pytest.raises(ValueError, match="old1"):
        adopt_orphaned_states(pops, [], [runs["a"]])


def test_progress_into_a_file_draws_a_line_per_change_and_on_a_terminal_every_poll(
    tmp_path: Path,
) -> None:
    """The grid's bar polls every two seconds. Into a log file it is drawn only when what
    it shows changes (before, every poll drew it twice: a 30-minute grid logged 1,800
    copies); on a terminal it is drawn at every poll, since its clock moves."""

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    for file, polls_drawn in ((io.StringIO(), 1), (Terminal(), 5)):
        runs = [tmp_path / type(file).__name__ / name for name in ("a", "b")]
        for run in runs:
            run.mkdir(parents=True)
        bar = GridProgress(2, 0, runs, enabled=True, file=file)
        start = file.getvalue().count("\r")
        for _ in range(5):
            bar.poll(2, [])
        assert file.getvalue().count("\r") - start == polls_drawn
        assert "jobs=2" in file.getvalue()
        (runs[0] / "done.json").write_text("{}")
        before = file.getvalue().count("\r")
        bar.poll(1, [])
        bar.poll(1, [])
        assert file.getvalue().count("\r") - before == (1 if polls_drawn == 1 else 2)
        assert " 1/2 " in file.getvalue().rsplit("\r", 1)[-1]
        bar.close()


BATCH_KILL_SPEC = """
name = "killbatch"
kind = "batch"
methods = ["ppo", "rpe"]
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
steps = 1920
"""


def test_sigkill_a_grid_of_batch_runs_then_resume_gives_complete_identical_records(
    tmp_path: Path,
) -> None:
    """Batch runs (30 updates, a checkpoint every 2): killed once a run has a checkpoint
    and restarted, every run's records are complete and equal to the uninterrupted
    grid's."""
    spec_path = write_spec(tmp_path, BATCH_KILL_SPEC, "batch.toml")
    spec = load_spec(spec_path)
    ref = tmp_path / "ref"
    assert reproduce(spec, ref, workers=2, progress=False).ok
    out = tmp_path / "out"
    proc = _launch(spec_path, out)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:  # until a run has a checkpoint and is not done
        ckpts = list(out.glob("pendulum/*/seed0/checkpoint.pt"))
        if ckpts and not all((c.parent / "done.json").exists() for c in ckpts):
            break
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    time.sleep(0.5)
    unfinished = [r.key for r in spec.runs if not (out / r.key / "done.json").exists()]
    assert unfinished, "the kill came too late to test resuming"
    saved = checkpointed_records(out)
    proc = _launch(spec_path, out)
    assert proc.wait(timeout=300) == 0
    assert resume_problems(saved) == []  # resumed from the checkpoints, not started over
    for run in spec.runs:
        got = records_of(out, run.key)
        assert [r.episode for r in got] == list(range(len(got)))
        assert got == records_of(ref, run.key)
        assert (out / run.key / "evaluation.json").read_text() == (
            ref / run.key / "evaluation.json"
        ).read_text()


class Clock:
    """A stand-in for the bar's clock: seconds, set by the test."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


HEADER = "episode,total_steps,ret,length\n"


def csv_rows(lengths: list[int]) -> str:
    steps = [sum(lengths[: i + 1]) for i in range(len(lengths))]
    return HEADER + "".join(f"{i},{s},0,{n}\n" for i, (s, n) in enumerate(zip(steps, lengths)))


def test_progress_counts_episodes_on_disk_and_the_time_left(tmp_path: Path) -> None:
    a, b, c, d = (tmp_path / x for x in "abcd")
    for folder in (a, b, c, d):
        folder.mkdir()
    (a / "episodes.csv").write_text(csv_rows([10, 20, 30]))
    (b / "episodes.csv").write_text(csv_rows([5]))
    (b / "done.json").write_text("{}")
    # 7 episodes left at the mean length of the recent ones, (10 + 20 + 30) / 3.
    assert run_progress(a, 10) == RunProgress(3, 60, 140.0, 20.0)
    assert run_progress(b, 10) == RunProgress(10, 5, 0.0, 5.0)  # done: the whole budget
    assert run_progress(d, 10) == RunProgress(0, 0, None)  # no episode yet
    assert run_progress(a, 2).episodes == 2  # never more than the budget
    many = list(range(1, 16))  # the mean of the last RECENT_EPISODES lengths only
    (c / "episodes.csv").write_text(csv_rows(many))
    recent = many[-RECENT_EPISODES:]
    assert run_progress(c, 20).steps_left == 5 * sum(recent) / len(recent)
    # Without the step columns every episode counts as one step.
    (c / "episodes.csv").write_text("episode,ret\n0,1\n1,2\n")
    assert run_progress(c, 10) == RunProgress(2, 2, 8.0, 1.0)
    (c / "episodes.csv").write_text(HEADER + "0,10,0,10\n1,x,0\n")  # edited by hand
    assert run_progress(c, 10) == RunProgress(2, 2, 8.0, 1.0)
    (c / "episodes.csv").write_bytes(HEADER.encode() + b"0,10,0,10\n\xff\xfe,1\n")  # not UTF-8
    assert run_progress(c, 10) == RunProgress(2, 2, 8.0, 1.0)

    clock = Clock()
    bar = GridProgress(4, 0, [a, b, c, d], enabled=False, budgets=[10, 10, None, 10], clock=clock)
    assert bar.episodes_total == 30  # c has no episode budget
    assert bar.count_episodes() == "13/30"  # the first count: no rate yet
    (a / "episodes.csv").write_text(csv_rows([10, 20, 30, 40]))
    clock.t = 120.0  # 40 steps in two minutes
    # Steps left: a 6 * 25 = 150, b 0, and d, which has no episode yet, its whole budget
    # at the recent length of the task's other runs, 10 * (25 + 5) / 2 = 150: 300 steps at
    # 40 / 120 s is 15 min. (The episode rate would say 16 episodes in 32 min; d guessed
    # at the others' steps left, as before, 4 min too few.)
    assert bar.count_episodes() == "14/30, left~15 min"
    # The rate is that of the last five minutes: old, faster progress is forgotten.
    clock.t = 120.0 + bar.RATE_WINDOW_S + 1
    assert bar.count_episodes() == "14/30"  # nothing gained within the window
    (a / "episodes.csv").write_text(csv_rows([1] * 10))
    (d / "done.json").write_text("{}")
    assert bar.count_episodes() == "30/30"


def test_progress_counts_the_live_episodes_of_this_call_and_its_rate(tmp_path: Path) -> None:
    """Between two checkpoints the bar counts the episodes each worker reports live
    (progress.json, every few seconds), not only those on disk: a fresh grid showed
    "episodes=0/6000" until its first checkpoint. The time left comes from the steps done
    in this call, from when work began: a resumed grid's estimate counted its workers'
    start-up as work and jumped from 5 to 37 minutes."""
    a, b = tmp_path / "task" / "m" / "a", tmp_path / "task" / "m" / "b"
    for run in (a, b):
        run.mkdir(parents=True)
    (a / "episodes.csv").write_text(csv_rows([10] * 50))  # 500 steps before this call
    # progress.json of an earlier call, ahead of the checkpoint: not this call's work
    stale = {"episodes": 80, "total_steps": 800, "lengths": [10], "time": time.time() - 60}
    (a / "progress.json").write_text(json.dumps(stale))
    clock = Clock()
    bar = GridProgress(2, 0, [a, b], enabled=False, budgets=[100, 100], clock=clock)
    assert bar.count_episodes() == "50/200"
    clock.t = 60.0  # the workers are starting: nothing done yet
    assert bar.count_episodes() == "50/200"

    def live(run: Path, episodes: int, steps: int) -> None:
        data = {"episodes": episodes, "total_steps": steps, "lengths": [10], "time": time.time()}
        (run / "progress.json").write_text(json.dumps(data))

    clock.t = 120.0
    live(a, 56, 560)
    live(b, 6, 60)  # no checkpoint yet, and its episodes count
    # 120 steps in the minute since work began (not in the two since the call began);
    # steps left (44 + 94) * 10 = 1380: 11.5 min
    assert bar.count_episodes() == "62/200, left~12 min"
    assert run_progress(b, 100, since=bar.since) == RunProgress(6, 60, 940.0, 10.0)
    assert run_progress(b, 100) == RunProgress(0, 0, None)  # without it: the disk's


def test_progress_bar_shows_its_own_time_left_and_not_tqdms(tmp_path: Path) -> None:
    """tqdm's own time left and rate extrapolate the count of finished runs, which in a
    population finish together ("13:31<6:32:04, 811.18s/run" for a grid that ended in 69
    minutes): the bar shows only its own estimate, from the steps still to run."""
    run = tmp_path / "a"
    run.mkdir()
    (run / "episodes.csv").write_text(csv_rows([10]))
    file = io.StringIO()
    clock = Clock()
    bar = GridProgress(3, 1, [run], enabled=True, budgets=[10], file=file, clock=clock)
    bar.poll(1, [])  # the first count: no rate yet
    (run / "episodes.csv").write_text(csv_rows([10, 10]))
    clock.t = 60.0  # 10 steps in a minute
    bar.poll(1, [])
    line = file.getvalue().rsplit("\r", 1)[-1]
    assert "episodes=2/10, left~8 min" in line  # 8 episodes of 10 steps at 10 steps a minute
    assert " 1/3 [" in line
    for tqdm_estimate in ("<", "run/s", "s/run", "?"):
        assert tqdm_estimate not in line, line
    (run / "done.json").write_text("{}")
    bar.close()  # counted once more: a short grid ended showing its first count
    assert "episodes=10/10]" in file.getvalue().rsplit("\r", 1)[-1]


def test_progress_counts_the_steps_of_batch_runs_and_their_time_left(tmp_path: Path) -> None:
    """Batch runs have a budget in steps, not episodes: the bar counts their steps (live,
    else checkpointed; a finished run its whole budget) and the time left at this call's
    step rate; a grid of batch runs showed only its run count, 0/120 for an hour."""
    a, b, c = (tmp_path / "task" / "m" / x for x in "abc")
    for run in (a, b, c):
        run.mkdir(parents=True)
    (a / "episodes.csv").write_text(csv_rows([1000] * 100))  # 100k steps checkpointed
    (b / "done.json").write_text("{}")
    clock = Clock()
    bar = GridProgress(3, 0, [a, b, c], enabled=False, clock=clock,
                       step_budgets=[1_000_000, 1_000_000, 1_000_000])  # fmt: skip
    assert bar.steps_total == 3_000_000 and bar.episodes_total == 0
    assert bar.count_steps() == "1.1M/3.0M"  # a 100k, b done, c nothing yet

    def live(run: Path, steps: int) -> None:
        data = {"episodes": 1, "total_steps": steps, "lengths": [1000], "time": time.time()}
        (run / "progress.json").write_text(json.dumps(data))

    clock.t = 60.0
    live(a, 160_000)
    live(c, 60_000)
    # 120k steps in a minute; 1.78M left: 14.8 min
    assert bar.count_steps() == "1.2M/3.0M, left~15 min"
    live(a, 2_000_000)  # past its budget (a last rollout): counted up to it
    assert bar.count_steps().startswith("2.1M/3.0M")


def test_a_grid_of_batch_runs_shows_its_steps_on_the_bar(tmp_path: Path) -> None:
    file = io.StringIO()
    (tmp_path / "r").mkdir()
    bar = GridProgress(1, 0, [tmp_path / "r"], enabled=True, file=file, step_budgets=[4096])
    bar.poll(1, [])
    assert "steps=0/4096" in file.getvalue().rsplit("\r", 1)[-1]
    bar.close()
