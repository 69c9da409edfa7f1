"""The argument parser of the ``pporpe`` command: a bad command line ends in one line.

argparse prints the whole usage block before its error (40 lines for ``pporpe train``);
:class:`OneLineParser` prints only the error, naming the command, and one hint::

    pporpe train: error: argument --method: invalid choice 'trpo' (choose from ppo, rb, rpe, spo)
    (pporpe train --help for the options)

and exits with status 2, as argparse does. :func:`bounded_int` is the argparse type of a
count with an upper bound (a budget, a seed), whose error names the bound.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any, NoReturn

__all__ = ["USAGE_ERROR", "OneLineParser", "bounded_int", "subcommand_parser"]

USAGE_ERROR = 2
"""Exit status of a command line argparse refuses (and of every one-line refusal)."""


class OneLineParser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose errors are one line plus a ``--help`` hint, no usage
    block; its subcommands' parsers are of this class too."""

    def error(self, message: str) -> NoReturn:
        """Print ``<prog>: error: <message>`` and the hint on standard error; exit 2."""
        self.exit(
            USAGE_ERROR, f"{self.prog}: error: {message}\n({self.prog} --help for the options)\n"
        )

    def _check_value(self, action: argparse.Action, value: Any) -> None:
        """An invalid choice, in the same words whatever the Python version."""
        if action.choices is not None and value not in action.choices:
            choices = ", ".join(map(str, action.choices))
            raise argparse.ArgumentError(
                action, f"invalid choice {value!r} (choose from {choices})"
            )


def subcommand_parser(parser: argparse.ArgumentParser, name: str) -> argparse.ArgumentParser:
    """The parser of the subcommand ``name`` of ``parser`` (``parser`` itself if none)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction) and name in action.choices:
            sub: argparse.ArgumentParser = action.choices[name]
            return sub
    return parser


def bounded_int(high: int | None, low: int | None = None) -> Callable[[str], int]:
    """The argparse type of an int at most ``high`` and at least ``low`` (each if not
    None), whose error says the bound."""

    def parse(text: str) -> int:
        shown = text if len(text) <= 24 else f"{text[:12]}... ({len(text)} characters)"
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an int, got {shown!r}") from None
        if low is not None and value < low:
            raise argparse.ArgumentTypeError(f"must be an int >= {low}; got {shown}")
        if high is not None and value > high:
            raise argparse.ArgumentTypeError(f"must be at most {high:,}; got {shown}")
        return value

    parse.__name__ = "int"
    return parse
