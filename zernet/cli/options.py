"""The options several commands share, each declared here once: ``--debug``, ``--set``, ``--skip-bad``,
``--workers``, ``--no-progress``, ``--device``.

A command module makes its parser with :func:`command_parser` (which gives it ``--debug``) and adds the shared
options it takes with the ``add_*`` functions below.
"""

from __future__ import annotations

import argparse


def command_parser(sub, name: str, *, help: str, description: str) -> argparse.ArgumentParser:
    """The subparser of command ``name``, with ``--debug``."""
    parser = sub.add_parser(name, help=help, description=description)
    # SUPPRESS: a subcommand's --debug must not reset a --debug given before the subcommand.
    parser.add_argument(
        "--debug",
        action="store_true",
        default=argparse.SUPPRESS,
        help="show full tracebacks instead of one-line errors",
    )
    return parser


def add_overrides(parser: argparse.ArgumentParser) -> None:
    """``--set KEY=VALUE ...``: dotted configuration overrides, read by :func:`zernet.training.apply_overrides`."""
    parser.add_argument(
        "--set",
        dest="overrides",
        nargs="+",
        action="extend",
        default=[],
        metavar="KEY=VALUE",
        help="override config entries with dotted keys, e.g. --set train.epochs=5 "
        "model.name=feastnet patch.scales.0.r0=4.5 (values are read as YAML)",
    )


def add_skip_bad(parser: argparse.ArgumentParser) -> None:
    """``--skip-bad``: the data's ``on_error: skip`` policy."""
    parser.add_argument(
        "--skip-bad",
        action="store_true",
        help="leave out shapes that fail to load or preprocess (each is listed with its reason, "
        "in train.log and metrics.json too) instead of stopping; the same as "
        "data.on_error: skip",
    )


def add_workers(parser: argparse.ArgumentParser) -> None:
    """``--workers N``: preprocessing processes."""
    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="N",
        help="preprocessing worker processes (default: the data module's choice, one per core)",
    )


def add_no_progress(parser: argparse.ArgumentParser) -> None:
    """``--no-progress``."""
    parser.add_argument("--no-progress", action="store_true", help="no progress bars (log lines only)")


def add_device(parser: argparse.ArgumentParser) -> None:
    """``--device``: where a stored run's model runs."""
    parser.add_argument("--device", default=None, help="override the run's device (cpu, cuda, ...)")


def overrides_with_skip_bad(args: argparse.Namespace) -> list[str]:
    """The ``--set`` overrides, with ``data.on_error=skip`` last when ``--skip-bad`` is given."""
    return list(args.overrides) + (["data.on_error=skip"] if args.skip_bad else [])
