"""A checkpoint read as data: what its pickle may name, how numpy values are rebuilt, and
the shape of a run's state, checked before anything is built from it.

A ``checkpoint.pt`` may come from someone else, so it is read in four steps, each refusing
with one ``ValueError`` that names the file:

1. the file (:func:`scan_checkpoint`): a regular file of at most
   :data:`~pporpe.limits.MAX_CHECKPOINT_BYTES` in torch's zip format, every entry stored
   uncompressed (no zip bomb), whose pickle names only :data:`PPORPE_GLOBALS`: torch's
   dense tensors and their storages, ``OrderedDict``, bytes, and numpy's array, scalar and
   dtype. Read without running it; anything else (a function such as ``os.system``,
   ``bytearray``, sets, sparse or quantized tensors) is refused;
2. the pickle (:func:`load_data`), by ``torch.load(weights_only=True)`` with numpy's names
   bound to pporpe's own stand-ins: a dtype or an array is recorded, never built from the
   pickle's state, and ``bytes`` only makes an empty one (``bytes(1 << 30)`` is refused);
3. the values (:func:`plain_data`): containers (dicts, lists, tuples) nested at most
   :data:`~pporpe.limits.MAX_CHECKPOINT_DEPTH` deep, numbers, strings, bytes, dense CPU
   tensors of number types, and numpy arrays and scalars rebuilt from their bytes with a
   dtype of a plain number type (bool, int, uint, float, complex; never an object dtype, a
   structured one, or one whose state hides fields), at most
   :data:`~pporpe.limits.MAX_CHECKPOINT_ELEMENTS` numbers in all;
4. the run state (:func:`check_run_state`): the records, the counters and the learner's
   state of its learner kind, so that a checkpoint of another kind (a batch run's in an
   online run's folder) or of no kind is one line naming the file.
"""

from __future__ import annotations

import math
import os
import stat
import zipfile
from collections import OrderedDict
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..limits import (
    MAX_CHECKPOINT_BYTES,
    MAX_CHECKPOINT_DEPTH,
    MAX_CHECKPOINT_ELEMENTS,
    MAX_STEPS,
    short_repr,
)

__all__ = [
    "PPORPE_GLOBALS",
    "NotData",
    "Unreadable",
    "building_from",
    "check_population_state",
    "check_run_state",
    "load_data",
    "plain_data",
    "scan_checkpoint",
    "state_kind",
]

_STORAGES = ("Float", "Double", "Half", "BFloat16", "Long", "Int", "Short", "Char", "Byte",
             "Bool", "ComplexFloat", "ComplexDouble")  # fmt: skip
_NUMPY_SPELLINGS = ("numpy._core.multiarray", "numpy.core.multiarray")
PPORPE_GLOBALS: frozenset[str] = frozenset(
    {
        "collections.OrderedDict",
        "torch._utils._rebuild_tensor_v2",
        "_codecs.encode",
        "builtins.bytes",
        "numpy.dtype",
        "numpy.ndarray",
        *(f"torch.{name}Storage" for name in _STORAGES),
        *(f"{module}.{name}" for module in _NUMPY_SPELLINGS for name in ("_reconstruct", "scalar")),
    }
)
"""Every name a pporpe checkpoint's pickle may hold: dense tensors (their rebuild function
and storage types), ``OrderedDict``, bytes (``_codecs.encode``, and ``bytes()`` for an empty
one), and numpy's dtype, array and scalar (numpy 1.x spells its functions
``numpy.core.multiarray``). Anything else is refused before the pickle is read."""

_NUMBER_KINDS = "?biufc"
"""numpy dtype kinds a checkpoint may hold: bool, signed and unsigned ints, floats, complex."""
_TENSOR_DTYPES = frozenset({torch.float16, torch.bfloat16, torch.float32, torch.float64,
                            torch.complex64, torch.complex128, torch.bool, torch.uint8,
                            torch.int8, torch.int16, torch.int32, torch.int64})  # fmt: skip


class NotData(ValueError):
    """A checkpoint holds something that is not a pporpe run's data (the message says what)."""


class Unreadable(ValueError):
    """A checkpoint file that is not a readable torch zip file (the message says why)."""


class _DTypeArgs:
    """Stands in for ``numpy.dtype`` while a checkpoint is unpickled: records the type code
    and the state the pickle gives, and builds a dtype only from a plain number type's code
    (:meth:`dtype`), never from the state."""

    spec: Any = None
    state: Any = None

    def __init__(self, spec: Any = None, align: Any = False, copy: Any = True) -> None:
        self.spec = spec

    def __setstate__(self, state: Any) -> None:
        self.state = state

    def dtype(self) -> np.dtype[Any]:
        """The plain number dtype the pickle names (its byte order kept), or ``NotData``."""
        spec, state = self.spec, self.state
        if not isinstance(spec, str) or len(spec) > 8:
            raise NotData(f"it holds a numpy dtype that is no number type ({short_repr(spec)})")
        try:
            dtype = np.dtype(spec)
        except (TypeError, ValueError):
            raise NotData(f"it holds an unknown numpy dtype {spec!r}") from None
        if dtype.kind not in _NUMBER_KINDS or dtype.fields is not None or dtype.subdtype:
            raise NotData(f"it holds a numpy value of dtype {spec!r} (objects or records)")
        order = "|"
        if state is not None:
            if not (isinstance(state, tuple) and len(state) >= 5 and state[2:5] == (None,) * 3):
                raise NotData(f"it holds a numpy dtype {spec!r} whose state adds fields")
            order = state[1]
        if order not in ("<", ">", "|", "="):
            raise NotData(f"it holds a numpy dtype {spec!r} of byte order {short_repr(order)}")
        return dtype.newbyteorder("<" if order == "<" else ">") if order in "<>" else dtype


class _ArrayArgs:
    """Stands in for numpy's ``_reconstruct`` while a checkpoint is unpickled: records the
    array's state, from which :meth:`array` rebuilds it (a copy of its bytes)."""

    args: tuple[Any, ...] = ()
    state: Any = None

    def __init__(self, *args: Any) -> None:
        self.args = args

    def __setstate__(self, state: Any) -> None:
        self.state = state

    def array(self) -> np.ndarray:
        """The array: shape, dtype (:meth:`_DTypeArgs.dtype`), order and bytes checked."""
        if self.args != (_NDARRAY, (0,), b"b"):
            raise NotData("it holds a numpy array pickled otherwise than numpy does")
        state = self.state
        if not (isinstance(state, tuple) and len(state) == 5 and state[0] == 1):
            raise NotData("it holds a numpy array with an unknown state")
        _, shape, dtype_args, fortran, raw = state
        if not isinstance(dtype_args, _DTypeArgs):
            raise NotData("it holds a numpy array without a dtype")
        dtype = dtype_args.dtype()
        ints = isinstance(shape, tuple) and all(type(n) is int and n >= 0 for n in shape)
        if not (ints and len(shape) <= 32 and isinstance(raw, bytes)):
            raise NotData("it holds a numpy array whose shape or data are not ints and bytes")
        if math.prod(shape) * dtype.itemsize != len(raw):
            raise NotData(f"it holds a numpy array of shape {shape} with {len(raw)} bytes")
        flat = np.frombuffer(raw, dtype=dtype)
        array = flat.reshape(shape, order="F") if fortran is True else flat.reshape(shape)
        return array.copy(order="K")


class _NDArrayName:
    """What ``numpy.ndarray`` names in a checkpoint: only an argument of ``_reconstruct``."""


_NDARRAY = _NDArrayName()


def _scalar(dtype_args: Any, raw: Any) -> np.generic:
    """Stands in for numpy's ``scalar``: a numpy scalar from a plain dtype and its bytes."""
    if not isinstance(dtype_args, _DTypeArgs) or not isinstance(raw, bytes):
        raise NotData("it holds a numpy scalar without a dtype and bytes")
    dtype = dtype_args.dtype()
    if len(raw) != dtype.itemsize:
        raise NotData(f"it holds a numpy scalar of dtype {dtype} with {len(raw)} bytes")
    value: np.generic = np.frombuffer(raw, dtype=dtype)[0]
    return value


def _empty_bytes(*args: Any) -> bytes:
    """Stands in for ``bytes``, which pickles of protocol 2 call for an empty ``b""`` only."""
    if args:
        raise NotData(f"it would call bytes{short_repr(args)} (pporpe's hold b'' only)")
    return b""


def _stand_ins() -> list[Any]:
    """numpy's and ``bytes``' names bound to the stand-ins, for ``torch.load``."""
    out: list[Any] = [(_DTypeArgs, "numpy.dtype"), (_NDARRAY, "numpy.ndarray"),
                      (_empty_bytes, "builtins.bytes")]  # fmt: skip
    for module in _NUMPY_SPELLINGS:
        out += [(_ArrayArgs, f"{module}._reconstruct"), (_scalar, f"{module}.scalar")]
    return out


def _globals_in(fh: Any) -> set[str]:
    """The names a pickle stream holds, read without running it (torch's own reader)."""
    from torch._weights_only_unpickler import get_globals_in_pkl

    names: set[str] = get_globals_in_pkl(fh)
    return names


def _legacy_globals(path: Path) -> set[str]:
    """The names in a checkpoint of torch's legacy (pre-zip) format: its first four pickles
    (magic number, protocol, system info, the state); empty if they cannot be read."""
    names: set[str] = set()
    try:
        with open(path, "rb") as fh:
            for _ in range(4):
                names |= _globals_in(fh)
    except Exception:
        pass
    return names


def scan_checkpoint(path: Path, unsafe: Callable[[str], ValueError]) -> None:
    """Step 1: the file, its zip entries and the names its pickle holds, without running it.

    ``unsafe(what)`` makes the error of a pickle that names more than :data:`PPORPE_GLOBALS`;
    the file's own faults are :class:`Unreadable`."""
    try:
        info = os.stat(path)
    except OSError as exc:
        raise Unreadable(exc.strerror or str(exc)) from None
    if not stat.S_ISREG(info.st_mode):
        raise Unreadable("not a regular file")
    if info.st_size > MAX_CHECKPOINT_BYTES:
        raise Unreadable(f"larger than pporpe reads, {MAX_CHECKPOINT_BYTES:,} bytes")
    if not zipfile.is_zipfile(path):
        foreign = _legacy_globals(path) - PPORPE_GLOBALS
        if foreign:
            raise unsafe(f"it would call {', '.join(sorted(foreign))}")
        raise Unreadable("not torch's zip format, which every pporpe version writes")
    try:
        with zipfile.ZipFile(path) as archive:
            entries = archive.infolist()
            if any(e.compress_type != zipfile.ZIP_STORED for e in entries):
                raise Unreadable("compressed entries; pporpe stores them uncompressed")
            if sum(e.file_size for e in entries) > info.st_size:
                raise Unreadable("its entries claim more bytes than the file holds")
            pickles = [e for e in entries if e.filename.rsplit("/", 1)[-1] == "data.pkl"]
            if len(pickles) != 1:
                raise Unreadable("not exactly one pickle (data.pkl) in it")
            with archive.open(pickles[0]) as fh:
                names = _globals_in(fh)
    except Unreadable:
        raise
    except Exception as exc:
        text = str(exc).strip().splitlines()
        raise Unreadable(f"{type(exc).__name__}: {text[0][:200] if text else ''}") from None
    foreign = names - PPORPE_GLOBALS
    if foreign:
        raise unsafe(f"it would call {', '.join(sorted(foreign))}")


def load_data(path: Path) -> Any:
    """Step 2 and 3: ``torch.load(weights_only=True)`` with the stand-ins, then
    :func:`plain_data`. Raises :class:`NotData` or torch's own errors (a torn file)."""
    with torch.serialization.safe_globals(_stand_ins()):
        state = torch.load(path, weights_only=True, map_location="cpu")
    return plain_data(state)


class _Budget:
    """How many more numbers and containers a checkpoint may hold."""

    def __init__(self) -> None:
        self.elements = MAX_CHECKPOINT_ELEMENTS
        self.nodes = MAX_CHECKPOINT_ELEMENTS

    def take(self, elements: int) -> None:
        self.elements -= elements
        self.nodes -= 1
        if self.elements < 0 or self.nodes < 0:
            raise NotData(f"it holds more than {MAX_CHECKPOINT_ELEMENTS:,} numbers")


_LEAVES = (type(None), bool, int, float, str, bytes)


def plain_data(value: Any, depth: int = 0, budget: _Budget | None = None) -> Any:
    """Step 3: ``value`` with the numpy stand-ins rebuilt (arrays, dtypes), checked to hold
    only containers, numbers, strings, bytes, dense tensors of number types and numpy
    values of plain number types (:class:`NotData` otherwise)."""
    budget = _Budget() if budget is None else budget
    if depth > MAX_CHECKPOINT_DEPTH:
        raise NotData(f"it nests containers more than {MAX_CHECKPOINT_DEPTH} deep")
    kind = type(value)
    if kind in _LEAVES or (isinstance(value, np.generic) and value.dtype.kind in _NUMBER_KINDS):
        budget.take(0)
        return value
    if kind is torch.Tensor:
        return _tensor(value, budget)
    if kind is _ArrayArgs:
        array = value.array()
        budget.take(array.size)
        return array
    if kind is _DTypeArgs:
        budget.take(0)
        return value.dtype()
    if kind in (dict, OrderedDict):
        budget.take(0)
        items = list(value.items())
        if not all(type(k) in (str, int) for k, _ in items):
            raise NotData("it holds a dict whose keys are not strings or ints")
        return kind((k, plain_data(v, depth + 1, budget)) for k, v in items)
    if kind in (list, tuple):
        budget.take(0)
        return kind(plain_data(v, depth + 1, budget) for v in value)
    raise NotData(f"it holds a {kind.__module__}.{kind.__qualname__}")


def _tensor(value: torch.Tensor, budget: _Budget) -> torch.Tensor:
    if value.layout != torch.strided or value.is_quantized or value.dtype not in _TENSOR_DTYPES:
        raise NotData(f"it holds a tensor of layout {value.layout} and dtype {value.dtype}")
    budget.take(value.numel())
    return value


# -- step 4: the run state --------------------------------------------------------------
def state_kind(state: dict[str, Any]) -> str | None:
    """The learner kind whose run state this is (``"online"``, ``"batch"``), by the state of
    its learner; None for neither."""
    learner = state.get("learner")
    if not isinstance(learner, dict):
        return None
    if "normalizer" in learner and "theta" in learner:
        return "batch"
    if "params" in learner or "traces" in learner:
        return "online"
    return None


def _count(v: Any) -> bool:
    return isinstance(v, int | np.integer) and not isinstance(v, bool) and 0 <= int(v) <= MAX_STEPS


def _number(v: Any) -> bool:
    if isinstance(v, bool) or not isinstance(v, int | float | np.integer | np.floating):
        return False
    return isinstance(v, float | np.floating) or abs(int(v)) <= 2**63


def _seconds(v: Any) -> bool:
    return _number(v) and math.isfinite(v) and v >= 0


def _tensor_of(v: Any) -> bool:
    return type(v) is torch.Tensor


_ROW_INTS = ("episode", "total_steps", "length")
_ROW_NUMBERS = ("ret", "wall_time")
_ROW_OPTIONAL = ("reg_amount", "past_threshold", "trace_decay", "ratio_dev")


def _record(row: Any) -> bool:
    """A record as checkpoints hold them: the ``episodes.csv`` columns, as numbers."""
    return (
        type(row) is dict
        and all(_count(row.get(k)) for k in _ROW_INTS)
        and all(_number(row.get(k)) for k in _ROW_NUMBERS)
        and all(k in row and (row[k] is None or _number(row[k])) for k in _ROW_OPTIONAL)
    )


def _update(row: Any) -> bool:
    return (
        type(row) is dict
        and _count(row.get("update"))
        and _count(row.get("total_steps"))
        and all(type(k) is str and _number(v) for k, v in row.items())
    )


_COMMON: dict[str, tuple[Callable[[Any], bool], bool, str]] = {
    "records": (lambda v: type(v) is list and all(map(_record, v)), True,
                "a list of episode records"),
    "updates": (lambda v: type(v) is list and all(map(_update, v)), False,
                "a list of update records"),
    "wall_time": (_seconds, True, "a finite number >= 0"),
    "cpu_time": (_seconds, False, "a finite number >= 0"),
    "cpu_time_since": (_count, False, "an int >= 0"),
}  # fmt: skip
"""Every run state's fields, whatever its learner kind: (check, required, what it must be)."""

_BY_KIND: dict[str, dict[str, tuple[Callable[[Any], bool], bool, str]]] = {
    "online": {
        "learner": (lambda v: type(v) is dict, True, "the learner's state"),
        "episodes": (_count, False, "an int >= 0"),
        "total_steps": (_count, True, "an int >= 0"),
        "episode": (lambda v: type(v) is dict and _number(v.get("ret")) and _count(v.get("length"))
                    and type(v.get("steps")) is list, False, "the episode in progress"),
        "env": (lambda v: v is None or type(v) is dict, False, "None or a replay record"),
        "env_rng": (lambda v: type(v) is dict, False, "a random generator's state"),
        "torch_rng": (_tensor_of, False, "a tensor"),
    },
    "batch": {
        "learner": (lambda v: type(v) is dict, True, "the learner's state"),
        "torch_rng": (_tensor_of, False, "a tensor"),
    },
}  # fmt: skip
"""The fields of each learner kind's run state besides :data:`_COMMON`."""

_LEARNER: dict[str, dict[str, Callable[[Any], bool]]] = {
    "online": {},
    "batch": {
        "theta": _tensor_of,
        "normalizer": lambda v: type(v) is dict and type(v.get("obs_rms")) is dict,
    },
}
"""Fields of the learner's state that a policy is built from (the builders check the rest
and name the file: :func:`building_from`)."""


def _a(word: str) -> str:
    return f"{'an' if word[:1] in 'aeiou' else 'a'} {word}"


def check_run_state(state: Any, path: Path, kind: str) -> None:
    """Step 4: ``state`` is a run state of learner kind ``kind`` (its records, counters and,
    for the built-in kinds, its learner), else one ``ValueError`` naming ``path``: a
    checkpoint of another kind says which kind the folder then holds. A kind registered by
    a user (:func:`~pporpe.runs.kinds.register_kind`) checks its own state."""
    tail = "; restore it from a copy, or use --force to start the run over"
    if type(state) is not dict or "members" in state:
        raise ValueError(f"{path} is not a run's checkpoint (a population's, or no pporpe "
                         f"checkpoint){tail}")  # fmt: skip
    found = state_kind(state)
    if found is None and kind in _BY_KIND:
        raise ValueError(f"{path} is not a pporpe run's checkpoint: it holds no online or "
                         f"batch learner's state ('learner'){tail}")  # fmt: skip
    if found is not None and found != kind:
        raise ValueError(
            f"{path} is not this run's checkpoint: this folder holds a {found} run's "
            f"checkpoint and the config.json of {_a(kind)} run{tail}"
        )
    fields = {**_COMMON, **_BY_KIND.get(kind, {})}
    for name, (check, required, what) in fields.items():
        if (name in state or required) and not check(state.get(name)):
            raise ValueError(f"{path}: {name} must be {what}{tail}")
    for name, check in _LEARNER.get(kind, {}).items():
        if not check(state["learner"].get(name)):
            raise ValueError(f"{path}: the learner's {name} is missing or malformed{tail}")


@contextmanager
def building_from(path: Path) -> Iterator[None]:
    """Errors of building a learner or a policy from the checkpoint ``path`` (a tensor of
    another shape, a missing entry) become one ``ValueError`` naming the file."""
    try:
        yield
    except (KeyError, TypeError, ValueError, IndexError, RuntimeError, AttributeError) as exc:
        if isinstance(exc, ValueError) and str(path) in str(exc):
            raise
        lines = str(exc).strip().splitlines()
        reason = lines[0][:200] if lines else type(exc).__name__
        if not isinstance(exc, ValueError):
            reason = f"{type(exc).__name__}: {reason}"
        raise ValueError(
            f"{path} does not fit this run's config.json ({reason}); restore it from a copy, "
            "or use --force to start the run over"
        ) from None


def check_population_state(saved: Any, path: Path, packing: bool = True) -> None:
    """A population's checkpoint: ``members`` (run name -> a state with its records; each
    state is checked as a run state when a run starts from it) and, with ``packing``, its
    packing (``runs``, and ``slots`` and ``queue`` naming them); else one ``ValueError``
    naming ``path``."""
    members = saved.get("members") if type(saved) is dict else None
    ok = type(members) is dict and all(
        type(k) is str and type(v) is dict and type(v.get("records", [])) is list
        for k, v in dict(members or {}).items()
    )
    if ok and not packing:
        return
    runs = saved.get("runs") if ok else None
    ok = ok and type(runs) is list and all(type(r) is str for r in runs or ())
    names: set[str] = set(runs or ()) if ok else set()
    ok = ok and type(saved.get("slots")) is list and type(saved.get("queue")) is list
    ok = ok and all(s is None or (type(s) is str and s in names) for s in saved["slots"])
    ok = ok and all(type(q) is str and q in names for q in saved["queue"])
    if not ok:
        raise ValueError(
            f"{path} is not a population's checkpoint (its runs, slots, queue and members); "
            "delete it to let each run resume from its own checkpoint"
        )
