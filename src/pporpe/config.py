"""The one home of the shared vocabulary, the small validators and the config round-trip.

* Vocabulary: the surrogate names (:data:`METHODS`), policy kinds (:data:`POLICY_KINDS`)
  and activations (:data:`ACTIVATIONS`), each a ``Literal`` type and its tuple of values.
* Validators: :func:`require` and the predicates every config uses, so that every invalid
  value raises ``ValueError`` naming the field, its value and what is allowed.
* Round-trip: configs become plain dictionaries (:func:`config_to_dict`) saved as JSON
  with every run, and are rebuilt with :func:`config_from_dict`.

The learner configs live beside their learners (:mod:`pporpe.online.config`,
:mod:`pporpe.batch.config`); names follow the paper's symbols (``docs/glossary.md``).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Literal, TypeVar, get_args

from .limits import (  # the bounds of a run's settings, re-exported for the command line
    MAX_EPISODES,
    MAX_EVAL_EPISODES,
    MAX_HIDDEN_WEIGHTS,
    MAX_LAYERS,
    MAX_SEED,
    MAX_STEPS,
    MAX_UNITS,
    check_int_in,
    short_repr,
)
from .surrogates import METHODS, Method, RPEForm, check_surrogate_params

__all__ = [
    "ACTIVATIONS",
    "MAX_EPISODES",
    "MAX_EVAL_EPISODES",
    "MAX_SEED",
    "MAX_STEPS",
    "METHODS",
    "POLICY_KINDS",
    "RPE_FORMS",
    "Activation",
    "Method",
    "PolicyKind",
    "RPEForm",
    "check_positive_int",
    "check_real",
    "config_from_dict",
    "config_to_dict",
    "is_int",
    "is_real",
    "require",
    "validate_network_fields",
    "validate_surrogate_fields",
]

PolicyKind = Literal["student_t", "normal"]
"""Policy distribution over the pre-map action u: diagonal student-t or Normal."""
POLICY_KINDS: tuple[str, ...] = get_args(PolicyKind)

Activation = Literal["swish", "relu", "tanh"]
"""Hidden activation; ``swish`` is ``x * sigmoid(x)`` (``nn.SiLU``)."""
ACTIVATIONS: tuple[str, ...] = get_args(Activation)

RPE_FORMS: tuple[str, ...] = get_args(RPEForm)



def require(cond: bool, name: str, value: object, allowed: str) -> None:
    """Raise ``ValueError("<name> must be <allowed>; got <name>=<value>")`` unless ``cond``
    (a long value cut short: :func:`~pporpe.limits.short_repr`)."""
    if not cond:
        raise ValueError(f"{name} must be {allowed}; got {name}={short_repr(value)}")


def is_real(x: object) -> bool:
    """A real number: an int or float, not a bool, not NaN (infinities allowed); an int too
    large for a float (over 10**308) is not one."""
    if isinstance(x, bool) or not isinstance(x, int | float):
        return False
    try:
        return not math.isnan(x)
    except OverflowError:
        return False


def is_int(x: object) -> bool:
    """An int that is not a bool."""
    return isinstance(x, int) and not isinstance(x, bool)


def check_real(name: str, value: Any, lo: float, hi: float, lo_open: bool, hi_open: bool) -> None:
    """Raise ValueError unless ``value`` is a real number in the given interval."""
    interval = f"{'(' if lo_open else '['}{lo}, {hi}{')' if hi_open else ']'}"
    if not is_real(value) and not (isinstance(value, float) and math.isnan(value)):
        raise ValueError(f"{name} must be a real number in {interval}, got {short_repr(value)}")
    v = float(value)
    ok = not math.isnan(v) and (v > lo if lo_open else v >= lo)
    ok = ok and (v < hi if hi_open else v <= hi)
    if not ok:
        raise ValueError(f"{name} must be in {interval}, got {value!r}")


def check_positive_int(name: str, value: object) -> int:
    """Return ``value`` if it is a positive int (not a bool), else raise ValueError."""
    if not is_int(value) or value < 1:  # type: ignore[operator]
        raise ValueError(f"{name} must be a positive int, got {value!r}")
    return value  # type: ignore[return-value]


def validate_surrogate_fields(cfg: Any) -> None:
    """Validate the surrogate fields every learner config has: method, eps, beta, eta, rpe_form.

    Raises ``ValueError`` naming the field, its value and the allowed range. ``beta`` and
    ``eta`` are range-checked even for the methods that ignore them, so a typo is caught.
    """
    require(cfg.method in METHODS, "method", cfg.method, f"one of {list(METHODS)}")
    for name in ("eps", "beta", "eta"):
        require(is_real(getattr(cfg, name)), name, getattr(cfg, name), "a number")
    check_surrogate_params(cfg.method, cfg.eps, cfg.beta, cfg.eta)
    if cfg.method != "rpe":
        require(0.0 <= cfg.beta <= 1.0, "beta", cfg.beta, "in [0, 1]")
    if cfg.method != "rb":
        require(0.0 <= cfg.eta < math.inf, "eta", cfg.eta, "a finite number >= 0")
    require(cfg.rpe_form in RPE_FORMS, "rpe_form", cfg.rpe_form, "'derived' or 'printed'")


def validate_network_fields(cfg: Any) -> None:
    """Validate the network fields the learner configs share: layers, units (each within
    :mod:`pporpe.limits`, and units * units * layers too), activation, policy."""
    check_int_in("layers", cfg.layers, 1, MAX_LAYERS)
    check_int_in("units", cfg.units, 1, MAX_UNITS)
    weights = cfg.units * cfg.units * cfg.layers
    require(
        weights <= MAX_HIDDEN_WEIGHTS,
        "units * units * layers",
        weights,
        f"at most {MAX_HIDDEN_WEIGHTS:,} (pporpe.limits.MAX_HIDDEN_WEIGHTS)",
    )
    require(
        cfg.activation in ACTIVATIONS, "activation", cfg.activation, f"one of {list(ACTIVATIONS)}"
    )
    require(cfg.policy in POLICY_KINDS, "policy", cfg.policy, f"one of {list(POLICY_KINDS)}")
    require(isinstance(cfg.layer_norm, bool), "layer_norm", cfg.layer_norm, "True or False")


def config_to_dict(cfg: Any) -> dict[str, Any]:
    """A JSON-ready dictionary of a config dataclass (nested configs become dicts)."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            value = config_to_dict(value)
        elif isinstance(value, tuple):
            value = list(value)
        elif isinstance(value, float) and math.isinf(value):
            value = "inf"
        out[f.name] = value
    return out


C = TypeVar("C")


def config_from_dict(cls: type[C], data: dict[str, Any], where: str = "config") -> C:
    """Build ``cls`` from a dictionary, rejecting unknown fields and wrong types by name.

    Nested dataclass fields accept dictionaries; lists become tuples; the string
    ``"inf"`` becomes ``math.inf``. ``where`` prefixes error messages (e.g. a file name).
    """
    if not isinstance(data, dict):
        raise ValueError(f"{where}: expected a table of settings; got {data!r}")
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ValueError(
            f"{where}: unknown field(s) {unknown}; allowed fields are {sorted(fields)}"
        )
    kwargs: dict[str, Any] = {}
    hints = {f.name: f.default_factory for f in fields.values()}  # nested config factories
    for name, value in data.items():
        factory = hints[name]
        if factory is not dataclasses.MISSING and dataclasses.is_dataclass(factory):
            value = config_from_dict(factory, value, f"{where}.{name}")
        elif isinstance(value, list):
            value = tuple(value)
        elif value == "inf":
            value = math.inf
        kwargs[name] = value
    try:
        return cls(**kwargs)
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None
    except TypeError as exc:
        raise ValueError(f"{where}: {exc}") from None
