"""Checkpoints are read as data, never as code: a ``checkpoint.pt`` whose pickle would call
a function (here ``os.system``, creating a marker file) is refused by every command that
reads checkpoints, with one line naming the file, and the function never runs. Every
checkpoint pporpe writes, and those of earlier versions, still load."""

from __future__ import annotations

import os
import shutil
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import warm_process
from tiny import tiny_grid_toml

import pporpe
from pporpe.experiments.grids.planning import plan_jobs
from pporpe.experiments.grids.spec import load_spec
from pporpe.runs.checkpoint_data import PPORPE_GLOBALS
from pporpe.runs.folder import (
    CHECKPOINT,
    config_json,
    load_checkpoint,
    open_run_dir,
    save_checkpoint,
)
from pporpe.runs.kinds import kind_of

FIXTURES = Path(__file__).parent / "fixtures"


class _Payload:
    """Unpickled by full pickle, this runs ``touch MARKER``."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[Any, tuple[str]]:
        return os.system, (f"touch {self.marker}",)


def plant(path: Path, marker: Path, legacy: bool = False) -> None:
    """A checkpoint that looks like pporpe's and runs ``touch marker`` when unpickled."""
    state = {"records": [], "wall_time": 0.0, "learner": _Payload(marker)}
    torch.save(state, path, _use_new_zipfile_serialization=not legacy)


def cli(*args: str, cwd: Path | None = None) -> warm_process.Finished:
    """``pporpe ARGS`` in a process of its own (:mod:`warm_process`)."""
    return warm_process.run(list(args), cwd=cwd, timeout=300)


def one_error_line(proc: warm_process.Finished, command: str) -> str:
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith(f"pporpe {command}: error: ")
    return lines[0]


def listing(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def test_the_planted_checkpoint_runs_its_code_when_fully_unpickled(tmp_path: Path) -> None:
    """The control: the payload is live (what ``weights_only=False`` used to do)."""
    marker = tmp_path / "marker"
    plant(tmp_path / CHECKPOINT, marker)
    torch.load(tmp_path / CHECKPOINT, weights_only=False)
    assert marker.exists()


@pytest.mark.parametrize("legacy", [False, True], ids=["zip", "legacy-format"])
def test_load_checkpoint_and_load_policy_refuse_code(tmp_path: Path, legacy: bool) -> None:
    run = tmp_path / "run"
    shutil.copytree(FIXTURES / "run_v0_1_online", run)
    marker = tmp_path / "marker"
    plant(run / CHECKPOINT, marker, legacy)
    for read in (load_checkpoint, pporpe.load_policy):
        with pytest.raises(ValueError, match="is not a safe checkpoint") as info:
            read(run)
        assert str(run / CHECKPOINT) in str(info.value) and "\n" not in str(info.value)
        assert "posix.system" in str(info.value)
    assert not marker.exists()


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A short online run, unfinished (its done.json removed) so that train resumes it."""
    run = tmp_path_factory.mktemp("trained") / "run"
    proc = cli(*TRAIN_ARGS, "--out", str(run))
    assert proc.returncode == 0, proc.stderr
    (run / "done.json").unlink()
    return run


TRAIN_ARGS = ("train", "--env", "pendulum", "--episodes", "3", "--eval-episodes", "0", "--quiet")


@pytest.mark.parametrize("command", ["evaluate", "train"])
def test_evaluate_and_resumed_train_refuse_code(
    tmp_path: Path, trained_run: Path, command: str
) -> None:
    run = tmp_path / "run"
    shutil.copytree(trained_run, run)
    marker = tmp_path / "marker"
    plant(run / CHECKPOINT, marker)
    before = listing(run)
    if command == "evaluate":
        proc = cli("evaluate", str(run), "--episodes", "2")
    else:
        proc = cli(*TRAIN_ARGS, "--out", str(run))
    line = one_error_line(proc, command)
    assert proc.returncode == 2
    assert f"{run / CHECKPOINT} is not a safe checkpoint" in line
    assert not marker.exists()
    assert listing(run) == before  # nothing written: no evaluation.json, no records


GRID = tiny_grid_toml()


@pytest.mark.parametrize("where", ["run", "population"])
def test_a_grid_refuses_code_before_any_work(tmp_path: Path, where: str) -> None:
    """A run folder's checkpoint, or a population's, that would run code stops the grid
    before anything is trained or written."""
    spec_path = tmp_path / "tiny.toml"
    spec_path.write_text(GRID)
    spec = load_spec(spec_path)
    out = tmp_path / "out"
    todo = [(out / run.key, run.config) for run in spec.runs]
    for run_dir, cfg in todo:
        open_run_dir(run_dir, config_json(kind_of(cfg), cfg))
    (job,) = plan_jobs(todo, out.resolve(), 4, 1)
    target = Path(job.home if where == "population" else job.runs[1][0]) / CHECKPOINT
    target.parent.mkdir(parents=True, exist_ok=True)
    marker = tmp_path / "marker"
    plant(target, marker)
    before = listing(out)
    args = ("--out", str(out), "--workers", "1", "--population", "4", "--quiet")
    proc = cli("reproduce", str(spec_path), *args)
    line = one_error_line(proc, "reproduce")
    assert proc.returncode == 2
    assert f"{target} is not a safe checkpoint" in line
    assert not marker.exists()
    assert listing(out) == before  # no grid.json, status.json, .lock or records


DATA = {
    "empty array": np.zeros((0,), np.float32),  # an episode's replay before its first action
    "empty 2-d": np.zeros((0, 3)),
    "array": np.arange(6, dtype=np.int64)[::2],
    "fortran": np.asfortranarray(np.ones((2, 2))),
    "0-d": np.array(2.5),
    "bool array": np.zeros(3, np.bool_),
    "complex": np.ones(2, np.complex64),
    "numpy scalars": [np.float64(0.5), np.float32(1.5), np.int64(3), np.bool_(True)],
    "bit generator": np.random.default_rng(0).bit_generator.state,
    "torch rng": torch.get_rng_state(),
    "plain": [b"", b"abc", (1, 2), 10**40, None, float("inf"), "text"],
}


@pytest.mark.parametrize("name", list(DATA))
def test_the_data_checkpoints_hold_loads_as_it_was_saved(tmp_path: Path, name: str) -> None:
    """What run states hold (numpy arrays of every shape, numpy scalars, random states)
    loads back equal and of the same types."""
    save_checkpoint(tmp_path / CHECKPOINT, {"records": [], "value": DATA[name]})
    got = load_checkpoint(tmp_path)["value"]
    want = DATA[name]
    assert type(got) is type(want) and repr(got) == repr(want)
    if isinstance(want, np.ndarray):
        assert got.dtype == want.dtype and np.array_equal(got, want)


def test_numpy_object_arrays_are_refused(tmp_path: Path) -> None:
    """Object arrays could hold anything; no run state has one."""
    save_checkpoint(tmp_path / CHECKPOINT, {"records": [], "value": np.array([1, "a"], object)})
    with pytest.raises(ValueError, match="is not a safe checkpoint"):
        load_checkpoint(tmp_path)


def test_checkpoints_written_under_numpy_1_still_load(tmp_path: Path) -> None:
    """numpy 1.x pickles its arrays' functions as ``numpy.core.multiarray``; a batch run's
    checkpoint (observation statistics as numpy arrays) so written loads the same."""
    run = tmp_path / "run"
    shutil.copytree(FIXTURES / "run_v0_1_batch", run)
    path = run / CHECKPOINT
    with zipfile.ZipFile(path) as src:
        entries = [(info, src.read(info)) for info in src.infolist()]
    renamed = False
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as dst:
        for info, data in entries:
            if info.filename.endswith("data.pkl"):
                renamed = b"numpy._core.multiarray" in data
                data = data.replace(b"numpy._core.multiarray", b"numpy.core.multiarray")
            dst.writestr(info, data)
    assert renamed
    got = load_checkpoint(run)
    want = load_checkpoint(FIXTURES / "run_v0_1_batch")
    rms, ref = got["learner"]["normalizer"]["obs_rms"], want["learner"]["normalizer"]["obs_rms"]
    assert isinstance(rms["mean"], np.ndarray) and np.array_equal(rms["mean"], ref["mean"])
    assert pporpe.load_policy(run).config == pporpe.load_policy(FIXTURES / "run_v0_1_batch").config


class _Call:
    """Pickles as ``func(*args)``: a call a crafted checkpoint may ask for."""

    def __init__(self, func: Any, *args: Any) -> None:
        self.func, self.args = func, args

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        return self.func, self.args


@pytest.mark.parametrize(
    ("value", "says"),
    [
        (np.zeros(2, [("a", "f8"), ("b", "i4")]), "is not a safe checkpoint: it holds a numpy"),
        (np.array(["text"]), "is not a safe checkpoint: it holds a numpy value of dtype"),
        (_Call(bytearray, 1 << 30), "it would call builtins.bytearray"),
        (_Call(bytes, 1 << 30), "it would call bytes(1073741824,)"),
        ({1, 2}, "it would call builtins.set"),
    ],
    ids=["structured", "strings", "bytearray", "bytes(n)", "set"],
)
def test_what_no_run_state_holds_is_refused(tmp_path: Path, value: Any, says: str) -> None:
    """The allow-list admits numbers only: no record, string or object dtype, no call of
    ``bytes`` with a size, nothing outside ``PPORPE_GLOBALS`` (``bytearray``, sets)."""
    assert "builtins.bytearray" not in PPORPE_GLOBALS and "builtins.bytes" in PPORPE_GLOBALS
    torch.save({"records": [], "value": value}, tmp_path / CHECKPOINT)
    with pytest.raises(ValueError) as info:
        load_checkpoint(tmp_path)
    assert says in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize("dtype", ["?", "i1", "u2", "<i4", ">i8", "<f2", ">f4", "f8", "c8", "c16"])
def test_arrays_of_every_number_type_and_byte_order_load_as_saved(
    tmp_path: Path, dtype: str
) -> None:
    want = (np.arange(6) % 2 == 1 if dtype == "?" else np.arange(6)).astype(dtype).reshape(2, 3)
    save_checkpoint(tmp_path / CHECKPOINT, {"records": [], "a": want, "s": want[0, 1]})
    got = load_checkpoint(tmp_path)
    assert got["a"].dtype == want.dtype and np.array_equal(got["a"], want)
    assert type(got["s"]) is type(want[0, 1]) and got["s"] == want[0, 1]


def test_a_compressed_checkpoint_is_refused_unread(tmp_path: Path) -> None:
    """pporpe stores its checkpoints' entries uncompressed: a compressed one (a zip bomb
    would be) is refused before anything is decompressed."""
    save_checkpoint(tmp_path / CHECKPOINT, {"records": [], "a": np.zeros(1000)})
    path = tmp_path / CHECKPOINT
    with zipfile.ZipFile(path) as src:
        entries = [(info.filename, src.read(info)) for info in src.infolist()]
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as dst:
        for name, data in entries:
            dst.writestr(name, data)
    with pytest.raises(ValueError, match=r"cannot be read \(compressed entries"):
        load_checkpoint(tmp_path)
