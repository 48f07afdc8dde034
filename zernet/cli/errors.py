"""How the ``zernet`` command reports problems, for every command alike.

A problem the user can fix (a missing file, a bad configuration key, an unknown model, a malformed mesh) is
one line on stderr, ``zernet COMMAND: error: ...``, with exit code 2; shapes that failed to preprocess get
one line each. Advice written for the Python API (``pass repair=True``) is rewritten as the command's own
options. Anything else is an internal error (exit code 1); ``--debug`` shows the traceback instead.
Warnings are printed on one line too.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from collections.abc import Callable

from zernet.data import DatasetError, PreprocessError
from zernet.geometry import SurfaceError
from zernet.training import ConfigError

EXIT_USER_ERROR = 2


class UsageError(Exception):
    """A command-line problem detected by the command itself (reported like any user error)."""


#: Exceptions that describe a problem the user can fix: reported as one line, exit code 2.
USER_ERRORS = (
    UsageError,
    ConfigError,
    SurfaceError,
    DatasetError,
    FileNotFoundError,
    NotADirectoryError,
    IsADirectoryError,
    PermissionError,
    ValueError,
    KeyError,
)

#: Advice written for the Python API, and what it means in each command: (API text, {command: CLI text}).
ADVICE = (
    (
        "pass repair=True to",
        {
            "predict": "rerun with --repair to",
            "evaluate": "rerun with --skip-bad to leave the shape out, or train with data.repair: true to",
            "*": "rerun with --set data.repair=true to",
        },
    ),
    (
        "run validate_surface(repair=True) first",
        {
            "predict": "rerun with --repair",
            "evaluate": "rerun with --skip-bad to leave the shape out",
            "*": "rerun with --set data.repair=true",
        },
    ),
    (
        "(on_error='skip' leaves them out)",
        {"predict": "", "*": "rerun with --skip-bad to leave them out (data.on_error: skip)"},
    ),
    (
        "give patch_configs",
        {
            "evaluate": "set patch.scales in the run's configuration",
            "predict": "set patch.scales in the run's configuration",
            "*": "set patch.scales (e.g. --set 'patch.scales=[{r0: 5.5}]')",
        },
    ),
    ("use kind 'synthetic' with task=...", {"*": "use data.kind: synthetic with data.task"}),
    ("(for a point cloud, set faces=None)", {"*": "(a point cloud is read from .xyz, .npy or a .ply without faces)"}),
)


def command_advice(command: str, message: str) -> str:
    """``message`` with advice meant for the Python API rewritten as the options of ``command``."""
    for api_text, by_command in ADVICE:
        if api_text in message:
            message = message.replace(api_text, by_command.get(command, by_command["*"]))
    return message


def error_lines(command: str, error: BaseException) -> list[str]:
    """The lines reporting a user error: one line, or for shapes that failed, one line per shape."""
    message = str(error.args[0]) if isinstance(error, KeyError) and error.args else str(error)
    message = command_advice(command, message)
    lines = [line.rstrip() for line in message.splitlines() if line.strip()]
    if isinstance(error, PreprocessError):
        return [f"zernet {command}: error: {lines[0]}"] + [f"  {line.strip()}" for line in lines[1:]]
    return [f"zernet {command}: error: " + ("; ".join(line.strip() for line in lines) or type(error).__name__)]


def one_line_warnings(command: str):
    """A ``warnings.showwarning`` that prints ``zernet COMMAND: warning: message`` on one line (no source
    line, which reads like a crash)."""

    def show(message, category, filename, lineno, file=None, line=None):
        text = "; ".join(part.strip() for part in str(message).splitlines() if part.strip())
        print(f"zernet {command}: warning: {command_advice(command, text)}", file=file or sys.stderr)

    return show


def run_reporting_errors(
    command: str, handler: Callable[[argparse.Namespace], int], args: argparse.Namespace, debug: bool
) -> int:
    """Run a command's handler; returns its exit code (0 success, 2 user error, 1 internal error, 130
    interrupted) with problems and warnings reported as described above."""
    previous_showwarning = warnings.showwarning
    warnings.showwarning = one_line_warnings(command)
    try:
        return int(handler(args) or 0)
    except KeyboardInterrupt:
        print(
            "zernet: interrupted (a training run continues with: zernet train --resume --run-dir DIR)", file=sys.stderr
        )
        return 130
    except Exception as error:
        if debug:
            raise
        if isinstance(error, USER_ERRORS):
            for line in error_lines(command, error):
                print(line, file=sys.stderr)
            return EXIT_USER_ERROR
        message = "; ".join(line.strip() for line in str(error).splitlines() if line.strip())
        print(
            f"zernet {command}: internal error: {type(error).__name__}: {message} "
            "(rerun with --debug for the traceback)",
            file=sys.stderr,
        )
        return 1
    finally:
        warnings.showwarning = previous_showwarning
