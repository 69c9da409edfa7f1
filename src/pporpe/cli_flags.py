"""Command-line flags generated from the config dataclasses: one flag per field.

A field ``lambdas`` of :class:`~pporpe.online.OnlineConfig` becomes ``--lambdas``, its help
the field's docstring, its type and choices from the annotation (``Literal`` -> choices,
``bool`` -> ``--x/--no-x``, ``tuple[float, float]`` -> two numbers, ``X | None`` -> also
``none``), and the default in the help the dataclass's. A flag not given is not set, so
the dataclass's own default applies (``--eps`` is 0.1 for the online learner and 0.2 for
batch PPO). Several dataclasses may share a flag (``--gamma``); :func:`values_for` returns
the given flags of one of them. Values are checked by the dataclass's ``__post_init__``,
which names the field. Written here rather than with tyro or simple-parsing: the CLI has
subcommands and two learner kinds sharing flags, which both handle only through nested
dataclasses that would change every flag's name.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import itertools
import textwrap
import types
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, get_args, get_origin

from .cli_parser import bounded_int

__all__ = ["ConfigFlags", "FlagGroup", "field_docs", "values_for"]


@dataclass(frozen=True, eq=False)
class FlagGroup:
    """The fields of one config dataclass that become flags (compared by identity)."""

    name: str
    """What the group is, in the help (e.g. ``"online"``)."""
    cls: type
    """The dataclass."""
    skip: frozenset[str] = frozenset()
    """Fields that get no flag."""
    rename: Mapping[str, str] = field(default_factory=dict)
    """Field -> flag name where they differ (``total_steps`` -> ``steps``)."""
    label: str = ""
    """What the help calls the group before its docstring of a flag whose groups' docstrings
    differ (default: the first word of :attr:`name`)."""

    @property
    def short(self) -> str:
        """:attr:`label`, or the first word of :attr:`name`."""
        return self.label or self.name.split()[0]

    def fields(self) -> list[tuple[str, dataclasses.Field[Any]]]:
        """``(flag name, field)`` of every field with a flag."""
        return [
            (self.rename.get(f.name, f.name), f)
            for f in dataclasses.fields(self.cls)
            if f.name not in self.skip
        ]


def field_docs(cls: type) -> dict[str, str]:
    """The docstring under each field of a dataclass (the string literal that follows the
    annotated assignment), whitespace collapsed."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    body = tree.body[0].body  # type: ignore[attr-defined]
    docs: dict[str, str] = {}
    for node, nxt in itertools.pairwise(body):
        if (
            isinstance(node, ast.AnnAssign)
            and isinstance(node.target, ast.Name)
            and isinstance(nxt, ast.Expr)
            and isinstance(nxt.value, ast.Constant)
            and isinstance(nxt.value.value, str)
        ):
            docs[node.target.id] = " ".join(nxt.value.value.split())
    return docs


def _none_or(convert: Any) -> Any:
    def parse(text: str) -> Any:
        return None if text.strip().lower() == "none" else convert(text)

    parse.__name__ = getattr(convert, "__name__", "value")
    return parse


def _argparse_spec(tp: Any, bound: int | None = None) -> dict[str, Any]:
    """argparse keywords (type, choices, nargs, action) for a field's annotation; an int
    field with a ``bound`` takes no value above it."""
    args = get_args(tp)
    if get_origin(tp) in (typing.Union, types.UnionType) and type(None) in args:
        (inner,) = [a for a in args if a is not type(None)]
        spec = _argparse_spec(inner, bound)
        return {**spec, "type": _none_or(spec.get("type", str)), "metavar": "VALUE|none"}
    if get_origin(tp) is Literal:
        return {"type": str, "choices": [str(a) for a in args]}
    if tp is bool:
        return {"action": argparse.BooleanOptionalAction}
    if get_origin(tp) is tuple:
        if not args or any(a is Ellipsis for a in args) or len(set(args)) != 1:
            raise TypeError(f"no flag for a tuple of {args}")
        return {"type": args[0], "nargs": len(args)}
    if tp is int and bound is not None:
        return {"type": bounded_int(bound)}
    if tp in (int, float, str):
        return {"type": tp}
    raise TypeError(f"no flag for a field of type {tp!r}")


def _spec_key(spec: dict[str, Any]) -> tuple[Any, ...]:
    t = spec.get("type")
    return (getattr(t, "__name__", t), tuple(spec.get("choices") or ()), spec.get("nargs"))


def _default_text(f: dataclasses.Field[Any]) -> str:
    if f.default is not dataclasses.MISSING:
        value = f.default
    elif f.default_factory is not dataclasses.MISSING:
        value = f.default_factory()
    else:
        return "required"
    if isinstance(value, tuple):
        return " ".join(str(v) for v in value)
    return str(value)


class ConfigFlags:
    """Flags of several :class:`FlagGroup` on one parser (shared names become one flag)."""

    def __init__(
        self, groups: Sequence[FlagGroup], bounds: Mapping[str, int] | None = None
    ) -> None:
        self.groups = list(groups)
        self.bounds = dict(bounds or {})
        """Flag -> the largest value it takes (an int flag: a budget, a seed)."""
        self.owners: dict[str, list[tuple[FlagGroup, str]]] = {}
        """Flag -> the groups (and their field names) it sets."""
        self._specs: dict[str, dict[str, Any]] = {}
        self._help: dict[str, list[str]] = {}
        """Flag -> the distinct docstrings of its fields, in the groups' order."""
        self._defaults: dict[str, list[tuple[str, str]]] = {}
        for group in self.groups:
            docs = field_docs(group.cls)
            hints = typing.get_type_hints(group.cls)
            for flag, f in group.fields():
                spec = _argparse_spec(hints[f.name], self.bounds.get(flag))
                if flag in self._specs and _spec_key(self._specs[flag]) != _spec_key(spec):
                    raise TypeError(f"flag --{flag} has different types in its configs")
                self._specs.setdefault(flag, spec)
                self.owners.setdefault(flag, []).append((group, f.name))
                doc = docs.get(f.name, f.name).replace("``", "")
                if doc not in self._help.setdefault(flag, []):
                    self._help[flag].append(doc)
                self._defaults.setdefault(flag, []).append((group.short, _default_text(f)))

    def add_to(
        self,
        parser: argparse.ArgumentParser,
        sections: Sequence[tuple[str, Sequence[str]]] | None = None,
    ) -> None:
        """Add every flag, none with a value unless given, under ``sections``: ``(title,
        flags)`` pairs that place every flag once (default: each flag under the first group
        that has it, titled ``"<group name> settings"``). Each flag's help ends with its
        default, or each group's where they differ."""
        if sections is None:
            sections = [
                (
                    f"{group.name} settings",
                    [f for f, _ in group.fields() if self.owners[f][0][0] is group],
                )
                for group in self.groups
            ]
        placed = [flag for _, flags in sections for flag in flags]
        if sorted(placed) != sorted(self.owners):
            raise ValueError(f"sections must place every flag once; got {placed}")
        for title, flags in sections:
            section = parser.add_argument_group(title)
            for flag in flags:
                help_text = f"{self._doc_help(flag)} [{self._default_help(flag)}]"
                section.add_argument(
                    f"--{flag.replace('_', '-')}",
                    dest=flag,
                    default=argparse.SUPPRESS,
                    help=help_text.replace("%", "%%"),
                    **self._specs[flag],
                )

    def _doc_help(self, flag: str) -> str:
        """The field's docstring, or each group's where they differ."""
        docs = self._help[flag]
        if len(docs) == 1:
            return docs[0]
        names = [group.short for group, _ in self.owners[flag]]
        return " ".join(f"{name}: {doc}" for name, doc in zip(names, docs, strict=False))

    def _default_help(self, flag: str) -> str:
        """``default: X``, or each group's default where they differ."""
        defaults = self._defaults[flag]
        if len({d for _, d in defaults}) == 1:
            return f"default: {defaults[0][1]}"
        return "; ".join(f"default {name}: {d}" for name, d in defaults)

    def given(self, args: argparse.Namespace) -> list[str]:
        """The flags given on the command line."""
        return [flag for flag in self.owners if hasattr(args, flag)]


def values_for(flags: ConfigFlags, args: argparse.Namespace, group: FlagGroup) -> dict[str, Any]:
    """The given flags of ``group``, by field name (tuples for two-number fields)."""
    out: dict[str, Any] = {}
    for flag, owners in flags.owners.items():
        for owner, name in owners:
            if owner is group and hasattr(args, flag):
                value = getattr(args, flag)
                out[name] = tuple(value) if isinstance(value, list) else value
    return out
