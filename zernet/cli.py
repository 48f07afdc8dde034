"""The ``zernet`` command: preprocess, train, evaluate, predict, demo.

Every subcommand has ``--help``. Problems a user can fix (a missing file, a bad configuration key, an
unknown model, a malformed mesh) are reported as one line on stderr with exit code 2; ``--debug`` shows
the full traceback instead. Training interrupted with Ctrl-C can be continued with ``--resume``.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from zernet.data import DatasetError, PreprocessError, SkippedShapesWarning
from zernet.data.bodies import POSE_MODES as BODY_POSES
from zernet.data.bodies import TOPOLOGIES as BODY_TOPOLOGIES
from zernet.data.bodies import write_bodies
from zernet.distributed import is_main
from zernet.geometry import SurfaceError, read_surface
from zernet.io_utils import atomic_write_bytes, write_json
from zernet.matching.cli import add_match_command
from zernet.training import (
    RESUME_CHANGEABLE,
    ConfigError,
    RunConfig,
    apply_overrides,
    build_dataset,
    check_model_config,
    checkpoint_path,
    evaluate,
    keep_freed_memory,
    load_checkpoint,
    load_config,
    parse_config,
    predict,
    read_config,
    summary_line,
    train,
)

__all__ = ["main", "build_parser", "DEMO_CONFIG", "demo_config"]

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

EXIT_USER_ERROR = 2


class _UsageError(Exception):
    """A command-line problem detected by the CLI itself (reported like any user error)."""


def demo_config() -> dict:
    """The demo configuration: ``configs/demo.yaml`` of a source checkout, else :data:`DEMO_CONFIG`."""
    repo_file = Path(__file__).resolve().parent.parent / "configs" / "demo.yaml"
    if repo_file.is_file():
        return load_config(repo_file)
    return copy.deepcopy(DEMO_CONFIG)


# --------------------------------------------------------------------------------------------------------
# Parser
# --------------------------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    """The ``zernet`` parser: one subcommand per public entry point, each with its own ``--help``."""
    common = argparse.ArgumentParser(add_help=False)
    # SUPPRESS: a subcommand's --debug must not reset a --debug given before the subcommand.
    common.add_argument(
        "--debug",
        action="store_true",
        default=argparse.SUPPRESS,
        help="show full tracebacks instead of one-line errors",
    )
    skip_bad = argparse.ArgumentParser(add_help=False)
    skip_bad.add_argument(
        "--skip-bad",
        action="store_true",
        help="leave out shapes that fail to load or preprocess (each is listed with its reason, "
        "in train.log and metrics.json too) instead of stopping; the same as "
        "data.on_error: skip",
    )
    overrides = argparse.ArgumentParser(add_help=False)
    overrides.add_argument(
        "--set",
        dest="overrides",
        nargs="+",
        action="extend",
        default=[],
        metavar="KEY=VALUE",
        help="override config entries with dotted keys, e.g. --set train.epochs=5 "
        "model.name=feastnet patch.scales.0.r0=4.5 (values are read as YAML)",
    )

    parser = argparse.ArgumentParser(
        prog="zernet",
        description="Convolutional neural networks on curved surfaces (ZerNet): preprocess, train, evaluate, "
        "predict, demo.",
        epilog="Run 'zernet COMMAND --help' for the options of one command. Start with 'zernet demo'.",
    )
    parser.add_argument(
        "--debug", action="store_true", default=False, help="show full tracebacks instead of one-line errors"
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    _add_preprocess_command(sub, [common, overrides, skip_bad])
    _add_train_command(sub, [common, overrides, skip_bad])
    _add_evaluate_command(sub, [common, skip_bad])
    _add_predict_command(sub, [common])
    _add_demo_command(sub, [common, overrides])
    _add_bodies_command(sub, [common])
    add_match_command(sub, [common])
    return parser


def _add_preprocess_command(sub, parents: list[argparse.ArgumentParser]) -> None:
    """The ``zernet preprocess`` subcommand."""
    p = sub.add_parser(
        "preprocess",
        parents=parents,
        help="build and cache the patch operators of a data set",
        description="Preprocess every shape of the data set described by CONFIG (area "
        "normalisation, sampling, geodesic polar coordinates, patch operators) in "
        "parallel and store the results under the config's cache_dir. Shapes already "
        "cached are skipped, so training afterwards starts at once. A shape that fails "
        "is listed with its reason and the command exits with status 2, unless "
        "--skip-bad.",
    )
    p.add_argument("config", type=Path, help="YAML configuration file (see configs/)")
    p.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="N",
        help="worker processes (default: the data module's choice, one per core)",
    )
    p.set_defaults(func=_cmd_preprocess)


def _add_train_command(sub, parents: list[argparse.ArgumentParser]) -> None:
    """The ``zernet train`` subcommand."""
    p = sub.add_parser(
        "train",
        parents=parents,
        help="train a model from a YAML configuration",
        description="Train a model, select the best epoch on the validation split, evaluate it on "
        "the test split and write the run folder: config.yaml, last.pt, best.pt, "
        "train.log, metrics.json and plots/. Before training, every shape is loaded and "
        "preprocessed: if any fails, all failures are listed and nothing is trained "
        "(exit status 2) unless --skip-bad.",
    )
    p.add_argument(
        "config",
        type=Path,
        nargs="?",
        default=None,
        help="YAML configuration file (optional with --resume: the run's own config.yaml is used)",
    )
    p.add_argument(
        "--run-dir", type=Path, default=None, metavar="DIR", help="run folder (default: runs/<config file name>)"
    )
    p.add_argument(
        "--resume", action="store_true", help="continue the run in --run-dir exactly where its last checkpoint left off"
    )
    p.add_argument(
        "--overwrite", action="store_true", help="start afresh even if the run folder already holds a checkpoint"
    )
    p.add_argument(
        "--init-from",
        type=Path,
        default=None,
        metavar="RUN",
        help="start from the weights of another run (its folder, i.e. its best.pt, or a .pt file): the "
        "convolutions are taken, the output layer is new where the number of classes differs",
    )
    p.add_argument("--workers", type=int, default=None, metavar="N", help="preprocessing worker processes")
    p.add_argument("--no-progress", action="store_true", help="no progress bars (log lines only)")
    p.set_defaults(func=_cmd_train)


def _add_evaluate_command(sub, parents: list[argparse.ArgumentParser]) -> None:
    """The ``zernet evaluate`` subcommand."""
    p = sub.add_parser(
        "evaluate",
        parents=parents,
        help="evaluate a trained run (or an ensemble) on a split",
        description="Evaluate the validation-selected model (best.pt) of RUN_DIR on a split of its "
        "data set, print the metrics and write them to RUN_DIR/metrics-SPLIT.json "
        "(metrics.json for the test split). Several RUN_DIRs (the same recipe trained "
        "with different train.seed) are evaluated as one ensemble: the mean of their "
        "probabilities, or of their regression outputs in the transformed target units; "
        "give --out to write its metrics.",
    )
    p.add_argument(
        "run_dir",
        type=Path,
        nargs="+",
        help="a run folder written by 'zernet train' (or a .pt checkpoint); several: an ensemble",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="metrics file to write (default for one run: inside RUN_DIR; an ensemble writes only here)",
    )
    p.add_argument("--split", default="test", help="split to evaluate: test (default), val or train")
    p.add_argument(
        "--refine-rings",
        type=int,
        nargs="+",
        default=None,
        metavar="N",
        help="refine over N rings of mesh neighbours (correspondence: by the neighbours' agreement; "
        "segmentation: their average where the network is unsure); several: the best on the validation split "
        "(default: the run's eval.refine_rings)",
    )
    p.add_argument(
        "--refine-spectral",
        type=float,
        nargs="+",
        default=None,
        metavar="R",
        help="correspondence, after the rings: keep the prediction within R (a fraction of the template's "
        "geodesic diameter) of a spectral map read from it, which repairs flipped regions; 0: off; several: "
        "chosen with the rings on the validation split (default: the run's eval.refine_spectral)",
    )
    p.add_argument("--device", default=None, help="override the run's device (cpu, cuda, ...)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=_cmd_evaluate)


def _add_predict_command(sub, parents: list[argparse.ArgumentParser]) -> None:
    """The ``zernet predict`` subcommand."""
    p = sub.add_parser(
        "predict",
        parents=parents,
        help="predict per-vertex values on a new surface",
        description="Run the model of RUN_DIR on MESH (a .ply/.obj/.off/.stl mesh, a .mat surface "
        "or a point cloud, whichever the run was trained on). Duplicate vertices are "
        "merged and degenerate faces dropped; non-manifold edges, holes and several "
        "components are used as they are. Writes PREFIX.npy (one class index or value "
        "per vertex or point of MESH) and "
        "PREFIX.ply (the surface coloured by the prediction); with --probabilities "
        "also PREFIX_probabilities.npy (classification).",
    )
    p.add_argument("run_dir", type=Path, help="a run folder written by 'zernet train' (or a .pt checkpoint)")
    p.add_argument("mesh", type=Path, help="the surface to predict on")
    p.add_argument("--out", required=True, metavar="PREFIX", help="output path prefix, e.g. out/shape1")
    p.add_argument("--probabilities", action="store_true", help="also write the per-class probabilities")
    # Repairs are always made now (one value per vertex of MESH comes back); accepted for older scripts.
    p.add_argument("--repair", action="store_true", help=argparse.SUPPRESS)
    p.add_argument(
        "--backend",
        choices=["front", "fast", "accurate"],
        default=None,
        help="geodesic polar backend for MESH (default: the run's own, normally front; a point "
        "cloud is triangulated through its points for the front)",
    )
    p.add_argument(
        "--scale",
        type=float,
        default=None,
        metavar="S",
        help="multiply MESH's coordinates by S instead of scaling it to the training area: for a "
        "partial scan, whose area is not the whole shape's",
    )
    p.add_argument(
        "--colormap",
        default=None,
        help="matplotlib colormap for the .ply (default: tab10/tab20 for a few classes, hsv for "
        "many, viridis for values)",
    )
    p.add_argument(
        "--refine-rings",
        type=int,
        default=None,
        metavar="N",
        help="refine over N rings of mesh neighbours (correspondence: by the neighbours' agreement; "
        "segmentation: their average where the network is unsure; default: what the run chose on its "
        "validation split; 0: off)",
    )
    p.add_argument(
        "--refine-spectral",
        type=float,
        default=None,
        metavar="R",
        help="correspondence, after the rings: keep the prediction within R (a fraction of the template's "
        "geodesic diameter) of a spectral map read from it (default: what the run chose; 0: off)",
    )
    p.add_argument("--device", default=None, help="override the run's device (cpu, cuda, ...)")
    p.set_defaults(func=_cmd_predict)


def _add_demo_command(sub, parents: list[argparse.ArgumentParser]) -> None:
    """The ``zernet demo`` subcommand."""
    p = sub.add_parser(
        "demo",
        parents=parents,
        help="train and evaluate on generated human bodies (a few minutes; needs zernet[bodies])",
        description="Train and evaluate a small ZerNet to segment generated human bodies into 8 "
        "parts (no download; configs/demo.yaml), then print the test metrics and the "
        "paths of the pictures. Takes a few minutes on a 2-core CPU, preprocessing "
        "included.",
    )
    p.add_argument(
        "--run-dir",
        type=Path,
        default=Path("runs/demo"),
        metavar="DIR",
        help="run folder (default: runs/demo; an earlier demo there is replaced)",
    )
    p.add_argument("--workers", type=int, default=None, metavar="N", help="preprocessing worker processes")
    p.add_argument("--no-progress", action="store_true", help="no progress bars (log lines only)")
    p.set_defaults(func=_cmd_demo)


def _add_bodies_command(sub, parents: list[argparse.ArgumentParser]) -> None:
    """The ``zernet bodies`` subcommand."""
    p = sub.add_parser(
        "bodies",
        parents=parents,
        help="generate human bodies with part labels and correspondence (needs zernet[bodies])",
        description="Generate posed human bodies of varied shape with one shared topology, 8-part "
        "labels and template-index correspondence, written in the layouts the "
        "segmentation and FAUST loaders read (see docs/BODIES.md).",
    )
    p.add_argument("out", type=Path, metavar="OUT", help="output folder")
    p.add_argument("--count", type=int, default=100, help="number of bodies (default 100)")
    p.add_argument("--n-test", type=int, default=20, help="of them, test bodies (default 20)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument(
        "--topology",
        choices=sorted(BODY_TOPOLOGIES),
        default="faust",
        help="shared mesh: faust (6,890 vertices), full, or a coarse one (default faust)",
    )
    p.add_argument(
        "--poses",
        choices=sorted(BODY_POSES),
        default="varied",
        help="rest, mild or varied joint rotations (default varied)",
    )
    p.add_argument(
        "--cache-dir",
        type=Path,
        default=Path(".zernet-cache"),
        metavar="DIR",
        help="cache of the body model's topology and generated bodies (default .zernet-cache)",
    )
    p.add_argument(
        "--forms",
        default=None,
        metavar="LIST",
        help="also write the bodies as scans come: a comma-separated list of remeshed, decimated, cloud, "
        "cloud-noisy, partial, or 'all' (default none; under OUT/forms, see docs/BODIES.md)",
    )
    p.add_argument(
        "--people",
        type=int,
        default=None,
        metavar="P",
        help="FAUST's structure: P people in COUNT/P poses each, consecutive bodies one person, the test "
        "bodies whole people (e.g. --count 100 --people 10: 8 people to train on, 2 unseen to test)",
    )
    p.add_argument(
        "--forms-split",
        choices=("test", "all"),
        default="test",
        help="bodies that get forms: the test bodies or all (default test)",
    )
    p.set_defaults(func=_cmd_bodies)


# --------------------------------------------------------------------------------------------------------
# Commands
# --------------------------------------------------------------------------------------------------------


def _cmd_bodies(args) -> int:
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


def _cmd_preprocess(args) -> int:
    config = read_config(args.config, _with_skip_bad(args))  # fails on a bad key now, before any work
    check_model_config(config)
    started = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SkippedShapesWarning)  # listed below instead
        dataset = build_dataset(config, progress=True, workers=args.workers)
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


def _with_skip_bad(args) -> list[str]:
    """The ``--set`` overrides, with ``data.on_error=skip`` last when ``--skip-bad`` is given."""
    return list(args.overrides) + (["data.on_error=skip"] if getattr(args, "skip_bad", False) else [])


def _cmd_train(args) -> int:
    if args.config is None and not args.resume:
        raise _UsageError("train needs a CONFIG file (or --resume with --run-dir of an existing run)")
    if args.resume and args.run_dir is None:
        raise _UsageError("--resume needs --run-dir: the run folder to continue")
    if args.resume and args.overwrite:
        raise _UsageError("--resume and --overwrite contradict each other")
    if args.resume and args.init_from is not None:
        raise _UsageError(
            "--init-from starts a new run from another run's weights; a run continued with --resume "
            "keeps its own weights (and the init-from it started with)"
        )
    overrides = _with_skip_bad(args)
    if args.config is not None:
        config = read_config(args.config, overrides)
    elif overrides:
        # --resume --set ...: the run's own configuration with the overrides (only some keys may change).
        stored = args.run_dir / "config.yaml"
        if not stored.is_file():
            raise _UsageError(f"--resume --set needs {stored} (or give the CONFIG file)")
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
        _print_metrics(metrics, run_dir)
    return 0


def _check_resume_overrides(overrides: list[str]) -> None:
    """On resume, ``--set`` may only change the keys that do not change the weights still to train."""
    allowed = {f"{section}.{key}" for section, key in RESUME_CHANGEABLE}
    refused = [item.partition("=")[0].strip() for item in overrides if item.partition("=")[0].strip() not in allowed]
    if refused:
        raise _UsageError(
            f"--resume --set cannot change {', '.join(refused)}: on resume only "
            f"{', '.join(sorted(allowed))} may change (train a new run with --run-dir for others)"
        )


def _cmd_evaluate(args) -> int:
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


def _cmd_predict(args) -> int:
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
    _write_coloured_ply(ply_path, surface, prediction, checkpoint, args.colormap)
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


def _write_coloured_ply(path: Path, surface, prediction, checkpoint: dict, colormap: str | None) -> None:
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


def _cmd_demo(args) -> int:
    config: RunConfig = parse_config(apply_overrides(demo_config(), args.overrides))
    started = time.perf_counter()
    metrics = train(config, args.run_dir, progress=not args.no_progress, overwrite=True, workers=args.workers)
    print(f"demo finished in {time.perf_counter() - started:.0f} s")
    _print_metrics(metrics, args.run_dir)
    return 0


def _print_metrics(metrics: dict, run_dir: Path) -> None:
    """The final banner: the split the scores are of, the selected epoch, skipped shapes, the files."""
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


# --------------------------------------------------------------------------------------------------------
# Entry point
# --------------------------------------------------------------------------------------------------------


def _user_errors() -> tuple[type[BaseException], ...]:
    """Exceptions that describe a problem the user can fix: reported as one line, exit code 2."""
    return (
        _UsageError,
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
_ADVICE = (
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
    for api_text, by_command in _ADVICE:
        if api_text in message:
            message = message.replace(api_text, by_command.get(command, by_command["*"]))
    return message


def _error_lines(command: str, error: BaseException) -> list[str]:
    """The lines reporting a user error: one line, or for shapes that failed, one line per shape."""
    message = str(error.args[0]) if isinstance(error, KeyError) and error.args else str(error)
    message = command_advice(command, message)
    lines = [line.rstrip() for line in message.splitlines() if line.strip()]
    if isinstance(error, PreprocessError):
        return [f"zernet {command}: error: {lines[0]}"] + [f"  {line.strip()}" for line in lines[1:]]
    return [f"zernet {command}: error: " + ("; ".join(line.strip() for line in lines) or type(error).__name__)]


def _one_line_warnings(command: str):
    """A ``warnings.showwarning`` that prints ``zernet COMMAND: warning: message`` on one line (no source
    line, which reads like a crash)."""

    def show(message, category, filename, lineno, file=None, line=None):
        text = "; ".join(part.strip() for part in str(message).splitlines() if part.strip())
        print(f"zernet {command}: warning: {command_advice(command, text)}", file=file or sys.stderr)

    return show


def main(argv: list[str] | None = None) -> int:
    """Run the ``zernet`` command; returns the exit code (0 success, 2 user error, 1 internal error)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    debug = bool(getattr(args, "debug", False))
    keep_freed_memory()
    previous_showwarning = warnings.showwarning
    warnings.showwarning = _one_line_warnings(args.command)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print(
            "zernet: interrupted (a training run continues with: zernet train --resume --run-dir DIR)", file=sys.stderr
        )
        return 130
    except Exception as error:
        if debug:
            raise
        if isinstance(error, _user_errors()):
            for line in _error_lines(args.command, error):
                print(line, file=sys.stderr)
            return EXIT_USER_ERROR
        message = "; ".join(line.strip() for line in str(error).splitlines() if line.strip())
        print(
            f"zernet {args.command}: internal error: {type(error).__name__}: {message} "
            "(rerun with --debug for the traceback)",
            file=sys.stderr,
        )
        return 1
    finally:
        warnings.showwarning = previous_showwarning


if __name__ == "__main__":
    sys.exit(main())
