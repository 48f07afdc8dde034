"""``zernet match SOURCE TARGET --out PREFIX [--run RUN] [--descriptors]``: a vertex map between two
surfaces, with the shipped template model (human bodies) unless a model file or run is given, or with the
shipped descriptor model and functional maps (``--descriptors``).

Writes ``PREFIX.npy`` and ``PREFIX.txt`` (the target vertex of each source vertex, 0-based, one per line),
``PREFIX_fmap.npy`` (the functional map, :class:`zernet.matching.match.MatchResult`),
``PREFIX_confidence.npy`` (per source vertex, in [0, 1]) and ``PREFIX.png`` (a colour field on the source
and the same field carried to the target by the map, side by side).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from zernet.cli.options import command_parser
from zernet.io_utils import atomic_write_bytes


def add_command(sub) -> None:
    parser = command_parser(
        sub,
        "match",
        help="a vertex-to-vertex correspondence between two surfaces",
        description="Match two surfaces (meshes or point clouds, any pose, placement, scale and "
        "triangulation; docs/MATCHING.md). Without --run, the template model shipped with zernet "
        "(trained on generated human bodies) names where on a body each point lies, and points are "
        "paired by that; --descriptors uses the shipped descriptor model and functional maps instead.",
    )
    parser.add_argument("source", type=Path, metavar="SOURCE", help="mesh or point-cloud file")
    parser.add_argument("target", type=Path, metavar="TARGET", help="mesh or point-cloud file")
    parser.add_argument(
        "--out",
        type=Path,
        required=True,
        metavar="PREFIX",
        help="writes PREFIX.npy / PREFIX.txt (target vertex per source vertex), PREFIX_fmap.npy, "
        "PREFIX_confidence.npy and PREFIX.png",
    )
    parser.add_argument(
        "--run",
        type=Path,
        default=None,
        metavar="RUN",
        help="a template or descriptor model file, or a descriptor training run folder (default: the "
        "shipped template model)",
    )
    parser.add_argument(
        "--descriptors",
        action="store_true",
        help="use the shipped descriptor model (descriptors, functional maps and ZoomOut) instead of the "
        "template model: for shapes other than human bodies, with a model of your own (--run)",
    )
    parser.add_argument(
        "--cache-dir",
        type=Path,
        default=None,
        metavar="DIR",
        help="cache of patch operators and eigenbases (default: none)",
    )
    parser.add_argument(
        "--same-scale",
        action="store_true",
        help="the two files are in the same units (scans from one scanner): scale both by one factor instead "
        "of each to the model's area, so that a partial SOURCE (one side of a body) is matched as a part of "
        "TARGET",
    )
    parser.add_argument(
        "--no-repair",
        action="store_true",
        help="keep the template model's map as it is: do not map again the vertices whose match does not "
        "come back (limbs read as another part; docs/MATCHING.md)",
    )
    parser.add_argument("--no-picture", action="store_true", help="skip PREFIX.png")
    parser.set_defaults(handler=run)


def source_colour_field(vertices: np.ndarray) -> np.ndarray:
    """(N,) a smooth field that tells the parts of a shape apart: the position along its first principal
    axis plus half the position along its second, each scaled to [0, 1]; a flipped left and right, or a
    swapped top and bottom, shows as a change of colour."""
    centred = vertices - vertices.mean(axis=0)
    _, _, axes = np.linalg.svd(centred, full_matrices=False)
    first, second = centred @ axes[0], centred @ axes[1]

    def unit(values):
        span = values.max() - values.min()
        return (values - values.min()) / span if span > 0 else np.zeros_like(values)

    return unit(first) + 0.5 * unit(second)


def transfer_field(field_on_source: np.ndarray, reverse_map: np.ndarray) -> np.ndarray:
    """The field carried to the target: each target vertex takes the value of its source vertex."""
    return np.asarray(field_on_source)[np.asarray(reverse_map)]


def run(args: argparse.Namespace) -> int:
    from zernet.geometry import read_surface
    from zernet.matching.match import load_matcher, match_surfaces
    from zernet.matching.model import load_matching_model
    from zernet.viz import render_side_by_side

    if args.descriptors and args.run is not None:
        raise ValueError("--descriptors picks the shipped descriptor model; with --run, give one model only")
    model = load_matching_model()[0] if args.descriptors else load_matcher(args.run)
    source, target = read_surface(args.source), read_surface(args.target)
    result, _, _ = match_surfaces(
        source, target, model, cache_dir=args.cache_dir, same_scale=args.same_scale, repair=not args.no_repair
    )
    prefix = args.out
    prefix.parent.mkdir(parents=True, exist_ok=True)
    written = [prefix.with_name(prefix.name + suffix) for suffix in (".npy", ".txt", "_fmap.npy", "_confidence.npy")]
    np.save(written[0], result.vertex_map)
    atomic_write_bytes(written[1], ("\n".join(str(int(v)) for v in result.vertex_map) + "\n").encode())
    np.save(written[2], result.fmap)
    np.save(written[3], result.confidence.astype(np.float32))
    if not args.no_picture:
        field = source_colour_field(source.vertices)
        written.append(
            render_side_by_side(
                [source, target],
                [field, transfer_field(field, result.reverse_map)],
                prefix.with_name(prefix.name + ".png"),
                [f"source {args.source.name}", f"target {args.target.name}"],
                title="colour on the source, carried to the target by the map",
            )
        )
    seconds = ", ".join(f"{name} {value:.2f} s" for name, value in result.seconds.items())
    print(
        f"matched {len(result.vertex_map)} source vertices to {len(result.reverse_map)} target vertices "
        f"(model: {_model_name(args)}; mean confidence "
        f"{float(result.confidence.mean()):.2f}; {seconds})"
    )
    for path in written:
        print(f"  {path}")
    return 0


def _model_name(args) -> str:
    if args.run is not None:
        return str(args.run)
    return "shipped descriptor model" if args.descriptors else "shipped template model"
