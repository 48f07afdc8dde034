"""``zernet bodies OUT``: generated human bodies with part labels and correspondence, written in the layouts
the segmentation and FAUST loaders read (docs/BODIES.md)."""

from __future__ import annotations

import argparse
from pathlib import Path

from zernet.cli.options import command_parser
from zernet.data.bodies import POSE_MODES, TOPOLOGIES, write_bodies


def add_command(sub) -> None:
    parser = command_parser(
        sub,
        "bodies",
        help="generate human bodies with part labels and correspondence (needs zernet[bodies])",
        description="Generate posed human bodies of varied shape with one shared topology, 8-part "
        "labels and template-index correspondence, written in the layouts the "
        "segmentation and FAUST loaders read (see docs/BODIES.md).",
    )
    parser.add_argument("out", type=Path, metavar="OUT", help="output folder")
    parser.add_argument("--count", type=int, default=100, help="number of bodies (default 100)")
    parser.add_argument("--n-test", type=int, default=20, help="of them, test bodies (default 20)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument(
        "--topology",
        choices=sorted(TOPOLOGIES),
        default="faust",
        help="shared mesh: faust (6,890 vertices), full, or a coarse one (default faust)",
    )
    parser.add_argument(
        "--poses",
        choices=sorted(POSE_MODES),
        default="varied",
        help="rest, mild, varied or wide joint rotations (wide: arms overhead, crossed, squats, one-leg "
        "stands, and weight and muscle over the whole range; docs/BODIES.md) (default varied)",
    )
    parser.add_argument(
        "--cache-dir",
        type=Path,
        default=Path(".zernet-cache"),
        metavar="DIR",
        help="cache of the body model's topology and generated bodies (default .zernet-cache)",
    )
    parser.add_argument(
        "--forms",
        default=None,
        metavar="LIST",
        help="also write the bodies as scans come: a comma-separated list of remeshed, decimated, cloud, "
        "cloud-noisy, partial, or 'all' (default none; under OUT/forms, see docs/BODIES.md)",
    )
    parser.add_argument(
        "--people",
        type=int,
        default=None,
        metavar="P",
        help="FAUST's structure: P people in COUNT/P poses each, consecutive bodies one person, the test "
        "bodies whole people (e.g. --count 100 --people 10: 8 people to train on, 2 unseen to test)",
    )
    parser.add_argument(
        "--forms-split",
        choices=("test", "all"),
        default="test",
        help="bodies that get forms: the test bodies or all (default test)",
    )
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    layout = write_bodies(
        args.out,
        count=args.count,
        seed=args.seed,
        topology=args.topology,
        poses=args.poses,
        n_test=args.n_test,
        cache_dir=args.cache_dir,
        progress=True,
        forms=args.forms,
        forms_split=args.forms_split,
        people=args.people,
    )
    print(f"{args.count} bodies ({args.topology}, {args.poses} poses) written to {layout.root}; see {layout.readme}")
    if layout.forms is not None:
        which = "the test bodies" if args.forms_split == "test" else "all bodies"
        print(f"forms {', '.join(layout.forms.forms)} of {which}: {layout.forms.root}")
    return 0
