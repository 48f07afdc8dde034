"""What every benchmark shares: its common flags, its result files (JSON with the commit and the machine, one
markdown table format) and its inputs (one generated body, a generated bodies folder).

Benchmarks are modules of the ``benchmarks`` package, run from the repository root::

    .venv/bin/python -m benchmarks.speed.bench_operator --help

so ``import benchmarks.harness`` works in every one of them without touching ``sys.path``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from zernet.io_utils import atomic_write_bytes

if TYPE_CHECKING:
    from zernet.geometry import Surface

REPO = Path(__file__).resolve().parents[1]
SPEED_RESULTS = REPO / "benchmarks" / "speed" / "results"
EXPERIMENT_RESULTS = REPO / "benchmarks" / "experiments" / "results"
RECIPES = REPO / "configs" / "recipes"
CACHE = REPO / ".zernet-cache"
BODY_AREA = 15000.0  # the paper's FAUST scale: a body's surface area with r0 = 5.5

# --------------------------------------------------------------------------------------------------------
# Flags
# --------------------------------------------------------------------------------------------------------


def arguments(docstring: str) -> argparse.ArgumentParser:
    """A parser whose description is the script's docstring, shown as written (its usage lines included)."""
    return argparse.ArgumentParser(description=docstring, formatter_class=argparse.RawDescriptionHelpFormatter)


def add_out(parser: argparse.ArgumentParser, default: Path) -> None:
    """``--out STEM``: the script writes ``STEM.json`` (and ``STEM.md``, ``STEM.png`` where it makes them)."""
    parser.add_argument(
        "--out",
        type=Path,
        default=default,
        metavar="STEM",
        help=f"stem of the result files: STEM.json and, where the script writes them, STEM.md and STEM.png "
        f"(default {default.relative_to(REPO)})",
    )


def add_threads(parser: argparse.ArgumentParser, default: int | None = None) -> None:
    """``--threads N``: torch's CPU threads (default: torch's own choice)."""
    parser.add_argument("--threads", type=int, default=default, help="torch CPU threads")


def add_device(parser: argparse.ArgumentParser) -> None:
    """``--device``: where the models run (default: the run's or the configuration's own)."""
    parser.add_argument("--device", default=None, help="cpu, cuda or cuda:N (default: the run's own)")


def add_data(parser: argparse.ArgumentParser, default: Path | None, what: str) -> None:
    """``--data DIR``: the folder the script reads its shapes from (``what`` says which shapes)."""
    parser.add_argument("--data", type=Path, default=default, metavar="DIR", help=what)


# --------------------------------------------------------------------------------------------------------
# Result files
# --------------------------------------------------------------------------------------------------------


def commit(checkout: Path = REPO) -> str:
    """The commit id of ``checkout`` (this repository), with ``-dirty`` when tracked files differ from it
    ("unknown" without git)."""
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=checkout, capture_output=True, text=True, check=True)
        changes = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"], cwd=checkout, capture_output=True, text=True
        )
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head.stdout.strip() + ("-dirty" if changes.stdout.strip() else "")


def machine() -> dict:
    """What the figures were measured on: CPU, cores, platform, Python, torch and its threads, the GPU if any."""
    import torch  # here, so that flag parsing (--help) does not wait for torch

    return {
        "processor": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        "load_average": list(os.getloadavg()),
    }


def command() -> str:
    """The command line that ran this script, as it would be typed from the repository root; a path outside
    the repository (the user's data, caches, run folders) is shown by its last part only (``.../MPI-FAUST``),
    so that result files never point outside the repository."""
    return " ".join(["python", "-m", module_name(Path(sys.argv[0])), *map(_shown, sys.argv[1:])])


def _shown(argument: str) -> str:
    key, equals, value = argument.rpartition("=") if "=" in argument else ("", "", argument)
    path = Path(value).expanduser()
    if not path.is_absolute() and not value.startswith("~"):
        return argument
    if path.resolve().is_relative_to(REPO):
        return key + equals + str(path.resolve().relative_to(REPO))
    return key + equals + ".../" + path.name


def module_name(script: Path) -> str:
    """``benchmarks.speed.bench_operator`` for ``.../benchmarks/speed/bench_operator.py``."""
    try:
        return ".".join(script.resolve().relative_to(REPO).with_suffix("").parts)
    except ValueError:
        return str(script)


def result_file(stem: Path, suffix: str) -> Path:
    """``STEM`` + ``suffix`` (stems may hold dots, as in ``lr2e-3``, so no ``with_suffix``)."""
    return Path(f"{stem}{suffix}")


def write_json(path: Path, result: dict) -> Path:
    """Write ``result`` as indented JSON, after the commit, the machine and the command that made it,
    atomically (an interrupted run leaves the previous file)."""
    payload = {"commit": commit(), "machine": machine(), "command": command(), **result}
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, (json.dumps(payload, indent=1, default=str) + "\n").encode())
    print(f"wrote {path}")
    return path


def markdown_table(header: Sequence[str], rows: Sequence[Sequence], align: str | None = None) -> list[str]:
    """The lines of a markdown table; ``align`` has one letter per column, ``l`` or ``r`` (default: the first
    column left, the others right, as tables of figures read)."""
    align = align or "l" + "r" * (len(header) - 1)
    rule = ["---:" if side == "r" else "---" for side in align]
    return ["| " + " | ".join(str(cell) for cell in line) + " |" for line in [header, rule, *rows]]


def write_markdown(path: Path, lines: Sequence[str]) -> Path:
    """Write a markdown report, its last line saying which command and commit made it."""
    text = "\n".join([*lines, "", f"Made by `{command()}` at commit `{commit()}`."]) + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, text.encode())
    print(f"wrote {path}")
    return path


# --------------------------------------------------------------------------------------------------------
# Inputs (zernet's body and geometry modules are imported inside: they load torch and the body model's code,
# seconds that a script's --help and the scripts without bodies need not wait)
# --------------------------------------------------------------------------------------------------------


def body_surface(seed: int = 0, area: float | None = BODY_AREA, cache_dir: Path = CACHE) -> tuple[Surface, np.ndarray]:
    """One posed generated body of FAUST's topology (6,890 vertices, fingers, armpits, crotch): training body
    0 of ``seed``, scaled to ``area`` (None: as generated); returns (surface, the body part name of each vertex).
    Needs the ``bodies`` extra."""
    from zernet.data.bodies import BodyGenerator
    from zernet.data.segmentation import HUMAN_PART_NAMES
    from zernet.geometry import Surface, normalize_area

    body = BodyGenerator("faust", "varied", seed=seed, cache_dir=cache_dir).body(0)
    surface = Surface(body.vertices, body.faces, name=f"generated body (seed {seed}, {len(body.vertices)} vertices)")
    if area is not None:
        surface, _ = normalize_area(surface, area)
    return surface, np.asarray(HUMAN_PART_NAMES)[body.parts]


def ensure_bodies(
    folder: Path,
    count: int,
    n_test: int,
    seed: int,
    topology: str = "faust",
    people: int | None = None,
    forms: str | None = None,
    forms_split: str = "test",
    cache_dir: Path = CACHE,
) -> Path:
    """``folder`` holding these generated bodies (``zernet bodies``' layout), written unless the stamp file it
    leaves, ``benchmark-bodies.json``, says it already holds them; returns ``folder``."""
    from zernet.data.bodies import write_bodies

    stamp = folder / "benchmark-bodies.json"
    wanted = {"count": count, "n_test": n_test, "seed": seed, "topology": topology, "people": people}
    wanted.update(forms=forms, forms_split=forms_split)
    if stamp.is_file() and json.loads(stamp.read_text()) == wanted:
        return folder
    write_bodies(
        folder,
        count,
        seed,
        topology,
        poses="varied",
        n_test=n_test,
        cache_dir=cache_dir,
        progress=True,
        forms=forms,
        forms_split=forms_split,
        people=people,
    )
    atomic_write_bytes(stamp, json.dumps(wanted, indent=1).encode())
    return folder
