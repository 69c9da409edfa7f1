"""A grid that cannot run is refused before any work, with one line naming what is wrong
and where: a task the learners cannot use, a setting in the spec's own section, an
``--out`` that is a file."""

from __future__ import annotations

from pathlib import Path

import pytest
import warm_process
from tiny import tiny_grid_toml

from pporpe.experiments.grids.spec import parse_spec

SPEC = tiny_grid_toml(episodes=2, checkpoint_every=None)


def reproduce(spec: Path, out: Path) -> tuple[int, str]:
    proc = warm_process.run(["reproduce", str(spec), "--out", str(out), "--quiet"], timeout=300)
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    return proc.returncode, lines[0]


def test_a_task_with_discrete_actions_is_refused_before_any_folder(tmp_path: Path) -> None:
    spec = tmp_path / "cartpole.toml"
    spec.write_text(SPEC.replace('"pendulum"', '"CartPole-v1"'))
    out = tmp_path / "out"
    code, line = reproduce(spec, out)
    assert code == 2
    assert line.startswith(
        f"pporpe reproduce: error: {spec}: task 'CartPole-v1': environment 'CartPole-v1' has "
        "action space Discrete(2), but a gymnasium.spaces.Box"
    )
    assert not out.exists()  # no run folder, .lock, error.txt, grid.json or status.json


def test_a_task_gymnasium_no_longer_builds_names_the_spec_and_the_task(tmp_path: Path) -> None:
    """Hopper-v3 is registered, but building it raises an ImportError (moved to
    gymnasium-robotics): the line named neither the spec nor the task."""
    spec = tmp_path / "old.toml"
    spec.write_text(SPEC.replace('"pendulum"', '"Hopper-v3"'))
    out = tmp_path / "out"
    code, line = reproduce(spec, out)
    assert code == 2
    assert line.startswith(f"pporpe reproduce: error: {spec}: task 'Hopper-v3': "), line
    assert not out.exists()


def test_an_out_that_is_a_file_is_named_as_train_names_it(tmp_path: Path) -> None:
    spec = tmp_path / "tiny.toml"
    spec.write_text(SPEC)
    out = tmp_path / "results"
    out.write_text("not a folder")
    code, line = reproduce(spec, out)
    assert (code, line) == (
        2,
        f"pporpe reproduce: error: the results folder {out} is an existing file; "
        "choose another --out",
    )
    assert out.read_text() == "not a folder"


def spec_with(learner: dict[str, float], task_learner: dict[str, float]) -> dict[str, object]:
    task: dict[str, object] = {"env": "pendulum", "episodes": 2}
    if task_learner:
        task["learner"] = task_learner
    return {"methods": ["rpe"], "seeds": 1, "learner": learner, "tasks": [task]}


@pytest.mark.parametrize(
    ("learner", "task_learner", "section"),
    [
        ({"eps": 2.0}, {}, "spec: learner: eps"),  # was reported as tasks[0].learner
        ({"eps": 2.0}, {"beta": 0.5}, "spec: learner: eps"),
        ({"eps": 0.2}, {"eps": 3.0}, r"spec: tasks\[0\]\.learner: eps"),
        ({}, {"eps": 3.0}, r"spec: tasks\[0\]\.learner: eps"),
    ],
)
def test_a_bad_learner_setting_names_the_section_it_is_in(
    learner: dict[str, float], task_learner: dict[str, float], section: str
) -> None:
    with pytest.raises(ValueError, match=f"^{section} must be a number in the open interval"):
        parse_spec(spec_with(learner, task_learner))
    assert parse_spec(spec_with(learner, {"eps": 0.2})).runs[0].config.learner.eps == 0.2
