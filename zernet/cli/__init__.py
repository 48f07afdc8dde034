"""The ``zernet`` command: preprocess, train, evaluate, predict, demo, bodies, match.

One module per command holds its parser and its handler (``add_command(sub)``, ``run(args)``); the options
several commands share are declared once in :mod:`zernet.cli.options`, and problems are reported the same
way for every command by :mod:`zernet.cli.errors` (one line on stderr and exit code 2 for what a user can
fix; ``--debug`` shows the full traceback instead). Training interrupted with Ctrl-C can be continued with
``--resume``.
"""

from __future__ import annotations

import argparse

from zernet.cli import bodies, demo, evaluate, match, predict, preprocess, train
from zernet.cli.errors import run_reporting_errors
from zernet.inference.runtime import keep_freed_memory

__all__ = ["main", "build_parser"]

COMMANDS = (preprocess, train, evaluate, predict, demo, bodies, match)


def build_parser() -> argparse.ArgumentParser:
    """The ``zernet`` parser: one subcommand per public entry point, each with its own ``--help``."""
    parser = argparse.ArgumentParser(
        prog="zernet",
        description="Convolutional neural networks on curved surfaces (ZerNet): preprocess, train, evaluate, "
        "predict, demo.",
        epilog="Run 'zernet COMMAND --help' for the options of one command. Start with 'zernet demo'.",
    )
    parser.add_argument(
        "--debug", action="store_true", default=False, help="show full tracebacks instead of one-line errors"
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for command in COMMANDS:
        command.add_command(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the ``zernet`` command; returns the exit code (0 success, 2 user error, 1 internal error)."""
    args = build_parser().parse_args(argv)
    keep_freed_memory()
    return run_reporting_errors(args.command, args.handler, args, debug=args.debug)
