"""``zernet demo``: train and evaluate a small ZerNet that segments generated human bodies into 8 parts."""

from __future__ import annotations

import argparse
import copy
import time
from pathlib import Path

from zernet.cli.options import add_no_progress, add_overrides, add_workers, command_parser
from zernet.cli.train import print_metrics
from zernet.training import RunConfig, apply_overrides, load_config, parse_config, train

# The built-in demo, used when the repository's configs/demo.yaml is not available (e.g. an installed wheel).
# configs/demo.yaml carries the same settings with comments; a test keeps the two identical.
DEMO_CONFIG = {
    "data": {
        "kind": "bodies",
        "task": "segmentation",
        "count": 40,
        "n_test": 8,
        "val_count": 4,
        "topology": "coarse-615",
        "poses": "varied",
        "seed": 0,
        "features": "xyz+normals",
    },
    "patch": {
        "area": 1000,
        "scales": [{"r0": 4.0, "n_samples": 1600, "n_max": 5, "ridge": 1.0e-2, "subtract_center": False}],
    },
    "model": {"name": "zernet", "widths": [16, 32, 64, 64], "angular_resolution": 4, "pooling": "max", "dropout": 0.1},
    "train": {"epochs": 12, "patience": 6, "lr": 5.0e-3, "seed": 0, "threads": 1},
    "eval": {"renders": 3},
    "cache_dir": ".zernet-cache",
}


def demo_config() -> dict:
    """The demo configuration: ``configs/demo.yaml`` of a source checkout, else :data:`DEMO_CONFIG`."""
    repo_file = Path(__file__).resolve().parents[2] / "configs" / "demo.yaml"
    if repo_file.is_file():
        return load_config(repo_file)
    return copy.deepcopy(DEMO_CONFIG)


def add_command(sub) -> None:
    parser = command_parser(
        sub,
        "demo",
        help="train and evaluate on generated human bodies (a few minutes; needs zernet[bodies])",
        description="Train and evaluate a small ZerNet to segment generated human bodies into 8 "
        "parts (no download; configs/demo.yaml), then print the test metrics and the "
        "paths of the pictures. Takes a few minutes on a 2-core CPU, preprocessing "
        "included.",
    )
    add_overrides(parser)
    parser.add_argument(
        "--run-dir",
        type=Path,
        default=Path("runs/demo"),
        metavar="DIR",
        help="run folder (default: runs/demo; an earlier demo there is replaced)",
    )
    add_workers(parser)
    add_no_progress(parser)
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    config: RunConfig = parse_config(apply_overrides(demo_config(), args.overrides))
    started = time.perf_counter()
    metrics = train(config, args.run_dir, progress=not args.no_progress, overwrite=True, workers=args.workers)
    print(f"demo finished in {time.perf_counter() - started:.0f} s")
    print_metrics(metrics, args.run_dir)
    return 0
