"""rl-zoo3's settings written as Python expressions, read as data and never run.

rl-zoo3's hyperparameter files write ``policy_kwargs`` as a string holding a Python
expression, e.g. ``"dict(net_arch=dict(pi=[256, 256], vf=[256, 256]), activation_fn=nn.ReLU)"``,
and rl-zoo3 evaluates it. :func:`read_zoo_literal` parses such a string with :mod:`ast` and
builds the value from the syntax tree itself: nothing in the string is evaluated, imported,
looked up or called, so a string from a file someone sent runs no code.
"""

from __future__ import annotations

import ast
from typing import Any

__all__ = ["ACTIVATION_NAMES", "MAX_DEPTH", "MAX_LENGTH", "read_zoo_literal"]

ACTIVATION_NAMES = (
    "ELU", "GELU", "LeakyReLU", "Mish", "ReLU", "SELU", "SiLU", "Sigmoid", "Softplus", "Tanh",
)  # fmt: skip
"""The ``torch.nn`` activation classes a string may name, as ``nn.<Name>``."""

MAX_LENGTH = 10_000
"""Longest string read, in characters (rl-zoo3's longest are a few hundred)."""

MAX_DEPTH = 32
"""Deepest nesting of dicts, lists and tuples read."""

_ALLOWED = (
    "dict(key=value, ...) and {key: value, ...}, lists, tuples, numbers, strings, "
    "True, False, None and nn.<activation> (" + ", ".join(ACTIVATION_NAMES) + ")"
)


class _Refused(Exception):
    """A part of the expression that is not one of the allowed forms."""

    def __init__(self, node: ast.AST, why: str = "is not allowed") -> None:
        super().__init__(why)
        self.node = node
        self.why = why


def read_zoo_literal(text: str, name: str = "policy_kwargs") -> Any:
    """The value an rl-zoo3 expression string such as ``policy_kwargs`` stands for.

    Accepts exactly, nested at most :data:`MAX_DEPTH` deep in a string of at most
    :data:`MAX_LENGTH` characters:

    * ``dict(key=value, ...)``, keyword arguments only (no positional argument, no ``**``),
      and ``{key: value, ...}`` whose keys are strings, numbers, ``True``, ``False`` or
      ``None`` (no ``**``): both become a ``dict``;
    * lists ``[...]`` and tuples ``(...)`` (no ``*``);
    * numbers (``int`` and ``float``, with an optional leading ``-`` or ``+``), strings,
      ``True``, ``False`` and ``None``;
    * ``nn.<Name>`` for a name in :data:`ACTIVATION_NAMES` (``nn.ReLU``, ``nn.Tanh``,
      ``nn.ELU``, ``nn.SiLU``, ``nn.LeakyReLU``, ``nn.GELU``, ...): the ``torch.nn`` class
      itself, not an instance.

    Anything else (any other name, attribute or call, an operator, a comprehension, a
    lambda) is refused.

    Raises:
        ValueError: one line naming ``name``, the refused part and its place, and what is
            accepted.
    """
    if not isinstance(text, str):
        raise ValueError(f"`{name}` must be a dict or a string; got {type(text).__name__}")
    if len(text) > MAX_LENGTH:
        raise ValueError(
            f"`{name}`: a string of {len(text)} characters; at most {MAX_LENGTH} are read"
        )
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except (SyntaxError, ValueError, RecursionError, MemoryError) as exc:
        reason = getattr(exc, "msg", None) or type(exc).__name__
        raise ValueError(f"`{name}`: not an expression pporpe can read ({reason})") from None
    try:
        return _value(tree.body, 0)
    except _Refused as exc:
        part = ast.get_source_segment(text.strip(), exc.node) or type(exc.node).__name__
        if len(part) > 60:
            part = part[:57] + "..."
        line, column = getattr(exc.node, "lineno", 1), getattr(exc.node, "col_offset", 0) + 1
        where = f"line {line}, column {column}"
        raise ValueError(
            f"`{name}`: {part!r} ({where}) {exc.why}; only {_ALLOWED} are read"
        ) from None


def _value(node: ast.AST, depth: int) -> Any:
    """The value of one allowed node, or :class:`_Refused`."""
    if depth > MAX_DEPTH:
        raise _Refused(node, f"is nested deeper than {MAX_DEPTH}")
    if isinstance(node, ast.Constant | ast.UnaryOp):
        return _constant(node)
    if isinstance(node, ast.List | ast.Tuple):
        items = [_value(item, depth + 1) for item in node.elts]
        return items if isinstance(node, ast.List) else tuple(items)
    if isinstance(node, ast.Dict):
        if any(key is None for key in node.keys):
            raise _Refused(node, "unpacks with **, which is not allowed")
        return {
            _constant(key): _value(value, depth + 1)  # type: ignore[arg-type]
            for key, value in zip(node.keys, node.values, strict=True)
        }
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "dict":
        if node.args or any(kw.arg is None for kw in node.keywords):
            raise _Refused(node, "is not dict(key=value, ...)")
        return {kw.arg: _value(kw.value, depth + 1) for kw in node.keywords}
    if (
        isinstance(node, ast.Attribute)
        and isinstance(node.value, ast.Name)
        and node.value.id == "nn"
        and node.attr in ACTIVATION_NAMES
    ):
        from torch import nn

        return getattr(nn, node.attr)
    raise _Refused(node)


def _constant(node: ast.AST) -> Any:
    """A number (signed or not), a string, True, False or None, or :class:`_Refused`."""
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub | ast.UAdd):
        value = node.operand.value if isinstance(node.operand, ast.Constant) else None
        if type(value) in (int, float):
            return -value if isinstance(node.op, ast.USub) else value  # type: ignore[operator]
        raise _Refused(node)
    if isinstance(node, ast.Constant) and (
        node.value is None or type(node.value) in (bool, int, float, str)
    ):
        return node.value
    raise _Refused(node)
