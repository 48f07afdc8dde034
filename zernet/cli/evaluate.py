"""``zernet evaluate RUN_DIR [RUN_DIR ...]``: the scores of a trained run, or of an ensemble of runs, on a
split of its data set."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from zernet.cli.options import add_device, add_no_progress, add_skip_bad, command_parser
from zernet.io_utils import write_json
from zernet.training import evaluate, summary_line


def add_command(sub) -> None:
    parser = command_parser(
        sub,
        "evaluate",
        help="evaluate a trained run (or an ensemble) on a split",
        description="Evaluate the validation-selected model (best.pt) of RUN_DIR on a split of its "
        "data set, print the metrics and write them to RUN_DIR/metrics-SPLIT.json "
        "(metrics.json for the test split). Several RUN_DIRs (the same recipe trained "
        "with different train.seed) are evaluated as one ensemble: the mean of their "
        "probabilities, or of their regression outputs in the transformed target units; "
        "give --out to write its metrics.",
    )
    add_skip_bad(parser)
    parser.add_argument(
        "run_dir",
        type=Path,
        nargs="+",
        help="a run folder written by 'zernet train' (or a .pt checkpoint); several: an ensemble",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=None,
        help="metrics file to write (default for one run: inside RUN_DIR; an ensemble writes only here)",
    )
    parser.add_argument("--split", default="test", help="split to evaluate: test (default), val or train")
    parser.add_argument(
        "--refine-rings",
        type=int,
        nargs="+",
        default=None,
        metavar="N",
        help="refine over N rings of mesh neighbours (correspondence: by the neighbours' agreement; "
        "segmentation: their average where the network is unsure); several: the best on the validation split "
        "(default: the run's eval.refine_rings)",
    )
    parser.add_argument(
        "--refine-passes",
        type=int,
        nargs="+",
        default=None,
        metavar="P",
        help="correspondence: repeat the refinement by rings P times, each pass refining the last one's scores; "
        "several: chosen with the rings on the validation split (default: the run's eval.refine_passes)",
    )
    parser.add_argument(
        "--refine-spectral",
        type=float,
        nargs="+",
        default=None,
        metavar="R",
        help="correspondence, after the rings: keep the prediction within R (a fraction of the template's "
        "geodesic diameter) of a spectral map read from it, which repairs flipped regions; 0: off; several: "
        "chosen with the rings on the validation split (default: the run's eval.refine_spectral)",
    )
    add_device(parser)
    add_no_progress(parser)
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    runs = args.run_dir if len(args.run_dir) > 1 else args.run_dir[0]
    # The same policy as preprocess and train: a shape that fails stops the command unless --skip-bad.
    metrics = evaluate(
        runs,
        split=args.split,
        progress=not args.no_progress,
        device=args.device,
        on_error="skip" if args.skip_bad else "raise",
        refine_rings=args.refine_rings,
        refine_spectral=args.refine_spectral,
        refine_passes=args.refine_passes,
    )
    what = f"ensemble of {len(args.run_dir)}, " if len(args.run_dir) > 1 else ""
    skipped = f"; {len(metrics['skipped'])} shapes skipped" if metrics.get("skipped") else ""
    print(f"{args.split} ({what}{metrics['n_shapes']} shapes{skipped}): {summary_line(metrics)}")
    for item in metrics.get("skipped", []):
        print(f"  skipped {item['name']}: {item['reason']}", file=sys.stderr)
    out = args.out
    if out is None and len(args.run_dir) == 1 and args.run_dir[0].is_dir():
        run_dir = args.run_dir[0]
        out = run_dir / ("metrics.json" if args.split == "test" else f"metrics-{args.split}.json")
        if out.name == "metrics.json" and out.is_file():
            # Keep what training recorded (timings, plots) and refresh the scores.
            previous = json.loads(out.read_text(encoding="utf-8"))
            previous.update(metrics)
            metrics = previous
    if out is not None:
        write_json(out, metrics)
        print(f"wrote {out}")
    return 0
