"""Bad input never leaks a traceback: corrupt run files, the output folder, and
property-based fuzzing of the configs, grid specs and CLI arguments (hypothesis)."""

from __future__ import annotations

import json
import math
import shutil
from dataclasses import fields
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from interrupt import Interrupted, at_episode
from tiny import tiny_learner

from pporpe.batch.config import BatchConfig
from pporpe.cli import main
from pporpe.experiments.grids.spec import parse_spec
from pporpe.online.config import OnlineConfig, TrainConfig
from pporpe.runs import load_policy, train

FIXTURES = Path(__file__).parent / "fixtures"
TINY = tiny_learner()


def tiny_run(tmp_path: Path, name: str = "run", episodes: int = 4) -> tuple[TrainConfig, Path]:
    cfg = TrainConfig(episodes=episodes, checkpoint_every=2, eval_episodes=0, learner=TINY)
    return cfg, tmp_path / name


def unfinished(tmp_path: Path) -> tuple[TrainConfig, Path]:
    """A run stopped after its checkpoint at 2 episodes (of 4)."""
    cfg, run = tiny_run(tmp_path)

    with pytest.raises(Interrupted):
        train(cfg, run, progress=False, on_episode=at_episode(2))
    return cfg, run


# --- corrupt or foreign run files -------------------------------------------------
def test_truncated_checkpoint_is_refused_and_kept(tmp_path: Path) -> None:
    cfg, run = unfinished(tmp_path)
    ckpt = run / "checkpoint.pt"
    ckpt.write_bytes(ckpt.read_bytes()[:100])
    before = ckpt.read_bytes()
    with pytest.raises(ValueError, match=r"checkpoint\.pt cannot be read .*not changed.*--force"):
        train(cfg, run, progress=False)
    assert ckpt.read_bytes() == before  # the evidence is not overwritten


def test_corrupt_config_json_names_the_file(tmp_path: Path) -> None:
    cfg, run = unfinished(tmp_path)
    (run / "config.json").write_text("{not json")
    with pytest.raises(ValueError, match=r"config\.json cannot be read"):
        train(cfg, run, progress=False)
    with pytest.raises(ValueError, match=r"config\.json cannot be read"):
        load_policy(run)


def test_corrupt_episodes_csv_of_a_finished_run_names_the_file(tmp_path: Path) -> None:
    run = tmp_path / "old"
    shutil.copytree(FIXTURES / "run_v0_1_batch", run)
    (run / "episodes.csv").write_text("episode,ret\n1,abc\n")
    from pporpe.runs.folder import read_config

    _, cfg = read_config(run)
    with pytest.raises(ValueError, match=r"episodes\.csv cannot be read as an episodes\.csv"):
        train(cfg, run, progress=False)


def test_corrupt_episodes_csv_of_an_unfinished_run_is_rewritten(tmp_path: Path) -> None:
    cfg, run = unfinished(tmp_path)
    (run / "episodes.csv").write_text("garbage")
    result = train(cfg, run, progress=False)
    assert [r.episode for r in result.records] == [0, 1, 2, 3]


def test_a_different_config_is_refused_naming_the_fields_unless_force(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    base = ["train", "--env", "pendulum", "--episodes", "1", "--eval-episodes", "0",
            "--no-compile", "--quiet", "--out", str(out)]  # fmt: skip
    assert main(base) == 0
    capsys.readouterr()
    assert main([*base[:-2], "--method", "ppo", "--eps", "0.2", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "differing: learner.eps, learner.method" in err and "--force" in err
    assert json.loads((out / "config.json").read_text())["learner"]["method"] == "rpe"
    assert main([*base[:-2], "--method", "ppo", "--force", "--out", str(out)]) == 0
    assert json.loads((out / "config.json").read_text())["learner"]["method"] == "ppo"


# --- property-based: configs --------------------------------------------------------
def values() -> st.SearchStrategy[Any]:
    """Values of every JSON-ish type, with edge cases."""
    return st.one_of(
        st.none(),
        st.booleans(),
        st.integers(min_value=-(10**12), max_value=10**12),
        st.floats(allow_nan=True, allow_infinity=True),
        st.text(max_size=8),
        st.lists(st.floats(allow_nan=False, width=32), max_size=3).map(tuple),
        st.sampled_from(["ppo", "rpe", "student_t", "swish", "derived", "inf", "scaled"]),
    )


def check_config(cls: type, name: str, value: Any, **extra: Any) -> None:
    """Either the config accepts the value, or a ValueError names the field."""
    try:
        cls(**{name: value, **extra})
    except ValueError as exc:
        msg = str(exc)
        assert name in msg or name.split("_")[0] in msg, (name, value, msg)
        assert "\n" not in msg


@settings(max_examples=300, deadline=None)
@given(st.sampled_from([f.name for f in fields(OnlineConfig)]), values())
def test_online_config_accepts_or_names_the_field(name: str, value: Any) -> None:
    check_config(OnlineConfig, name, value)


@settings(max_examples=300, deadline=None)
@given(st.sampled_from([f.name for f in fields(BatchConfig)]), values())
def test_batch_config_accepts_or_names_the_field(name: str, value: Any) -> None:
    check_config(BatchConfig, name, value)


@settings(max_examples=150, deadline=None)
@given(st.sampled_from([f.name for f in fields(TrainConfig) if f.name != "learner"]), values())
def test_train_config_accepts_or_names_the_field(name: str, value: Any) -> None:
    check_config(TrainConfig, name, value)


# --- property-based: grid specs --------------------------------------------------
GOOD_SPEC: dict[str, Any] = {
    "name": "fuzz",
    "methods": ["ppo", "rpe"],
    "seeds": 2,
    "eval_episodes": 1,
    "learner": {"layers": 1, "units": 8},
    "tasks": [{"env": "pendulum", "episodes": 2}],
}
TOP_FIELDS = ["name", "kind", "methods", "seeds", "eval_episodes", "checkpoint_every",
              "learner", "tasks", "unknown_field"]  # fmt: skip


@settings(max_examples=200, deadline=None)
@given(
    st.sampled_from(TOP_FIELDS),
    st.one_of(
        values(),
        st.lists(values(), max_size=3),
        st.dictionaries(st.text(max_size=6), values(), max_size=2),
    ),
    st.booleans(),
)
def test_a_mutated_spec_parses_or_names_the_field(field: str, value: Any, delete: bool) -> None:
    spec = json.loads(json.dumps(GOOD_SPEC))
    if delete:
        spec.pop(field, None)
    else:
        spec[field] = value
    try:
        parsed = parse_spec(spec, "fuzz.toml")
    except ValueError as exc:
        msg = str(exc)
        assert msg.startswith("fuzz.toml"), msg
    else:
        assert len(parsed.runs) >= 1


@settings(max_examples=150, deadline=None)
@given(
    st.sampled_from(["env", "episodes", "steps", "learner", "extra"]),
    st.one_of(
        values(),
        st.dictionaries(st.sampled_from(["lr", "eps", "kappa", "x"]), values(), max_size=2),
    ),
)
def test_a_mutated_task_parses_or_names_the_task(field: str, value: Any) -> None:
    spec = json.loads(json.dumps(GOOD_SPEC))
    spec["tasks"][0][field] = value
    try:
        parse_spec(spec, "fuzz.toml")
    except ValueError as exc:
        assert str(exc).startswith("fuzz.toml: tasks[0]"), str(exc)


# --- property-based: CLI arguments ------------------------------------------------
def assert_one_line_error(err: str, command: str) -> None:
    """One line ``pporpe <command>: error: ...``; an argparse error adds one hint line and
    no usage block."""
    lines = err.splitlines()
    assert "usage:" not in err and lines, err
    assert lines[0].startswith(f"pporpe {command}: error: "), err
    assert lines[1:] in ([], [f"(pporpe {command} --help for the options)"]), err


OPTIONS = {
    "--method": st.sampled_from(["ppo", "rb", "rpe", "spo", "trpo", ""]),
    "--eps": st.sampled_from(["0.1", "0.5", "1.5", "-1", "nan", "x"]),
    "--beta": st.sampled_from(["0.5", "0.95", "2", "inf"]),
    "--eta": st.sampled_from(["0.3", "-0.1", "1e9"]),
    "--gamma": st.sampled_from(["0.99", "1.0", "-0.5"]),
    "--lr": st.sampled_from(["3e-4", "0", "-1", "inf"]),
    "--seed": st.sampled_from(["0", "3", "-1", "1.5"]),
    "--env": st.sampled_from(["pendulum", "NoSuchEnv-v9", "CartPole-v1", "π"]),
    "--episodes": st.sampled_from(["1", "0", "-3", "two"]),
    "--eval-episodes": st.sampled_from(["0", "1", "-1"]),
    "--checkpoint-every": st.sampled_from(["1", "0"]),
}


@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(st.dictionaries(st.sampled_from(sorted(OPTIONS)), st.just(None), max_size=4).flatmap(
    lambda chosen: st.fixed_dictionaries({k: OPTIONS[k] for k in chosen})
))  # fmt: skip
def test_cli_train_runs_or_fails_in_one_line(
    tmp_path_factory: pytest.TempPathFactory, capsys: pytest.CaptureFixture[str], options: dict
) -> None:
    out = tmp_path_factory.mktemp("cli") / "run"
    argv = ["train", "--quiet", "--no-compile", "--out", str(out)]
    for k, v in options.items():
        argv += [k, v]
    if "--episodes" not in options:
        argv += ["--episodes", "1"]
    if "--eval-episodes" not in options:
        argv += ["--eval-episodes", "0"]
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse: usage error
        code = int(exc.code or 0)
    err = capsys.readouterr().err
    assert "Traceback" not in err and "usage:" not in err
    if code == 0:
        assert (out / "done.json").exists()
    else:
        assert code == 2, (argv, err)
        assert not out.exists(), argv  # nothing was created
        assert_one_line_error(err, "train")


# --- what the fuzzing found, kept as plain regression tests -------------------------
def test_found_opt_betas_none_is_a_value_error() -> None:
    with pytest.raises(ValueError, match="opt_betas"):
        OnlineConfig(opt_betas=None)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="lambdas"):
        OnlineConfig(lambdas=3)  # type: ignore[arg-type]


def test_found_a_non_string_kind_is_a_value_error() -> None:
    with pytest.raises(ValueError, match=r"fuzz\.toml: field 'kind'"):
        parse_spec({**GOOD_SPEC, "kind": []}, "fuzz.toml")


def test_found_a_discrete_task_creates_no_folder(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    code = main(["train", "--env", "CartPole-v1", "--episodes", "1", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and "gymnasium.spaces.Box" in err and not out.exists()


# --- the other subcommands, the TOML text, the grid's population settings ---------
@settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    st.sampled_from(["evaluate", "reproduce", "report", "figures"]),
    st.lists(
        st.sampled_from(["--episodes", "0", "-2", "x", "3", "--seed", "--population", "0",
                         "--checkpoint-seconds", "-1", "nan", "--workers", "--backend", "mars",
                         "--address", "h:1", "--eps", "2", "--beta", "--eta", "--out",
                         "NOPE", "π", ""]),
        max_size=5,
    ),
)  # fmt: skip
def test_other_subcommands_fail_in_one_line(
    tmp_path_factory: pytest.TempPathFactory,
    capsys: pytest.CaptureFixture[str],
    command: str,
    words: list[str],
) -> None:
    where = tmp_path_factory.mktemp("sub")
    target = str(where / "missing")
    argv = [command, *([target] if command in ("evaluate", "reproduce", "report") else []), *words]
    if command in ("reproduce", "figures") and "--out" not in words:
        argv += ["--out", str(where / "out")]
    try:
        code = main(argv)
    except SystemExit as exc:
        code = int(exc.code or 0)
    err = capsys.readouterr().err
    assert "Traceback" not in err
    if code != 0:
        assert code == 2, (argv, err)
        assert_one_line_error(err, command)
    if command == "reproduce":
        assert not (where / "out").exists() and not (where / "NOPE").exists()


@settings(
    max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(st.text(max_size=200))
def test_any_toml_text_parses_or_fails_naming_the_file(
    tmp_path_factory: pytest.TempPathFactory, text: str
) -> None:
    from pporpe.experiments.grids.spec import load_spec

    path = tmp_path_factory.mktemp("toml") / "spec.toml"
    path.write_text(text, encoding="utf-8")
    try:
        load_spec(path)
    except ValueError as exc:
        assert str(exc).startswith(str(path)), str(exc)


ODD = st.one_of(
    st.integers(-3, 3), st.floats(allow_nan=True), st.booleans(), st.none(), st.text(max_size=3)
)


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(ODD, ODD, st.one_of(st.integers(-2, 2), st.none(), st.booleans(), st.text(max_size=2)))
def test_population_settings_are_checked_before_any_work(
    tmp_path_factory: pytest.TempPathFactory, population: Any, seconds: Any, workers: Any
) -> None:
    from pporpe.experiments.grids.reproduce import reproduce

    spec = parse_spec(GOOD_SPEC, "fuzz.toml")
    out = tmp_path_factory.mktemp("grid") / "out"

    def whole(x: Any) -> bool:
        return isinstance(x, int) and not isinstance(x, bool)

    ok_pop = whole(population) and population >= 1
    ok_sec = isinstance(seconds, int | float) and not isinstance(seconds, bool)
    ok_sec = ok_sec and 0 <= seconds < math.inf
    ok_workers = workers is None or (whole(workers) and workers >= 1)
    if ok_pop and ok_sec and ok_workers:
        return  # valid: would start work
    with pytest.raises(ValueError, match=r"population|checkpoint_seconds|workers"):
        reproduce(spec, out, population=population, checkpoint_seconds=seconds, workers=workers)
    assert not out.exists()


def test_an_unwritable_out_folder_is_a_one_line_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import os

    if os.geteuid() == 0:
        pytest.skip("running as root: permissions do not stop writes, so this cannot be made")
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    code = main(["train", "--episodes", "1", "--out", str(locked / "run")])
    err = capsys.readouterr().err
    assert code == 2 and "cannot create the run folder" in err and "Traceback" not in err


@pytest.fixture
def small_disk(tmp_path: Path) -> Any:
    """A 256 KiB tmpfs (needs root and mount); skipped with the reason where unavailable."""
    import subprocess

    where = tmp_path / "disk"
    where.mkdir()
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(where)],
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here: {done.stderr.strip() or done.returncode}")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False)  # lazy: open handles


def test_a_full_disk_is_a_one_line_error(
    small_disk: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A checkpoint (megabytes at the paper's network size) does not fit: the run stops with
    one line naming the file, and no partial checkpoint is left behind."""
    out = small_disk / "run"
    code = main(["train", "--episodes", "3", "--checkpoint-every", "1", "--eval-episodes", "0",
                 "--no-compile", "--quiet", "--out", str(out)])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and "No space left on device" in err and "Traceback" not in err, err
    assert err.count("\n") == 1
    assert (out / "config.json").exists() and not (out / "checkpoint.pt").exists()
    assert not list(out.glob(".*.tmp"))


@settings(max_examples=60, deadline=None)
@given(st.sampled_from([f.name for f in fields(OnlineConfig)]), values())
def test_an_accepted_online_config_takes_a_few_steps(name: str, value: Any) -> None:
    """Whatever OnlineConfig accepts, the learner runs with it: a few steps, no exception
    (non-finite numbers are the run loop's to report)."""
    import numpy as np

    from pporpe.online.population import PopulationLearner

    try:
        cfg = OnlineConfig(**{"layers": 1, "units": 4, "compile": False, name: value})
    except ValueError:
        return
    if cfg.layers > 3 or cfg.units > 64:
        return  # accepted, but too big to run in a unit test
    pop = PopulationLearner(3, -np.ones(2), np.ones(2), [cfg], [0], compile_update=False)
    pop.begin_episode([0], np.zeros((1, 3)))
    no = np.zeros(1, dtype=bool)
    for t in range(3):
        pop.step(np.ones(1), np.full((1, 3), 0.1 * t), no, np.array([t == 2]))


def test_found_layer_norm_none_is_a_value_error() -> None:
    with pytest.raises(ValueError, match="layer_norm"):
        OnlineConfig(layer_norm=None)  # type: ignore[arg-type]
