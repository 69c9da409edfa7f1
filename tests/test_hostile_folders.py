"""A run folder from anyone is data, never code (issue 56).

Every hostile folder tried as a new user would (a config.json that imports a module, huge
or deeply nested values, checkpoints that hold only data but are not pporpe's, crafted
numpy dtypes, symbolic links out of the folder) is refused through the CLI in a process of
its own (``pporpe evaluate``, ``pporpe train`` resuming or with ``--force``, ``pporpe report``,
``pporpe reproduce``) and through :func:`pporpe.load_policy`: one line on standard error,
exit status 2, within 10 s of CPU time and 1 GB of memory (counted from the fork of a
process that has imported torch: :mod:`warm_process`; a hang that waits instead of
computing is caught by a wall-clock limit), no marker file, and nothing in the temporary
tree changed (the folder, and the folder outside it that a link points to).
A hypothesis strategy then mutates committed config.json, done.json and evaluation.json
files and checks that every reader refuses in one line or returns a valid result.
"""

from __future__ import annotations

import json
import math
import os
import resource
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import warm_process
from tiny import tiny_grid_toml

import pporpe
from pporpe.config import config_from_dict, config_to_dict
from pporpe.evaluation import load_evaluation
from pporpe.run_files import DONE_FIELDS, read_done
from pporpe.runs.folder import CHECKPOINT, load_checkpoint, read_config

ROOT = Path(__file__).resolve().parent.parent
LIMIT_S = 10
"""CPU seconds a hostile case may take, the interpreter's start included (RLIMIT_CPU: the
machine that runs the suite may be busy, so its wall clock says little)."""
WALL_S = 120
"""Wall-clock seconds after which a hostile case counts as hung."""
LIMIT_BYTES = 2**30
"""Peak resident memory of the CLI's process in a hostile case."""
ADDRESS_SPACE = 2 * 2**30
"""Address space of the CLI's process (RLIMIT_AS): an allocation far beyond
:data:`LIMIT_BYTES` fails at once. (Building a learner reserves just over 1 GiB of address
space for numba's compiler, of which it uses half.)"""
TRAIN_ARGS = ("train", "--env", "pendulum", "--episodes", "3", "--eval-episodes", "0", "--quiet")
"""The run every case starts from (its folder is copied and made hostile)."""


# -- running a case ----------------------------------------------------------------------
LIMITS = {
    resource.RLIMIT_AS: (ADDRESS_SPACE, ADDRESS_SPACE),
    resource.RLIMIT_CPU: (LIMIT_S, LIMIT_S + 1),
}


def cli(*args: str, cwd: Path, pythonpath: Path | None = None) -> warm_process.Finished:
    """``pporpe *args`` in a process of its own (:mod:`warm_process`: forked warm, torch and
    the kernels imported) limited to :data:`LIMIT_S` CPU seconds and
    :data:`ADDRESS_SPACE`, killed as hung after :data:`WALL_S`; its peak resident memory
    is at most :data:`LIMIT_BYTES`."""
    env = dict(os.environ)
    if pythonpath is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(pythonpath), env.get("PYTHONPATH", "")])
    proc = warm_process.run(list(args), cwd=cwd, env=env, limits=LIMITS, timeout=WALL_S)
    assert proc.returncode != -9, f"hung for {WALL_S} s: {proc.stderr[-2000:]}"
    assert proc.cpu_s is not None, f"killed (exit status {proc.returncode}): {proc.stderr[-2000:]}"
    assert proc.cpu_s <= LIMIT_S, "took more than 10 s of CPU time"
    assert proc.max_rss_kb is not None and proc.max_rss_kb * 1024 <= LIMIT_BYTES, (
        f"peak memory {proc.max_rss_kb} kB"
    )
    return proc


def refused(proc: warm_process.Finished, command: str) -> str:
    """The one error line of a refused command (exit status 2)."""
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert len(lines) == 1, proc.stderr[-3000:]
    assert lines[0].startswith(f"pporpe {command}: error: "), lines[0]
    return lines[0]


def snapshot(root: Path) -> dict[str, Any]:
    """Every entry under ``root``: files with their bytes, links with their targets."""
    out: dict[str, Any] = {}
    for folder, dirs, files in os.walk(root, followlinks=False):
        for name in dirs + files:
            path = Path(folder) / name
            rel = str(path.relative_to(root))
            if path.is_symlink():
                out[rel] = ("link", os.readlink(path))
            elif path.is_dir():
                out[rel] = ("folder",)
            else:
                out[rel] = ("file", path.read_bytes())
    return out


# -- the runs the cases start from ------------------------------------------------------
@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A short online run, unfinished (done.json removed), as ``pporpe train`` writes it."""
    run = tmp_path_factory.mktemp("trained") / "run"
    proc = warm_process.run([*TRAIN_ARGS, "--out", str(run)])
    assert proc.returncode == 0, proc.stderr
    (run / "done.json").unlink()
    return run


@pytest.fixture(scope="module")
def batch_checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The checkpoint of a short batch PPO run."""
    from pporpe.batch import BatchConfig

    run = tmp_path_factory.mktemp("batch") / "run"
    cfg = BatchConfig(env="pendulum", total_steps=64, n_steps=32, batch_size=16,
                      eval_episodes=0, layers=1, units=8)  # fmt: skip
    pporpe.train(cfg, run, progress=False)
    return run / CHECKPOINT


# -- the hostile folders ------------------------------------------------------------------
class Reduce:
    """Pickles as ``func(*args)``, then ``state`` set on the result: any call a pickle can
    ask for, made by hand (what a crafted checkpoint holds)."""

    def __init__(self, func: Any, args: tuple[Any, ...], state: Any = None) -> None:
        self.func, self.args, self.state = func, args, state

    def __reduce__(self) -> tuple[Any, ...]:
        return (self.func, self.args) if self.state is None else (self.func, self.args, self.state)


def _array(dtype: Any, shape: tuple[int, ...], data: Any) -> Reduce:
    """A numpy array as numpy pickles one, with any dtype and data."""
    rebuild = np.ndarray.__reduce__(np.zeros(1))[0]  # numpy's _reconstruct
    return Reduce(rebuild, (np.ndarray, (0,), b"b"), (1, shape, dtype, False, data))


OBJECT_DTYPE = Reduce(np.dtype, ("O8", False, True))
"""numpy.dtype('O'), built without its state (which pickle does not require)."""
CRAFTED_DTYPE = Reduce(np.dtype, ("f8", False, True),
                       (3, "|", None, ("a",), {"a": (OBJECT_DTYPE, 0)}, 8, 8, 0))  # fmt: skip
"""A float64 dtype whose state adds a field of objects and says it holds none: reading an
array of it reads 8 arbitrary bytes as a pointer."""


def _set_config(**changes: Any) -> Callable[[Path, Path], None]:
    def make(run: Path, tmp: Path) -> None:
        data = json.loads((run / "config.json").read_text())
        for key, value in changes.items():
            target = data["learner"] if key in data["learner"] else data
            target[key] = value
        (run / "config.json").write_text(json.dumps(data))

    return make


def _module_import(run: Path, tmp: Path) -> None:
    """The run folder holds evil.py and names it as its task's module."""
    (run / "evil.py").write_text(f"open({str(tmp / 'MARKER')!r}, 'w').write('ran')\n")
    _set_config(env=f"{run.name}.evil:Foo-v0")(run, tmp)


def _deep_config(run: Path, tmp: Path) -> None:
    (run / "config.json").write_text("[" * 100_000)


def _checkpoint(state: Any) -> Callable[[Path, Path], None]:
    def make(run: Path, tmp: Path) -> None:
        torch.save(state, run / CHECKPOINT)

    return make


def _edited_checkpoint(edit: Callable[[dict[str, Any]], None]) -> Callable[[Path, Path], None]:
    def make(run: Path, tmp: Path) -> None:
        state = load_checkpoint(run)
        edit(state)
        torch.save(state, run / CHECKPOINT)

    return make


def _wrong_shape(state: dict[str, Any]) -> None:
    state["learner"]["params"] = state["learner"]["params"][:, :3]


def _wrong_kinds(state: dict[str, Any]) -> None:
    state["records"] = ["an episode"]


def _population(state: dict[str, Any]) -> None:
    members = {"run": dict(state)}
    state.clear()
    state.update(runs=["run"], slots=["run"], queue=[], members=members)


def _outside(tmp: Path) -> Path:
    """A folder of the user's outside the run folder, with a file in it."""
    outside = tmp / "outside"
    outside.mkdir(exist_ok=True)
    (outside / "keep.txt").write_text("the user's")
    return outside


def _tensorboard_link(run: Path, tmp: Path) -> None:
    shutil.rmtree(run / "tensorboard", ignore_errors=True)
    (run / "tensorboard").symlink_to(_outside(tmp), target_is_directory=True)


def _evaluation_link(run: Path, tmp: Path) -> None:
    (run / "evaluation.json").symlink_to(_outside(tmp) / "keep.txt")


RECORD = {
    "episode": 0,
    "total_steps": 1,
    "ret": 0.0,
    "length": 1,
    "wall_time": 0.0,
    **dict.fromkeys(("reg_amount", "past_threshold", "trace_decay", "ratio_dev")),
}

CASES: dict[str, tuple[Callable[[Path, Path], None], str]] = {
    # config.json
    "module-import": (_module_import, "names a module to import"),
    "this:Foo-v0": (_set_config(env="this:Foo-v0"), "names a module to import"),
    "units 10**9": (_set_config(units=10**9), "units must be an int in [1, 4,096]"),
    "layers 10**7": (_set_config(layers=10**7), "layers must be an int in [1, 64]"),
    "units 10**30": (_set_config(units=10**30), "got units=an int of 31 digits"),
    "units*units*layers": (_set_config(units=4096, layers=64), "units * units * layers"),
    "seed 10**30": (_set_config(seed=10**30), "seed must be an int in [0, 4,294,967,295]"),
    "steps 10**20": (_set_config(episodes=None, steps=10**20), "steps must be an int in"),
    "deep nesting": (_deep_config, "nests lists or objects more than 32 deep"),
    # checkpoint.pt: data, but not pporpe's
    "object array": (_checkpoint({"records": [], "learner": {}, "x": _array(OBJECT_DTYPE, (1,),
                     [None])}), "is not a safe checkpoint: it holds a numpy value of dtype"),
    "crafted dtype": (_checkpoint({"records": [], "learner": {}, "x": _array(CRAFTED_DTYPE,
                      (1,), b"\x01" * 8)}), "whose state adds fields"),
    "bytes(1 << 30)": (_checkpoint({"records": [], "learner": Reduce(bytes, (1 << 30,))}),
                       "it would call bytes"),
    "no learner": (_checkpoint({"records": [RECORD], "wall_time": 0.0}),
                   "holds no online or batch learner's state"),
    "wrong kinds": (_edited_checkpoint(_wrong_kinds), "records must be a list of episode records"),
    "population checkpoint": (_edited_checkpoint(_population), "is not a run's checkpoint"),
    "wrong shape": (_edited_checkpoint(_wrong_shape), "does not fit this run's config.json"),
    "batch checkpoint": (lambda run, tmp: None, "this folder holds a batch run"),
    # symbolic links out of the folder
    "tensorboard link": (_tensorboard_link, "is a symbolic link"),
    "evaluation.json link": (_evaluation_link, "is a symbolic link"),
}  # fmt: skip
"""Each hostile folder: how it is made from a copy of the trained run, and what the one
line says."""

EVALUATE = [c for c in CASES if c != "tensorboard link"]
RESUME = ["module-import", "units 10**9", "deep nesting", "seed 10**30", "object array",
          "crafted dtype", "bytes(1 << 30)", "no learner", "wrong kinds", "wrong shape",
          "batch checkpoint", "tensorboard link"]  # fmt: skip
LOAD_POLICY = [c for c in CASES if "link" not in c]


def hostile(case: str, tmp: Path, trained: Path, batch_checkpoint: Path) -> Path:
    """A copy of the trained run in ``tmp/<folder>``, made hostile as ``case`` says."""
    run = tmp / "shared_run"
    shutil.copytree(trained, run)
    if case == "batch checkpoint":
        shutil.copyfile(batch_checkpoint, run / CHECKPOINT)
    CASES[case][0](run, tmp)
    return run


DIFFERENT_CONFIG = "holds a run with a different config"
"""What resuming says of a folder whose config.json is another run's (the values in it are
compared as data, never built)."""
RESUME_SAYS = {"module-import": DIFFERENT_CONFIG, "units 10**9": DIFFERENT_CONFIG,
               "seed 10**30": DIFFERENT_CONFIG}  # fmt: skip


def check_refused(proc: warm_process.Finished, command: str, case: str) -> None:
    line = refused(proc, command)
    says = RESUME_SAYS.get(case, CASES[case][1]) if command == "train" else CASES[case][1]
    assert says in line, line
    assert "Beautiful is better than ugly" not in proc.stdout + proc.stderr  # import this


@pytest.mark.parametrize("case", EVALUATE)
def test_evaluate_refuses_a_hostile_folder(
    tmp_path: Path, trained: Path, batch_checkpoint: Path, case: str
) -> None:
    run = hostile(case, tmp_path, trained, batch_checkpoint)
    before = snapshot(tmp_path)
    proc = cli("evaluate", run.name, "--episodes", "1", cwd=tmp_path, pythonpath=tmp_path)
    check_refused(proc, "evaluate", case)
    assert not (tmp_path / "MARKER").exists()
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("case", RESUME)
def test_resuming_a_hostile_folder_is_refused(
    tmp_path: Path, trained: Path, batch_checkpoint: Path, case: str
) -> None:
    run = hostile(case, tmp_path, trained, batch_checkpoint)
    before = snapshot(tmp_path)
    proc = cli(*TRAIN_ARGS, "--out", run.name, cwd=tmp_path, pythonpath=tmp_path)
    check_refused(proc, "train", case)
    assert not (tmp_path / "MARKER").exists()
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("case", LOAD_POLICY)
def test_load_policy_refuses_a_hostile_folder(
    tmp_path: Path, trained: Path, batch_checkpoint: Path, case: str,
    monkeypatch: pytest.MonkeyPatch,
) -> None:  # fmt: skip
    run = hostile(case, tmp_path, trained, batch_checkpoint)
    monkeypatch.syspath_prepend(str(tmp_path))  # the folder's parent is importable
    before = snapshot(tmp_path)
    t0 = time.perf_counter()
    with pytest.raises(ValueError) as info:
        pporpe.load_policy(run)
    assert time.perf_counter() - t0 < LIMIT_S
    assert "\n" not in str(info.value) and CASES[case][1] in str(info.value)
    assert str(run) in str(info.value)  # the file (or the folder) is named
    assert not (tmp_path / "MARKER").exists()
    assert "shared_run.evil" not in sys.modules
    assert snapshot(tmp_path) == before


def test_force_refuses_a_linked_tensorboard_and_removes_nothing(
    tmp_path: Path, trained: Path, batch_checkpoint: Path
) -> None:
    """``--force`` checks every file it removes first: with ``tensorboard/`` a link to a
    folder of the user's, nothing is removed, in the run folder or outside it."""
    run = hostile("tensorboard link", tmp_path, trained, batch_checkpoint)
    before = snapshot(tmp_path)
    proc = cli(*TRAIN_ARGS, "--out", run.name, "--force", cwd=tmp_path)
    line = refused(proc, "train")
    assert f"{run.name}/tensorboard is a symbolic link" in line
    assert snapshot(tmp_path) == before


def test_the_controls_are_live(tmp_path: Path) -> None:
    """What the cases refuse would run or crash without pporpe's checks: the module runs
    when imported, the crafted dtype hides an object field and says it holds none, and
    ``bytes`` takes a size."""
    marker = tmp_path / "MARKER"
    (tmp_path / "evil_control.py").write_text(f"open({str(marker)!r}, 'w').write('ran')\n")
    sys.path.insert(0, str(tmp_path))
    try:
        __import__("evil_control")
    finally:
        sys.path.remove(str(tmp_path))
        sys.modules.pop("evil_control", None)
    assert marker.exists()
    import pickle

    crafted = pickle.loads(pickle.dumps(CRAFTED_DTYPE, protocol=2))
    assert crafted.kind == "f" and crafted.fields is not None and not crafted.hasobject
    assert len(pickle.loads(pickle.dumps(Reduce(bytes, (1 << 10,)), protocol=2))) == 1 << 10


def test_a_grid_key_out_of_the_folder_is_refused_by_report(tmp_path: Path) -> None:
    grid = tmp_path / "grid"
    shutil.copytree(ROOT / "results" / "paper-testbed", grid,
                    ignore=shutil.ignore_patterns("*.png", "*.pdf", "seed[1-9]*"))  # fmt: skip
    data = json.loads((grid / "grid.json").read_text())
    data["runs"][0]["key"] = "../outside/seed0"
    (grid / "grid.json").write_text(json.dumps(data))
    _outside(tmp_path)
    before = snapshot(tmp_path)
    line = refused(cli("report", "grid", cwd=tmp_path), "report")
    assert "a run's key must be a relative path inside the grid folder" in line
    assert snapshot(tmp_path) == before


def test_a_grid_writes_through_no_linked_run_folder(tmp_path: Path) -> None:
    """``pporpe reproduce`` into a folder whose task folder is a link out of it: refused
    before anything is written."""
    (tmp_path / "tiny.toml").write_text(tiny_grid_toml())
    (tmp_path / "grid").mkdir()
    (tmp_path / "grid" / "pendulum").symlink_to(_outside(tmp_path), target_is_directory=True)
    before = snapshot(tmp_path)
    proc = cli("reproduce", "tiny.toml", "--out", "grid", "--workers", "1", "--quiet",
               cwd=tmp_path)  # fmt: skip
    assert "grid/pendulum is a symbolic link" in refused(proc, "reproduce")
    assert snapshot(tmp_path) == before


def test_a_deep_done_json_is_refused_on_resume(tmp_path: Path, trained: Path) -> None:
    run = tmp_path / "run"
    shutil.copytree(trained, run)
    (run / "done.json").write_text('{"a": ' * 100_000)
    before = snapshot(tmp_path)
    line = refused(cli(*TRAIN_ARGS, "--out", "run", cwd=tmp_path), "train")
    assert "done.json nests lists or objects more than 32 deep" in line
    assert snapshot(tmp_path) == before


# -- the documented bounds, the links, the readers ------------------------------------------
BOUNDS = [
    # (config, field, the largest value allowed, what the error says above it)
    ("online", "units", 4096, "units must be an int in [1, 4,096]"),
    ("online", "layers", 64, "layers must be an int in [1, 64]"),
    ("run", "seed", 2**32 - 1, "seed must be an int in [0, 4,294,967,295]"),
    ("run", "episodes", 10**6, "episodes must be an int in [1, 1,000,000]"),
    ("run", "eval_episodes", 10**4, "eval_episodes must be an int in [0, 10,000]"),
    ("batch", "total_steps", 10**9, "total_steps must be an int in [1, 1,000,000,000]"),
    ("batch", "n_envs", 1024, "n_envs must be an int in [1, 1,024]"),
    ("batch", "seed", 2**32 - 1, "seed must be an int in [0, 4,294,967,295]"),
]


def _config(which: str, **kw: Any) -> Any:
    from pporpe.batch import BatchConfig
    from pporpe.online import OnlineConfig, TrainConfig

    if which == "online":
        return OnlineConfig(**{"units": 1, "layers": 1, **kw})
    if which == "batch":
        return BatchConfig(**{"units": 1, "layers": 1, "n_steps": 1, "batch_size": 1, **kw})
    return TrainConfig(**kw)


@pytest.mark.parametrize(("which", "field", "most", "says"), BOUNDS)
def test_each_bound_admits_its_value_and_refuses_the_next(
    which: str, field: str, most: int, says: str
) -> None:
    assert getattr(_config(which, **{field: most}), field) == most
    with pytest.raises(ValueError) as info:
        _config(which, **{field: most + 1})
    assert str(info.value) == f"{says}; got {field}={most + 1}"


def test_the_weights_of_a_network_are_bounded_together() -> None:
    """units * units * layers <= 2**24: 2048 x 4 is at the bound, 2048 x 5 past it, though
    each is within its own bound."""
    assert _config("online", units=2048, layers=4).layers == 4
    with pytest.raises(ValueError, match=r"units \* units \* layers must be at most 16,777,216"):
        _config("online", units=2048, layers=5)
    with pytest.raises(ValueError, match=r"n_envs \* n_steps must be at most 1,048,576"):
        _config("batch", n_envs=1024, n_steps=1025)


def test_the_cli_refuses_a_bound_in_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    from pporpe.cli import main

    assert main(["train", "--out", "unused", "--units", "5000", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["pporpe train: error: units must be an int in [1, 4,096]; got units=5000"]


def test_no_writer_replaces_a_link_and_force_removes_nothing_then(tmp_path: Path) -> None:
    from pporpe.io import atomic_write_text
    from pporpe.runs.folder import clear_run_dir

    outside = _outside(tmp_path)
    run = tmp_path / "run"
    (run / "tensorboard" / "events").mkdir(parents=True)
    (run / "config.json").write_text("{}")
    (run / "tensorboard" / "events" / "deep").symlink_to(outside / "keep.txt")
    (run / "evaluation.json").symlink_to(outside / "keep.txt")
    before = snapshot(tmp_path)
    with pytest.raises(ValueError, match=r"evaluation\.json is a symbolic link"):
        atomic_write_text(run / "evaluation.json", "{}")
    assert snapshot(tmp_path) == before
    (run / "evaluation.json").unlink()
    before = snapshot(tmp_path)
    with pytest.raises(ValueError, match=r"events/deep is a symbolic link.*run again$"):
        clear_run_dir(run)  # a link two folders down in tensorboard/: nothing removed
    assert snapshot(tmp_path) == before


def test_a_fifo_or_a_huge_number_is_one_line_and_no_wait(tmp_path: Path) -> None:
    from pporpe.run_files import read_json

    os.mkfifo(tmp_path / "done.json")  # opening it for reading would wait for a writer
    with pytest.raises(ValueError, match=r"done\.json is not a regular file"):
        read_done(tmp_path)
    (tmp_path / "x.json").write_text("1" * 5000)
    with pytest.raises(ValueError, match=r"x.json cannot be read \(Exceeds the limit"):
        read_json(tmp_path / "x.json")


# -- the committed runs still load, as they are ----------------------------------------
def _holds(full: dict[str, Any], part: dict[str, Any]) -> bool:
    """Whether ``full`` has every setting of ``part`` at its value (a setting added since a
    run was written is filled in: :mod:`pporpe.runs.migrate`)."""
    return all(
        _holds(full[k], v) if isinstance(v, dict) else full.get(k) == v for k, v in part.items()
    )


COMMITTED = sorted(p.parent for p in (ROOT / "results").glob("*/*/*/seed*/done.json"))


def test_every_committed_run_folder_reads_as_it_is() -> None:
    """Every committed run's config.json, done.json and evaluation.json pass the schemas and
    read as written: the settings round-trip, the scores are the stored medians."""
    assert len(COMMITTED) >= 600
    for run in COMMITTED:
        kind, cfg = read_config(run)
        raw = json.loads((run / "config.json").read_text())
        assert kind.name == raw["kind"]
        assert _holds(config_to_dict(cfg), {k: v for k, v in raw.items() if k != "kind"})
        assert read_done(run) == json.loads((run / "done.json").read_text())
        stored = json.loads((run / "evaluation.json").read_text())
        evaluation = load_evaluation(run)
        assert evaluation is not None and evaluation.returns == stored["returns"]
        assert evaluation.median == stored["median"]


# -- fuzzing the committed files -----------------------------------------------------------
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

SAMPLES = {
    "config.json": [COMMITTED[0], COMMITTED[-1]],  # a batch run's and an online run's
    "done.json": [COMMITTED[0], COMMITTED[-1]],
    "evaluation.json": [COMMITTED[0]],
}
"""The committed files the fuzzer mutates (a run of results/batch-mujoco and one of
results/paper-testbed)."""


def _deep(depth: int) -> Any:
    value: Any = 0
    for _ in range(depth):
        value = [value]
    return value


HOSTILE_VALUES = st.one_of(
    st.sampled_from([None, True, -1, 0, 2**63, 10**30, -(10**400), 1e308, math.inf, math.nan,
                     "", "x" * 100_000, "os:system", "this:Foo-v0", "inf", [], {}, [1, 2, 3],
                     {"a": 1}, _deep(40), _deep(500)]),
    st.integers(), st.floats(), st.text(max_size=20),
    st.lists(st.integers(), max_size=5), st.dictionaries(st.text(max_size=5), st.integers(),
                                                          max_size=3),
)  # fmt: skip
"""Values of every type and size that a field of a hostile file might hold."""


def _paths(value: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """Every place in a parsed JSON value (the keys and indices that lead to it)."""
    out = [prefix]
    if isinstance(value, dict):
        for key, item in value.items():
            out += _paths(item, (*prefix, key))
    elif isinstance(value, list):
        for i, item in enumerate(value[:3]):
            out += _paths(item, (*prefix, i))
    return out


@st.composite
def mutated(draw: st.DrawFn, name: str, how: str) -> tuple[Path, Any]:
    """A committed file ``name``, parsed, mutated ``how``: one place replaced by a hostile
    value, an unknown key added to an object, or a key removed from one: (its run folder,
    the mutated value)."""
    run = draw(st.sampled_from(SAMPLES[name]))
    data = json.loads((run / name).read_text())
    places = [p for p in _paths(data) if how == "replace" or isinstance(_at(data, p), dict)]
    place = draw(st.sampled_from(places))
    if how == "replace" and not place:
        return run, draw(HOSTILE_VALUES)
    target = _at(data, place[:-1]) if how == "replace" else _at(data, place)
    if how == "replace":
        target[place[-1]] = draw(HOSTILE_VALUES)
    elif how == "add key":
        target["x_" + draw(st.text(max_size=10))] = draw(HOSTILE_VALUES)
    elif target:
        del target[draw(st.sampled_from(sorted(target)))]
    return run, data


def _at(value: Any, place: tuple[Any, ...]) -> Any:
    for key in place:
        value = value[key]
    return value


def _read(name: str, run: Path) -> Any:
    if name == "config.json":
        return read_config(run)
    if name == "done.json":
        return read_done(run)
    return load_evaluation(run)


@pytest.fixture(scope="module")
def readers_warm() -> None:
    """Every reader run once (the first reads import the task registry), so that each
    example's time is its own."""
    for name in SAMPLES:
        _read(name, SAMPLES[name][0])


@pytest.mark.parametrize("how", ["replace", "add key", "remove key"])
@pytest.mark.parametrize("name", sorted(SAMPLES))
@settings(max_examples=40, deadline=2000, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_a_mutated_committed_file_is_refused_in_one_line_or_read_as_valid(
    readers_warm: None, name: str, how: str, data: st.DataObject
) -> None:
    """Each example within 2 s (hypothesis' deadline): a clean refusal, or a valid result
    (an unknown field is never accepted)."""
    source, mutation = data.draw(mutated(name, how))
    with tempfile.TemporaryDirectory() as tmp:
        run = Path(tmp) / "run"
        shutil.copytree(source, run, ignore=shutil.ignore_patterns("*.csv"))
        (run / name).write_text(json.dumps(mutation, allow_nan=True))
        try:
            got = _read(name, run)
        except ValueError as exc:
            assert "\n" not in str(exc) and str(run) in str(exc)
            return
    assert how != "add key", "an unknown field was accepted"
    if name == "config.json":
        kind, cfg = got
        assert ":" not in cfg.env
        assert config_from_dict(kind.config_type, config_to_dict(cfg)) == cfg
    elif name == "done.json":
        assert set(got) <= set(DONE_FIELDS) and got == mutation
    else:
        assert got.returns == mutation["returns"]
