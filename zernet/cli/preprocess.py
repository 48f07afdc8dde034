"""``zernet preprocess CONFIG``: build and cache the patch operators of a data set, so training starts at once."""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

from zernet.cli.options import (
    add_no_progress,
    add_overrides,
    add_skip_bad,
    add_workers,
    command_parser,
    overrides_with_skip_bad,
)
from zernet.data import SkippedShapesWarning
from zernet.training import build_dataset, check_model_config, read_config


def add_command(sub) -> None:
    parser = command_parser(
        sub,
        "preprocess",
        help="build and cache the patch operators of a data set",
        description="Preprocess every shape of the data set described by CONFIG (area "
        "normalisation, sampling, geodesic polar coordinates, patch operators) in "
        "parallel and store the results under the config's cache_dir. Shapes already "
        "cached are skipped, so training afterwards starts at once. A shape that fails "
        "is listed with its reason and the command exits with status 2, unless "
        "--skip-bad.",
    )
    add_overrides(parser)
    add_skip_bad(parser)
    parser.add_argument("config", type=Path, help="YAML configuration file (see configs/)")
    add_workers(parser)
    add_no_progress(parser)
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    config = read_config(args.config, overrides_with_skip_bad(args))  # fails on a bad key now, before any work
    check_model_config(config)
    started = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SkippedShapesWarning)  # listed below instead
        dataset = build_dataset(config, progress=not args.no_progress, workers=args.workers)
    seconds = time.perf_counter() - started
    print(
        f"preprocessed {dataset.summary() if hasattr(dataset, 'summary') else len(dataset)} "
        f"in {seconds:.1f} s; cache: {config.cache_dir}"
    )
    if not dataset.patch_configs:
        print(f"no patch operators built: model {config.model.name} reads only the mesh edges")
    failures = getattr(dataset, "failures", {})
    if failures:
        print(f"{len(failures)} shapes skipped (--skip-bad / data.on_error: skip):", file=sys.stderr)
    for name, reason in failures.items():
        print(f"  skipped {name}: {reason}", file=sys.stderr)
    return 0
