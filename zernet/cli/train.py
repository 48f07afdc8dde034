"""``zernet train CONFIG``: train a model, choose its epoch on the validation split, evaluate it on the test
split, and write the run folder; ``--resume`` continues an interrupted run."""

from __future__ import annotations

import argparse
from pathlib import Path

from zernet.cli.errors import UsageError
from zernet.cli.options import (
    add_no_progress,
    add_overrides,
    add_skip_bad,
    add_workers,
    command_parser,
    overrides_with_skip_bad,
)
from zernet.distributed import is_main
from zernet.training import RESUME_CHANGEABLE, read_config, summary_line, train


def add_command(sub) -> None:
    parser = command_parser(
        sub,
        "train",
        help="train a model from a YAML configuration",
        description="Train a model, select the best epoch on the validation split, evaluate it on "
        "the test split and write the run folder: config.yaml, last.pt, best.pt, "
        "train.log, metrics.json and plots/. Before training, every shape is loaded and "
        "preprocessed: if any fails, all failures are listed and nothing is trained "
        "(exit status 2) unless --skip-bad.",
    )
    add_overrides(parser)
    add_skip_bad(parser)
    parser.add_argument(
        "config",
        type=Path,
        nargs="?",
        default=None,
        help="YAML configuration file (optional with --resume: the run's own config.yaml is used)",
    )
    parser.add_argument(
        "--run-dir", type=Path, default=None, metavar="DIR", help="run folder (default: runs/<config file name>)"
    )
    parser.add_argument(
        "--resume", action="store_true", help="continue the run in --run-dir exactly where its last checkpoint left off"
    )
    parser.add_argument(
        "--overwrite", action="store_true", help="start afresh even if the run folder already holds a checkpoint"
    )
    parser.add_argument(
        "--init-from",
        type=Path,
        default=None,
        metavar="RUN",
        help="start from the weights of another run (its folder, i.e. its best.pt, or a .pt file): the "
        "convolutions are taken, the output layer is new where the number of classes differs",
    )
    add_workers(parser)
    add_no_progress(parser)
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    if args.config is None and not args.resume:
        raise UsageError("train needs a CONFIG file (or --resume with --run-dir of an existing run)")
    if args.resume and args.run_dir is None:
        raise UsageError("--resume needs --run-dir: the run folder to continue")
    if args.resume and args.overwrite:
        raise UsageError("--resume and --overwrite contradict each other")
    if args.resume and args.init_from is not None:
        raise UsageError(
            "--init-from starts a new run from another run's weights; a run continued with --resume "
            "keeps its own weights (and the init-from it started with)"
        )
    overrides = overrides_with_skip_bad(args)
    if args.config is not None:
        config = read_config(args.config, overrides)
    elif overrides:
        # --resume --set ...: the run's own configuration with the overrides (only some keys may change).
        stored = args.run_dir / "config.yaml"
        if not stored.is_file():
            raise UsageError(f"--resume --set needs {stored} (or give the CONFIG file)")
        _check_resume_overrides(overrides)
        config = read_config(stored, overrides)
    else:
        config = None
    run_dir = args.run_dir or Path("runs") / args.config.stem
    metrics = train(
        config,
        run_dir,
        resume=args.resume,
        progress=not args.no_progress,
        overwrite=args.overwrite,
        workers=args.workers,
        init_from=args.init_from,
    )
    if is_main():  # under torchrun, rank 0 alone evaluated the model and reports
        print_metrics(metrics, run_dir)
    return 0


def _check_resume_overrides(overrides: list[str]) -> None:
    """On resume, ``--set`` may only change the keys that do not change the weights still to train."""
    allowed = {f"{section}.{key}" for section, key in RESUME_CHANGEABLE}
    refused = [item.partition("=")[0].strip() for item in overrides if item.partition("=")[0].strip() not in allowed]
    if refused:
        raise UsageError(
            f"--resume --set cannot change {', '.join(refused)}: on resume only "
            f"{', '.join(sorted(allowed))} may change (train a new run with --run-dir for others)"
        )


def print_metrics(metrics: dict, run_dir: Path) -> None:
    """The final banner of a training run: the split the scores are of, the selected epoch, skipped shapes,
    the files."""
    split = metrics.get("split", "test")
    skipped = metrics.get("skipped") or []
    extra = f", {len(skipped)} shapes skipped" if skipped else ""
    print(
        f"{split} metrics ({metrics.get('n_shapes', '?')} shapes, model of epoch {metrics.get('best_epoch')} "
        f"chosen on validation{extra}): {summary_line(metrics)}"
    )
    if split == "val":
        print(
            "  note: no test shapes; these are scores on the validation split, the one the model was chosen "
            "on, so they overstate how it does on new shapes"
        )
    for item in skipped:
        print(f"  skipped {item['name']}: {item['reason']}")
    print(f"run folder: {run_dir}")
    print(f"  metrics:  {run_dir / 'metrics.json'}")
    for plot in metrics.get("plots", []):
        print(f"  picture:  {plot}")
