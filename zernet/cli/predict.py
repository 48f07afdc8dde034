"""``zernet predict RUN_DIR MESH --out PREFIX``: a trained run's per-vertex prediction on a new surface,
saved as numbers (``PREFIX.npy``) and as the surface coloured by it (``PREFIX.ply``)."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from zernet.cli.options import add_device, command_parser
from zernet.geometry import read_surface
from zernet.inference.model_file import checkpoint_path, load_checkpoint
from zernet.inference.predict import predict
from zernet.io_utils import atomic_write_bytes


def add_command(sub) -> None:
    parser = command_parser(
        sub,
        "predict",
        help="predict per-vertex values on a new surface",
        description="Run the model of RUN_DIR on MESH (a .ply/.obj/.off/.stl mesh, a .mat surface "
        "or a point cloud, whichever the run was trained on). Duplicate vertices are "
        "merged and degenerate faces dropped; non-manifold edges, holes and several "
        "components are used as they are. Writes PREFIX.npy (one class index or value "
        "per vertex or point of MESH) and "
        "PREFIX.ply (the surface coloured by the prediction); with --probabilities "
        "also PREFIX_probabilities.npy (classification).",
    )
    parser.add_argument("run_dir", type=Path, help="a run folder written by 'zernet train' (or a .pt checkpoint)")
    parser.add_argument("mesh", type=Path, help="the surface to predict on")
    parser.add_argument("--out", required=True, metavar="PREFIX", help="output path prefix, e.g. out/shape1")
    parser.add_argument("--probabilities", action="store_true", help="also write the per-class probabilities")
    # Repairs are always made now (one value per vertex of MESH comes back); accepted for older scripts.
    parser.add_argument("--repair", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument(
        "--backend",
        choices=["front", "fast", "accurate"],
        default=None,
        help="geodesic polar backend for MESH (default: the run's own, normally front; a point "
        "cloud is triangulated through its points for the front)",
    )
    parser.add_argument(
        "--scale",
        type=float,
        default=None,
        metavar="S",
        help="multiply MESH's coordinates by S instead of scaling it to the training area: for a "
        "partial scan, whose area is not the whole shape's",
    )
    parser.add_argument(
        "--colormap",
        default=None,
        help="matplotlib colormap for the .ply (default: tab10/tab20 for a few classes, hsv for "
        "many, viridis for values)",
    )
    parser.add_argument(
        "--refine-rings",
        type=int,
        default=None,
        metavar="N",
        help="refine over N rings of mesh neighbours (correspondence: by the neighbours' agreement; "
        "segmentation: their average where the network is unsure; default: what the run chose on its "
        "validation split; 0: off)",
    )
    parser.add_argument(
        "--refine-passes",
        type=int,
        default=None,
        metavar="P",
        help="correspondence: repeat the refinement by rings P times (default: what the run chose)",
    )
    parser.add_argument(
        "--refine-spectral",
        type=float,
        default=None,
        metavar="R",
        help="correspondence, after the rings: keep the prediction within R (a fraction of the template's "
        "geodesic diameter) of a spectral map read from it (default: what the run chose; 0: off)",
    )
    add_device(parser)
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    if not args.mesh.is_file():
        raise FileNotFoundError(f"mesh not found: {args.mesh}")
    path = checkpoint_path(args.run_dir)
    checkpoint = load_checkpoint(path)
    surface = read_surface(args.mesh)
    result = predict(
        path,
        surface,
        progress=True,  # says what was repaired
        probabilities=args.probabilities,
        device=args.device,
        refine_rings=args.refine_rings,
        refine_spectral=args.refine_spectral,
        refine_passes=args.refine_passes,
        backend=args.backend,
        scale=args.scale,
    )
    prediction, probabilities = result if args.probabilities else (result, None)

    prefix = Path(args.out)
    prefix.parent.mkdir(parents=True, exist_ok=True)
    npy_path = prefix.parent / f"{prefix.name}.npy"
    np.save(npy_path, prediction)
    written = [npy_path]
    if probabilities is not None:
        prob_path = prefix.parent / f"{prefix.name}_probabilities.npy"
        np.save(prob_path, probabilities)
        written.append(prob_path)
    ply_path = prefix.parent / f"{prefix.name}.ply"
    write_coloured_ply(ply_path, surface, prediction, checkpoint, args.colormap)
    written.append(ply_path)
    if checkpoint["task"] == "classification":
        counts = np.bincount(prediction, minlength=1)
        print(f"predicted {len(prediction)} vertices of {args.mesh}: {np.count_nonzero(counts)} distinct classes")
    else:
        print(
            f"predicted {len(prediction)} vertices of {args.mesh}: values from {prediction.min():.4g} to "
            f"{prediction.max():.4g} (mean {prediction.mean():.4g})"
        )
    for path in written:
        print(f"wrote {path}")
    return 0


def write_coloured_ply(path: Path, surface, prediction, checkpoint: dict, colormap: str | None) -> None:
    """Write the surface (mesh or point cloud, original coordinates) with vertex colours from ``prediction``."""
    import matplotlib  # here, not at start-up: `zernet --help` and the other commands do not pay for it
    import trimesh

    if checkpoint["task"] == "classification":
        n_classes = int(checkpoint["num_classes"])
        name = colormap or ("tab10" if n_classes <= 10 else "tab20" if n_classes <= 20 else "hsv")
        cmap = matplotlib.colormaps[name]
        if n_classes <= 20 and colormap is None:
            rgba = cmap(prediction % cmap.N)  # qualitative maps: one distinct colour per class
        else:
            rgba = cmap(prediction / max(n_classes - 1, 1))
    else:
        cmap = matplotlib.colormaps[colormap or "viridis"]
        low, high = float(np.min(prediction)), float(np.max(prediction))
        rgba = cmap((prediction - low) / (high - low) if high > low else np.zeros_like(prediction))
    colours = (np.asarray(rgba) * 255).round().astype(np.uint8)
    if surface.faces is not None:
        geometry = trimesh.Trimesh(surface.vertices, surface.faces, vertex_colors=colours, process=False)
    else:
        geometry = trimesh.PointCloud(surface.vertices, colors=colours)
    atomic_write_bytes(path, geometry.export(file_type="ply"))
