"""How a loader describes one shape to the preprocessing: :class:`ShapeSource`, and content keys of files."""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from zernet.data.dataset import DatasetError
from zernet.geometry import Surface

__all__ = ["ShapeSource", "file_key", "read_text_numbers"]


@dataclass(frozen=True)
class ShapeSource:
    """How to obtain one shape and its ground truth.

    Attributes:
        name: unique name within the data set (used in splits, messages and the cache file name).
        load: zero-argument callable returning ``(surface, target)``; ``target`` is an (N,) per-vertex array
            or None. It runs in a worker process, so it must be picklable: a module-level function or a
            ``functools.partial`` of one — never a lambda or a closure. It should raise
            :class:`~zernet.geometry.surface.SurfaceError` / :class:`~zernet.data.dataset.DatasetError` with a clear
            message for a bad file.
        key: a string that changes whenever the shape's content would change (e.g. file paths with sizes
            and modification times, or generator parameters), used to skip already cached shapes without
            loading them. None disables the skip (operators are still cached by geometry hash).
        target_exponent: area exponent of a regression target: the target is multiplied by
            ``(target_area / area) ** target_exponent`` when the surface is normalised (0.5 for wall stress,
            -0.5 for a curvature, 0 for labels and dimensionless values).
    """

    name: str
    load: Callable[[], tuple[Surface, np.ndarray | None]]
    key: str | None = None
    target_exponent: float = 0.0


def file_key(*paths: str | os.PathLike) -> str:
    """Content key for file-based sources: absolute path, size and modification time of each file."""
    parts = []
    for path in paths:
        stat = os.stat(path)
        parts.append(f"{os.path.abspath(path)}|{stat.st_size}|{stat.st_mtime_ns}")
    return ";".join(parts)


def read_text_numbers(path: str | os.PathLike, what: str = "value") -> tuple[np.ndarray, np.ndarray]:
    """The numbers of a text file (one or more per line, ``#`` starts a comment): (L,) float64 values and
    the (L,) 1-based line each one is on.

    A token that is not a number is reported with the file and its 1-based line, as an editor shows it:
    ``labels.txt: line 21: 'abc' is not a number``. A file that is not text (not UTF-8) says so.
    """
    path = Path(path)
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as error:
        raise DatasetError(
            f"{path}: unreadable: not a text file of {what}s (not UTF-8 at byte {error.start})"
        ) from None
    except OSError as error:
        raise DatasetError(f"{path}: cannot read {what}s: {error.strerror or error}") from None
    numbers: list[float] = []
    lines: list[int] = []
    for line_number, line in enumerate(text.splitlines(), start=1):
        for token in line.split("#", 1)[0].replace(",", " ").split():
            try:
                numbers.append(float(token))
                lines.append(line_number)
            except ValueError:
                raise DatasetError(
                    f"{path}: line {line_number}: {token[:40]!r} is not a number (expected one {what} per line)"
                ) from None
    return np.asarray(numbers, dtype=np.float64), np.asarray(lines, dtype=np.int64)
