"""Scans as users bring them: one segmentation model, trained on clean generated bodies, on every other form.

In one run, on the same generated FAUST-sized bodies (``zernet bodies OUT --forms all``: 80 training bodies
with 8 carved for validation, 20 test bodies, each test body also remeshed, decimated with the
non-manifold edges a simplifier leaves, sampled as a uniform cloud and as a half-density noisy cloud of
uneven density, and cut to a partial scan; ground truth through the position on the original body):

1. trains each model in ``--models`` (a run folder per model under ``--runs``; an existing run with a
   ``best.pt`` is reused) with ``configs/bodies_segmentation.yaml``, changing only the data folders, the
   model name and the epochs (and, for ``zernet-mixed``, the training set, the scaling and the recipe of
   ``configs/recipes/scans.yaml``: ``MODELS``);
2. predicts every form of every test body with ``zernet.inference.predict`` (what ``zernet predict`` does:
   repairs, the backend chosen by the kind of surface, the refinement the run chose on validation, one
   value per input vertex), and scores the
   vertex accuracy against the form's ground truth; a form that raises counts as *refused*;
3. writes ``benchmarks/experiments/results/scans.md`` and ``scans.json`` (``--out``) (accuracy per model and form, pooled over the
   vertices of the 20 test bodies, its drop from the original form, refusals, seconds per shape) and one
   picture per form and zernet model (``scans_<form>.png``, ``scans_mixed_<form>.png``: the first test body
   coloured by the predicted part, and where the prediction is wrong).

Partial scans cover part of the body, so scaling them to the training area would enlarge them: they are
scaled instead by the factor that takes the training bodies (all in metres) to the training area, the
median over the training bodies, as a user who knows their scanner's units would (``predict(scale=...)``,
``zernet predict --scale``).

    .venv/bin/python -m benchmarks.experiments.scans --bodies data/scans --runs runs/scans --models zernet feastnet zernet-mixed
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import numpy as np
import yaml
from scipy.spatial import cKDTree

from benchmarks.harness import (
    EXPERIMENT_RESULTS,
    RECIPES,
    REPO,
    add_out,
    add_threads,
    arguments,
    ensure_bodies,
    markdown_table,
    result_file,
    write_json,
    write_markdown,
)
from zernet.data.bodies import closest_points
from zernet.data.segmentation import HUMAN_PART_NAMES
from zernet.geometry import Surface, read_surface
from zernet.inference import load_checkpoint
from zernet.inference.predict import predict
from zernet.training import load_config
from zernet.training.config import apply_overrides
from zernet.viz import render_comparison

#: The mixed recipe: ``base``, ``recipes["zernet-mixed"]`` (--set overrides), ``mixed_form_bodies``.
BOOK = yaml.safe_load((RECIPES / "scans.yaml").read_text())
CONFIG = REPO / BOOK["base"]
FORMS = ("original", "remeshed", "decimated", "cloud", "cloud-noisy", "partial")
#: zernet and FeaStNet (the same widths and dropout) trained on the original bodies; zernet-mixed: zernet
#: trained from scratch on the original training bodies plus forms of the first training bodies, at one
#: fixed scale, with the recipe of configs/recipes/scans.yaml.
MODELS = ("zernet", "feastnet", "zernet-mixed")
#: Models whose predictions are drawn, and the suffix of their pictures' names.
PICTURES = {"zernet": "", "zernet-mixed": "_mixed"}
#: Model options only zernet takes.
ZERNET_ONLY = ("angular_resolution", "pooling")


def parse_args(argv=None) -> argparse.Namespace:
    parser = arguments(__doc__)
    parser.add_argument(
        "--bodies",
        type=Path,
        default=REPO / "data" / "scans",
        help="folder written by 'zernet bodies OUT --forms all' (made if missing)",
    )
    parser.add_argument("--runs", type=Path, default=REPO / "runs" / "scans", help="one run folder per model")
    parser.add_argument("--models", nargs="+", default=["zernet"], choices=MODELS)
    parser.add_argument("--forms", nargs="+", default=list(FORMS), choices=FORMS)
    parser.add_argument("--epochs", type=int, default=15)
    add_threads(parser, default=1)
    parser.add_argument("--limit", type=int, default=None, help="only the first N test bodies")
    add_out(parser, EXPERIMENT_RESULTS / "scans")
    parser.add_argument(
        "--mixed",
        nargs="+",
        default=[],
        metavar="FORM=N",
        help="zernet-mixed: take FORM of the first N training bodies (default: mixed_form_bodies of "
        "configs/recipes/scans.yaml)",
    )
    parser.add_argument(
        "--set",
        nargs="+",
        default=[],
        metavar="KEY=VALUE",
        dest="overrides",
        help="zernet-mixed: change the recipe's configuration, as 'zernet train --set' does "
        "(e.g. data.features=xyz+normals+hks model.input_skip=true)",
    )
    args = parser.parse_args(argv)
    mixed = dict(BOOK["mixed_form_bodies"])
    for item in args.mixed:
        form, _, count = item.partition("=")
        if form not in mixed or not count.isdigit() or not 0 <= int(count) <= 80:
            parser.error(f"--mixed {item}: expected FORM=N with FORM one of {', '.join(mixed)} and N in 0-80")
        mixed[form] = int(count)
    args.mixed = mixed
    return args


def ensure_run(model: str, bodies: Path, run_dir: Path, args) -> Path:
    """Train ``model`` (see :data:`MODELS`) unless ``run_dir`` already holds a trained run."""
    if (run_dir / "best.pt").is_file():
        return run_dir
    config = load_config(CONFIG)
    segmentation = bodies / "segmentation"
    config["data"].update(meshes=str(segmentation / "meshes"), labels=str(segmentation / "labels"))
    config["train"].update(epochs=args.epochs, threads=args.threads)
    config["eval"]["renders"] = 0
    if model == "feastnet":
        config["model"] = {key: value for key, value in config["model"].items() if key not in ZERNET_ONLY}
        config["model"]["name"] = "feastnet"
    if model == "zernet-mixed":
        mixed = mixed_training_folder(bodies, args.mixed)
        config["data"].update(meshes=str(mixed / "meshes"), labels=str(mixed / "labels"))
        config["patch"]["scale"] = training_scale(bodies, config["patch"].pop("area"))
        config = apply_overrides(config, [*BOOK["recipes"]["zernet-mixed"], *args.overrides])
    path = run_dir.parent / f"{model}.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(config))
    subprocess.run(
        [
            sys.executable,
            "-m",
            "zernet.cli",
            "train",
            str(path),
            "--run-dir",
            str(run_dir),
            "--no-progress",
            "--workers",
            str(args.threads),
        ],
        check=True,
    )
    return run_dir


def mixed_training_folder(bodies: Path, form_bodies: dict[str, int]) -> Path:
    """A segmentation folder of links: the original training and test bodies, plus each form of
    ``form_bodies`` (``--mixed``) of that many of the first training bodies (generated if
    missing)."""
    forms = ensure_bodies(
        bodies / "train-forms", 100, 20, 0, forms=",".join(BOOK["mixed_form_bodies"]), forms_split="all"
    )
    mixed = bodies / ("mixed-" + "-".join(f"{form}{count}" for form, count in form_bodies.items()))
    links = [
        (bodies / "segmentation" / kind / split / f"{path.stem}{suffix}", mixed / kind / split / f"{path.stem}{suffix}")
        for split in ("train", "test")
        for path in sorted((bodies / "segmentation" / "meshes" / split).glob("*.ply"))
        for kind, suffix in (("meshes", ".ply"), ("labels", ".txt"))
    ]
    for form, count in form_bodies.items():
        for path in sorted((forms / "forms" / form / "meshes" / "train").glob("*.ply"))[:count]:
            for kind, suffix in (("meshes", ".ply"), ("labels", ".txt")):
                links.append(
                    (
                        forms / "forms" / form / kind / "train" / f"{path.stem}{suffix}",
                        mixed / kind / "train" / f"{path.stem}_{form}{suffix}",
                    )
                )
    for source, link in links:
        link.parent.mkdir(parents=True, exist_ok=True)
        if not link.exists():
            link.symlink_to(source.resolve())
    return mixed


def form_files(bodies: Path, form: str, stem: str = "*") -> list[tuple[Path, Path]]:
    """(surface file, label file) of every test body in ``form`` (``stem``: only that body)."""
    root = bodies / "segmentation" if form == "original" else bodies / "forms" / form
    meshes = sorted((root / "meshes" / "test").glob(f"{stem}.ply"))
    return [(mesh, root / "labels" / "test" / f"{mesh.stem}.txt") for mesh in meshes]


def training_scale(bodies: Path, area: float) -> float:
    """Median factor that takes a training body to ``area`` (the scale for partial scans)."""
    areas = []
    for path in sorted((bodies / "segmentation" / "meshes" / "train").glob("*.ply")):
        areas.append(read_surface(path).area)
    return float(np.sqrt(area / np.median(areas)))


def near_part_boundary(points: np.ndarray, original: Surface, labels: np.ndarray) -> np.ndarray:
    """(M,) bool: the points whose place on the original body lies in a triangle with corners of two parts.

    There the ground truth (the part of the triangle's nearest corner) runs along the original
    triangulation's edges, jagged at the scale of a triangle, which no other sampling of the surface shows. A
    point at a vertex of the original (the original form, partial scans) counts if any triangle at that vertex
    has two parts; any other point by the triangle nearest to it.
    """
    corner_parts = labels[original.faces]
    two_part = corner_parts.min(axis=1) != corner_parts.max(axis=1)
    at_two_part_vertex = np.zeros(original.n_vertices, dtype=bool)
    at_two_part_vertex[original.faces[two_part].ravel()] = True
    distance, vertex = cKDTree(original.vertices).query(points)
    face, _, _, _ = closest_points(original.vertices, original.faces, points)
    on_vertex = distance <= 1e-6 * np.linalg.norm(np.ptp(original.vertices, axis=0))
    return np.where(on_vertex, at_two_part_vertex[vertex], two_part[face])


def score_form(run_dir: Path, bodies: Path, files, scale: float | None, picture: Path | None) -> dict:
    """Pooled vertex accuracy of the run on ``files``, also apart for the points by a part boundary of the
    original body (:func:`near_part_boundary`) and the others, refusals and seconds per shape."""
    correct = total = 0
    boundary_correct = boundary_total = elsewhere_correct = 0
    refused, seconds, per_shape = [], [], []
    for number, (mesh, labels) in enumerate(files):
        truth = np.loadtxt(labels, dtype=np.int64).reshape(-1)
        original, original_labels = form_files(bodies, "original", mesh.stem)[0]
        near = near_part_boundary(
            read_surface(mesh).vertices, read_surface(original), np.loadtxt(original_labels, dtype=np.int64)
        )
        started = time.perf_counter()
        try:
            prediction = predict(run_dir, mesh, scale=scale, cache_dir=run_dir / "scan-cache")
        except Exception as error:  # a refusal is a result here: count it and say why
            refused.append(f"{mesh.name}: {type(error).__name__}: {error}")
            continue
        seconds.append(time.perf_counter() - started)
        right = prediction == truth
        correct += int(right.sum())
        total += len(truth)
        boundary_correct += int(right[near].sum())
        boundary_total += int(near.sum())
        elsewhere_correct += int(right[~near].sum())
        per_shape.append(float((prediction == truth).mean()))
        if number == 0 and picture is not None:
            surface = read_surface(mesh)
            render_comparison(
                surface,
                prediction,
                truth,
                prediction != truth,
                picture,
                class_names=HUMAN_PART_NAMES,
                title=f"{mesh.parent.parent.parent.name}: {mesh.stem}, "
                f"{100 * per_shape[-1]:.1f} % of {len(truth)} vertices",
            )
    return {
        "accuracy": correct / total if total else None,
        "near_boundary_share": boundary_total / total if total else None,
        "accuracy_near_boundary": boundary_correct / boundary_total if boundary_total else None,
        "accuracy_elsewhere": elsewhere_correct / (total - boundary_total) if total > boundary_total else None,
        "shapes": len(per_shape),
        "vertices": total,
        "per_shape_min": min(per_shape) if per_shape else None,
        "refused": refused,
        "seconds_per_shape_median": float(np.median(seconds)) if seconds else None,
    }


def percent(fraction: float | None, digits: int = 1) -> str:
    """``fraction`` in percent, or "-" for a row measured before the figure existed."""
    return "-" if fraction is None else f"{100 * fraction:.{digits}f} %"


def markdown(results: dict, args, scale: float) -> list[str]:
    mixed = args.mixed
    lines = [
        "# Scans as users bring them: segmentation on every form of 20 held-out generated bodies",
        "",
        "zernet and FeaStNet trained on the original (clean, shared-topology) training bodies only; "
        "zernet-mixed: zernet trained on the original training bodies plus "
        + ", ".join(f"{form} forms of {count}" for form, count in mixed.items())
        + " of them, at one fixed scale (`patch.scale`) instead of per-shape area normalisation, with "
        + ", ".join(f"`{item}`" for item in BOOK["recipes"]["zernet-mixed"])
        + ". Test split: 20 bodies "
        "never seen in training, each in every form (`zernet bodies ... --forms all`). Accuracy pooled over "
        "the vertices (points) of the form, against the ground truth carried from the original body; "
        "*drop*: points below the original form; *refused*: shapes that raised; *rings*: the refinement the "
        "run chose on its validation split (the vertices the network is unsure of take the average of that "
        "many rings, `eval.refine_rings`; 0: none), applied as `zernet predict` applies it; *by a boundary*: "
        "the share of the points whose place on the original body lies in a triangle with corners of two parts, "
        "where the ground truth (the part of the nearest corner) follows the original triangulation's edges, and "
        "the accuracy there / on all other points.",
        f"Partial scans scaled by the training bodies' median factor {scale:.2f} (`predict(scale=...)`).",
        "",
    ]
    header = ["model", "form", "accuracy", "drop", "worst shape", "by a boundary", "there / elsewhere"]
    header += ["refused", "rings", "s / shape"]
    rows = []
    for model, forms in results.items():
        original = forms.get("original", {}).get("accuracy")
        for form, row in forms.items():
            accuracy, worst, seconds = row["accuracy"], row["per_shape_min"], row["seconds_per_shape_median"]
            drop = (
                ""
                if accuracy is None or original is None or form == "original"
                else f"{100 * (original - accuracy):.1f}"
            )
            cells = [
                "-" if accuracy is None else f"{100 * accuracy:.1f} %",
                drop,
                "-" if worst is None else f"{100 * worst:.1f} %",
                percent(row.get("near_boundary_share")),
                f"{percent(row.get('accuracy_near_boundary'))} / {percent(row.get('accuracy_elsewhere'), 2)}",
                f"{len(row['refused'])} / {row['shapes'] + len(row['refused'])}",
                str(row.get("refine_rings", 0)),
                "-" if seconds is None else f"{seconds:.1f}",
            ]
            rows.append([model, form, *cells])
    return lines + markdown_table(header, rows, align="llrrrrrrrr")


def main(argv=None) -> int:
    args = parse_args(argv)
    ensure_bodies(args.bodies, 100, 20, 0, forms="all")
    scale = training_scale(args.bodies, 15000.0)
    results = {}
    for model in args.models:
        run_dir = ensure_run(model, args.bodies, args.runs / model, args)
        results[model] = {}
        for form in args.forms:
            files = form_files(args.bodies, form)[: args.limit]
            picture = result_file(args.out, f"{PICTURES[model]}_{form}.png") if model in PICTURES else None
            row = score_form(run_dir, args.bodies, files, scale if form == "partial" else None, picture)
            row["refine_rings"] = int(load_checkpoint(run_dir / "best.pt").get("refine_rings", 0))
            results[model][form] = row
            accuracy = "-" if row["accuracy"] is None else f"{100 * row['accuracy']:.2f} %"
            print(f"{model:9} {form:12} {accuracy:>9}  refused {len(row['refused'])}", flush=True)
    # Models measured by an earlier call with the same --out are kept (one model at a time fits a session).
    stored = result_file(args.out, ".json")
    if stored.is_file():
        earlier = json.loads(stored.read_text())["models"]
        results = {**{m: r for m, r in earlier.items() if m not in results}, **results}
    write_json(stored, {"models": results, "partial_scale": scale})
    lines = markdown(results, args, scale)
    write_markdown(result_file(args.out, ".md"), lines)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
