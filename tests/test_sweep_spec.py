"""Sweeps as a grid dimension (issue 55, item 2): a spec's ``[sweep]`` table expands into
cells with their own folders, and every bad sweep is refused before any folder is written,
in one line naming the spec, the method and the field."""

from __future__ import annotations

import copy
import dataclasses
import tomllib
from pathlib import Path
from typing import Any

import pytest
import warm_process

from pporpe.experiments.grids.merge import write_grid_summary
from pporpe.experiments.grids.spec import load_spec, parse_spec, select_runs, spec_summary
from pporpe.experiments.reports.sweep.selected_spec import toml_text
from pporpe.experiments.sweep_terms import cell_name, value_text
from pporpe.runs.folder import config_json, open_run_dir
from pporpe.runs.kinds import kind_of
from pporpe.surrogates import check_surrogate_params

ROOT = Path(__file__).resolve().parents[1]

BASE: dict[str, Any] = {
    "kind": "batch",
    "methods": ["ppo", "rpe"],
    "seeds": [100, 101],
    "eval_episodes": 1,
    "learner": {"n_steps": 64, "batch_size": 32, "n_epochs": 1, "layers": 1, "units": 8},
    "tasks": [{"env": "Pendulum-v1", "steps": 128}],
}


def with_sweep(sweep: dict[str, Any], **top: Any) -> dict[str, Any]:
    data = copy.deepcopy(BASE)
    data.update(top)
    data["sweep"] = sweep
    return data


GRID = {"eps": [0.1, 0.2], "lr": [3e-4, 1e-3]}
TWO = {"eps": [0.1, 0.2]}


def test_every_combination_is_a_cell_with_its_own_folder_and_settings() -> None:
    spec = parse_spec(with_sweep({"ppo": GRID, "rpe": GRID}))
    assert spec.methods == ["ppo", "rpe"] and spec.envs == ["Pendulum-v1"]
    assert len(spec.runs) == 2 * 4 * 2  # methods x settings x seeds
    first = [r.key for r in spec.runs if r.seed == 100 and r.method == "rpe"]
    assert first == [
        "Pendulum-v1/rpe-eps0.1-lr0.0003/seed100", "Pendulum-v1/rpe-eps0.1-lr0.001/seed100",
        "Pendulum-v1/rpe-eps0.2-lr0.0003/seed100", "Pendulum-v1/rpe-eps0.2-lr0.001/seed100",
    ]  # fmt: skip
    for run in spec.runs:  # the folder's settings are the run's
        setting = dict(run.setting)
        assert (run.config.eps, run.config.lr) == (setting["eps"], setting["lr"])
        assert run.config.method == run.method and run.config.seed == run.seed
        assert run.config.units == 8  # the spec's [learner] still applies
    assert len({r.key for r in spec.runs}) == len(spec.runs)
    summary = spec_summary(spec)
    assert summary["runs"][0]["setting"] == {"eps": 0.1, "lr": 0.0003}
    sweep = summary["sweep"]
    assert sweep["stage"] == 1 and sweep["select"] == "iqm:mean_return"
    assert sweep["settings"]["rpe"][3] == {"eps": 0.2, "lr": 0.001}
    assert sweep["evaluation_seeds"] == list(range(10))  # the default: 10 fresh seeds
    assert sweep["spec"]["sweep"] == {"ppo": GRID, "rpe": GRID}
    # a chunk of a sweep: one method's cells, every setting
    chunk = select_runs(spec, methods=["rpe"], seeds=[101])
    assert [r.key for r in chunk.runs] == [k.replace("seed100", "seed101") for k in first]


def test_an_online_grid_sweeps_its_learners_settings() -> None:
    data = {"methods": ["ppo", "rpe"], "seeds": 1, "learner": {"layers": 1, "units": 8},
            "tasks": [{"env": "pendulum", "episodes": 2}],
            "sweep": {"ppo": {"lr": [1e-4, 1e-3]}, "rpe": {"lr": [1e-4, 1e-3]}}}  # fmt: skip
    spec = parse_spec(data)
    assert [r.key for r in spec.runs] == [
        "pendulum/ppo-lr0.0001/seed0", "pendulum/ppo-lr0.001/seed0",
        "pendulum/rpe-lr0.0001/seed0", "pendulum/rpe-lr0.001/seed0",
    ]  # fmt: skip
    assert [r.config.learner.lr for r in spec.runs] == [1e-4, 1e-3] * 2
    assert {r.config.learner.units for r in spec.runs} == {8}
    data["sweep"]["rpe"] = {"kappa": [10.0, -1.0]}
    with pytest.raises(ValueError, match=r"^spec: sweep\.rpe\.kappa: kappa must be"):
        parse_spec(data)


def test_a_method_the_sweep_does_not_name_keeps_its_plain_folder() -> None:
    spec = parse_spec(with_sweep({"equal_budget": False, "rpe": {"eps": [0.1, 0.3]}}))
    keys = [r.key for r in spec.runs if r.seed == 100]
    assert keys == ["Pendulum-v1/ppo/seed100", "Pendulum-v1/rpe-eps0.1/seed100",
                    "Pendulum-v1/rpe-eps0.3/seed100"]  # fmt: skip


def test_a_grid_without_a_sweep_writes_its_committed_grid_json_byte_for_byte(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(ROOT)  # the spec's path as the committed grid.json records it
    spec = load_spec("experiments/batch-mujoco.toml")
    assert spec.sweep is None and all(r.setting == () for r in spec.runs)
    assert write_grid_summary(tmp_path, spec)
    committed = ROOT / "results" / "batch-mujoco" / "grid.json"
    assert (tmp_path / "grid.json").read_bytes() == committed.read_bytes()


def test_folder_names_of_values() -> None:
    assert [value_text(v) for v in (0.1, 3e-4, 1e-5, 1e-3, 2, True, False, "tanh")] == [
        "0.1", "0.0003", "1e-05", "0.001", "2", "true", "false", "tanh"
    ]  # fmt: skip
    assert value_text(0.1 + 0.2) != value_text(0.3)  # distinct floats, distinct folders
    assert cell_name("rb", (("eta", 0.3), ("lr", 1e-3))) == "rb-eta0.3-lr0.001"
    assert cell_name("ppo", ()) == "ppo"


def surrogate_error(method: str, **params: float) -> str:
    with pytest.raises(ValueError) as info:
        check_surrogate_params(method, **params)
    return str(info.value)


REFUSALS = [
    # (the sweep, the start of the one line, the message of the config's own check or None)
    ({"trpo": {"eps": [0.1]}}, "sweep.trpo: unknown method", None),
    ({"rb": {"eps": [0.1]}}, "sweep.rb: the method is not in the spec's methods", None),
    ({"colour": 3, "ppo": GRID, "rpe": GRID}, "sweep.colour: unknown field", None),
    ({"ppo": {"eps": []}, "rpe": {"eps": []}}, "sweep.ppo.eps: must be a non-empty list", None),
    ({"ppo": {"eps": 0.1}, "rpe": {"eps": [0.1]}}, "sweep.ppo.eps: must be a non-empty list",
     None),
    ({"ppo": {"eps": [0.1, 0.1]}, "rpe": GRID}, "sweep.ppo.eps: a list without repeats", None),
    ({"ppo": {"eps": [[0.1]]}, "rpe": {"eps": [0.1]}}, "sweep.ppo.eps: values must be", None),
    ({"ppo": {"colour": [1]}, "rpe": {"eps": [0.1]}},
     "sweep.ppo.colour: unknown field(s) ['colour'] of BatchConfig", None),
    ({"ppo": {"seed": [1]}, "rpe": {"eps": [0.1]}}, "sweep.ppo.seed: not a learner setting",
     None),
    ({"ppo": {"method": ["rpe"]}, "rpe": {"eps": [0.1]}},
     "sweep.ppo.method: not a learner setting", None),
    ({"ppo": {"eps": [0.1, 0.0]}, "rpe": TWO}, "sweep.ppo.eps: ", ("ppo", {"eps": 0.0})),
    ({"ppo": {"eps": [0.1, 1.0]}, "rpe": TWO}, "sweep.ppo.eps: ", ("ppo", {"eps": 1.0})),
    ({"ppo": {"lr": [3e-4, 0.0]}, "rpe": TWO}, "sweep.ppo.lr: lr must be a finite number > 0",
     None),
    ({"ppo": {"lr": [-1e-3]}, "rpe": {"lr": [1e-3]}}, "sweep.ppo.lr: lr must be", None),
    # beta (1 + eps) >= 1: beta 0.9 refused with the spec's eps 0.2 ...
    ({"ppo": {"eps": [0.1]}, "rpe": {"beta": [0.9]}}, "sweep.rpe.beta: ",
     ("rpe", {"eps": 0.2, "beta": 0.9})),
    # ... and beta 0.7 with eps 0.5 only together: both fields named
    ({"ppo": {"eps": [0.1]}, "rpe": {"eps": [0.5], "beta": [0.7]}}, "sweep.rpe.eps and beta: ",
     ("rpe", {"eps": 0.5, "beta": 0.7})),
    ({"ppo": GRID, "rpe": {"eps": [0.1, 0.2]}}, "sweep.rpe: 2 setting(s), but ppo has 4", None),
    ({"equal_budget": "no", "ppo": GRID, "rpe": GRID}, "sweep.equal_budget: must be true", None),
    ({"select": "best", "ppo": GRID, "rpe": GRID}, "sweep.select: must be '<statistic>:<metric>'",
     None),
    ({"select": "median:score", "ppo": GRID, "rpe": GRID}, "sweep.select: must be", None),
    ({"evaluation_seeds": [0, 101], "ppo": GRID, "rpe": GRID},
     "sweep.evaluation_seeds: seeds [101] are tuning seeds", None),
    ({"evaluation_seeds": 0, "ppo": GRID, "rpe": GRID}, "sweep.evaluation_seeds: must be", None),
]  # fmt: skip


IDS = [r[1].split(":")[0] + f"-{i}" for i, r in enumerate(REFUSALS)]


@pytest.mark.parametrize(("sweep", "start", "check"), REFUSALS, ids=IDS)
def test_a_bad_sweep_is_refused_naming_the_method_and_the_field(
    sweep: dict[str, Any], start: str, check: tuple[str, dict[str, float]] | None
) -> None:
    with pytest.raises(ValueError) as info:
        parse_spec(with_sweep(sweep))
    line = str(info.value)
    assert line.startswith("spec: " + start), line
    assert "\n" not in line
    if check is not None:  # the config's own check of the values, word for word
        method, params = check
        assert line.endswith(surrogate_error(method, **params)), line


def test_unequal_budgets_are_allowed_when_the_spec_says_so() -> None:
    spec = parse_spec(with_sweep({"equal_budget": False, "ppo": GRID, "rpe": {"eps": [0.1]}}))
    assert len([r for r in spec.runs if r.method == "ppo"]) == 4 * 2
    assert len([r for r in spec.runs if r.method == "rpe"]) == 1 * 2


def test_a_task_cannot_set_a_swept_field() -> None:
    data = with_sweep({"ppo": GRID, "rpe": GRID})
    data["tasks"][0]["learner"] = {"lr": 1e-3}
    with pytest.raises(ValueError, match=r"^spec: tasks\[0\]\.learner: field 'lr' is swept by "
                       r"sweep\.ppo"):  # fmt: skip
        parse_spec(data)


def test_evaluation_seeds_given_as_a_count_are_the_smallest_fresh_ones() -> None:
    spec = parse_spec(with_sweep({"evaluation_seeds": 3, "ppo": GRID, "rpe": GRID}, seeds=[0, 2]))
    assert spec.sweep is not None and spec.sweep.evaluation_seeds == (1, 3, 4)


def test_the_cli_refuses_a_bad_sweep_in_one_line_before_any_folder(tmp_path: Path) -> None:
    spec = tmp_path / "sweep.toml"
    spec.write_text(toml_text(with_sweep({"ppo": {"eps": [0.1, 1.5]}, "rpe": {"eps": [0.1, 0.2]}})))
    out = tmp_path / "out"
    proc = warm_process.run(["reproduce", str(spec), "--out", str(out), "--quiet"], timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        f"pporpe reproduce: error: {spec}: sweep.ppo.eps: eps must be a number in the open "
        "interval (0, 1); got eps=1.5"
    ]
    assert not out.exists()


def test_toml_text_reads_back_equal() -> None:
    data = {
        "name": 'a "quoted" name', "seeds": [0, 1], "flag": True, "tiny": 1e-05, "big": 1e16,
        "learner": {"lr": 3e-4, "eps": 0.1 + 0.2, "policy": "normal"},
        "tasks": [{"env": "a", "steps": 10, "learner": {"lr": 1e-3}}, {"env": "b", "steps": 5}],
        "sweep": {"stage1": ".", "rpe": {"eps": [0.3]}, "rb": {"eta": [0.3], "lr": [0.001]}},
    }  # fmt: skip
    assert tomllib.loads(toml_text(data)) == data


def test_the_tuned_mujoco_study_gives_every_method_the_same_eight_settings() -> None:
    """experiments/tuned-mujoco.toml: 4 methods x 4 tasks x 8 settings x 2 tuning seeds, every
    other setting as experiments/batch-mujoco.toml; evaluation on seeds 0-19."""
    study = load_spec(ROOT / "experiments" / "tuned-mujoco.toml")
    batch = load_spec(ROOT / "experiments" / "batch-mujoco.toml")
    assert study.methods == ["ppo", "rb", "rpe", "spo"] and study.envs == batch.envs
    assert len(study.runs) == 256 and {r.seed for r in study.runs} == {100, 101}
    assert study.sweep is not None and study.sweep.evaluation_seeds == tuple(range(20))
    assert study.sweep.rule == "iqm:mean_return" and study.sweep.equal_budget
    grid = [(("eps", e), ("lr", lr)) for e in (0.1, 0.2, 0.3, 0.5) for lr in (3e-4, 1e-3)]
    settings = {m: list(s) for m, s in study.sweep.settings.items()}
    assert settings == {m: grid for m in study.methods}
    anchor = {(r.env, r.method): r.config for r in batch.runs if r.seed == 0}
    for run in study.runs:
        cfg = run.config
        base = anchor.get((run.env, run.method), anchor[(run.env, "ppo")])
        assert shared(cfg) == shared(base)
        assert (cfg.eps, cfg.lr) == tuple(v for _, v in run.setting)


def shared(cfg: Any) -> dict[str, Any]:
    """A batch run's settings but those a sweep cell or a seed changes."""
    return {k: v for k, v in dataclasses.asdict(cfg).items()
            if k not in ("seed", "eps", "lr", "method")}  # fmt: skip


def test_the_tuned_mujoco_sweep_is_in_range_for_ppo_rb_and_rpe() -> None:
    """The study's spec without SPO: every value of the sweep is accepted for PPO, PPO-RB
    and PPO-RPE (beta 0.5 with eps 0.5: 0.75 < 1), and the cells are batch-mujoco's runs
    at their settings."""
    data = tomllib.loads((ROOT / "experiments" / "tuned-mujoco.toml").read_text())
    data["methods"].remove("spo")
    del data["sweep"]["spo"]
    study = parse_spec(data, "tuned-mujoco.toml")
    assert len(study.runs) == 3 * 4 * 8 * 2
    batch = load_spec(ROOT / "experiments" / "batch-mujoco.toml")
    anchor = {(r.env, r.method): r.config for r in batch.runs if r.seed == 0}
    for run in study.runs:
        assert shared(run.config) == shared(anchor[(run.env, run.method)])
    assert {(r.config.eps, r.config.lr) for r in study.runs if r.method == "rpe"} == {
        (e, lr) for e in (0.1, 0.2, 0.3, 0.5) for lr in (3e-4, 1e-3)
    }


def test_the_committed_batch_runs_are_the_sweeps_eps_0_2_lr_3e_4_cells(tmp_path: Path) -> None:
    """results/batch-mujoco's runs (seeds 0-9, which no selection sees) are configured as
    the tuned study's eps 0.2 / lr 3e-4 cells on those seeds: a stage 2 that selects that
    setting can take them in (their folders copied under the cell's name) as finished."""
    data = tomllib.loads((ROOT / "experiments" / "tuned-mujoco.toml").read_text())
    data["methods"].remove("spo")
    del data["sweep"]["spo"]
    data["seeds"] = [0, 9]
    data["sweep"]["evaluation_seeds"] = [1]
    study = parse_spec(data, "tuned-mujoco.toml")
    cells = [r for r in study.runs if r.setting == (("eps", 0.2), ("lr", 3e-4))]
    assert len(cells) == 3 * 4 * 2
    for run in cells:
        committed = ROOT / "results" / "batch-mujoco" / run.env / run.method / f"seed{run.seed}"
        copy = tmp_path / run.key
        copy.mkdir(parents=True)
        (copy / "config.json").write_text((committed / "config.json").read_text())
        open_run_dir(copy, config_json(kind_of(run.config), run.config))  # raises if not
