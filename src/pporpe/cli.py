"""Command-line interface: ``pporpe <command> ...``.

Every command validates its arguments before it builds an environment or starts work.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

__all__ = ["build_parser", "main"]


def _cmd_figures(args: argparse.Namespace) -> int:
    from .figures import draw_analytic_figures

    for path in draw_analytic_figures(args.out, eps=args.eps, beta=args.beta, eta=args.eta):
        print(path)
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``pporpe`` command."""
    parser = argparse.ArgumentParser(
        prog="pporpe",
        description="PPO-RPE, PPO and PPO-RB: train, evaluate and reproduce the paper.",
    )
    sub = parser.add_subparsers(dest="command", required=True)

    fig = sub.add_parser(
        "figures", help="draw the paper's analytic figures (relative ratio, negative loss)"
    )
    fig.add_argument("--out", default="results/figures", help="output folder (PNG and PDF)")
    fig.add_argument("--eps", type=float, default=0.1, help="threshold eps in (0, 1)")
    fig.add_argument("--beta", type=float, default=0.5, help="RPE mixture ratio beta in [0, 1]")
    fig.add_argument("--eta", type=float, default=0.3, help="PPO-RB rollback eta >= 0")
    fig.set_defaults(func=_cmd_figures)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``pporpe`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except ValueError as exc:
        print(f"pporpe {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
