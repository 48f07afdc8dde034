"""Scans as users bring them: one segmentation model, trained on clean generated bodies, on every other form.

In one run, on the same generated FAUST-sized bodies (``zernet bodies OUT --forms all``: 80 training bodies
with 8 carved for validation, 20 test bodies, each test body also remeshed, decimated with the
non-manifold edges a simplifier leaves, sampled as a uniform cloud and as a half-density noisy cloud of
uneven density, and cut to a partial scan; ground truth through the position on the original body):

1. trains each model in ``--models`` (a run folder per model under ``--runs``; an existing run with a
   ``best.pt`` is reused) with ``configs/bodies_segmentation.yaml``, changing only the data folders, the
   model name and the epochs (and, for ``zernet-mixed``, the training set and the scaling: ``MODELS``);
2. predicts every form of every test body with ``zernet.inference.predict`` (what ``zernet predict`` does:
   repairs, the backend chosen by the kind of surface, the refinement the run chose on validation, one
   value per input vertex), and scores the
   vertex accuracy against the form's ground truth; a form that raises counts as *refused*;
3. writes ``benchmarks/results/scans.md`` and ``scans.json`` (accuracy per model and form, pooled over the
   vertices of the 20 test bodies, its drop from the original form, refusals, seconds per shape) and one
   picture per form and zernet model (``scans_<form>.png``, ``scans_mixed_<form>.png``: the first test body
   coloured by the predicted part, and where the prediction is wrong).

Partial scans cover part of the body, so scaling them to the training area would enlarge them: they are
scaled instead by the factor that takes the training bodies (all in metres) to the training area, the
median over the training bodies, as a user who knows their scanner's units would (``predict(scale=...)``,
``zernet predict --scale``).

    .venv/bin/python benchmarks/scans.py --bodies data/scans --runs runs/scans --models zernet feastnet zernet-mixed
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import numpy as np  # noqa: E402
import yaml  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

from zernet.data.bodies import closest_points  # noqa: E402
from zernet.data.segmentation import HUMAN_PART_NAMES  # noqa: E402
from zernet.geometry import Surface, read_surface  # noqa: E402
from zernet.inference import load_checkpoint  # noqa: E402
from zernet.inference.predict import predict  # noqa: E402
from zernet.io_utils import atomic_write_bytes, write_json  # noqa: E402
from zernet.training import load_config  # noqa: E402
from zernet.training.config import apply_overrides  # noqa: E402
from zernet.viz import render_comparison  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
CONFIG = ROOT / "configs" / "bodies_segmentation.yaml"
FORMS = ("original", "remeshed", "decimated", "cloud", "cloud-noisy", "partial")
#: zernet and FeaStNet (the same widths and dropout) trained on the original bodies; zernet-mixed: zernet
#: trained from scratch on the original training bodies plus the forms of the first training bodies
#: (MIXED_FORM_BODIES: augmentation by remeshing, decimation, resampling and one-sided views), at one fixed
#: scale
#: (``patch.scale``: the training bodies' median factor to the training area) instead of per-shape area
#: normalisation, which would enlarge a partial scan to a whole body's area; with the heat kernel signature
#: as input and every input seen by the head (:data:`MIXED_RECIPE`).
MODELS = ("zernet", "feastnet", "zernet-mixed")
#: Form -> how many training bodies (the first ones) join the mixed training set in that form. Partial
#: scans and both clouds of all 80 rather than 40: each chosen on 10 validation bodies of another seed in
#: every form (docs/RECIPES.md, "Segmentation of scans"); with the clouds of 80, refined, every form was as
#: good or better (noisy half clouds 93.2 -> 94.3 %, clouds 96.3 -> 96.5, the rest within 0.15).
#: ``--mixed FORM=N`` changes it for one call.
MIXED_FORM_BODIES = {"remeshed": 40, "decimated": 40, "cloud": 80, "cloud-noisy": 80, "partial": 80}
#: What the mixed recipe changes in the configuration besides the data and the scale: the head also sees
#: the inputs (``model.input_skip``) and the inputs include the heat kernel signature (``hks``), so the model
#: knows where on the body a point is, which the patches (centre value subtracted, a few radii wide) do not
#: tell it: chosen on the validation bodies of seed 7 (docs/RECIPES.md), clouds 96.5 -> 98.1 %, noisy half
#: clouds 94.3 -> 96.7, partial scans 95.4 -> 97.9, meshes +0.3-0.4.
MIXED_RECIPE = ("data.features=xyz+normals+hks", "model.input_skip=true")
#: Models whose predictions are drawn, and the suffix of their pictures' names.
PICTURES = {"zernet": "", "zernet-mixed": "_mixed"}
#: Model options only zernet takes.
ZERNET_ONLY = ("angular_resolution", "pooling")


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--bodies",
        type=Path,
        default=ROOT / "data" / "scans",
        help="folder written by 'zernet bodies OUT --forms all' (made if missing)",
    )
    parser.add_argument("--runs", type=Path, default=ROOT / "runs" / "scans", help="one run folder per model")
    parser.add_argument("--models", nargs="+", default=["zernet"], choices=MODELS)
    parser.add_argument("--forms", nargs="+", default=list(FORMS), choices=FORMS)
    parser.add_argument("--epochs", type=int, default=15)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--limit", type=int, default=None, help="only the first N test bodies")
    parser.add_argument("--out", default="scans", help="stem of the result files in benchmarks/results")
    parser.add_argument(
        "--mixed",
        nargs="+",
        default=[],
        metavar="FORM=N",
        help="zernet-mixed: take FORM of the first N training bodies (default: MIXED_FORM_BODIES)",
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
    mixed = dict(MIXED_FORM_BODIES)
    for item in args.mixed:
        form, _, count = item.partition("=")
        if form not in mixed or not count.isdigit() or not 0 <= int(count) <= 80:
            parser.error(f"--mixed {item}: expected FORM=N with FORM one of {', '.join(mixed)} and N in 0-80")
        mixed[form] = int(count)
    args.mixed = mixed
    return args


def ensure_bodies(bodies: Path) -> None:
    """Generate the bodies and their forms unless they are there."""
    if (bodies / "forms").is_dir() and (bodies / "segmentation").is_dir():
        return
    subprocess.run(
        [
            sys.executable,
            "-m",
            "zernet.cli",
            "bodies",
            str(bodies),
            "--count",
            "100",
            "--n-test",
            "20",
            "--seed",
            "0",
            "--forms",
            "all",
        ],
        check=True,
    )


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
        # All the epochs, the best on validation kept: its 8 validation shapes (noisy clouds among them) move
        # by up to 2 points from one epoch to the next, and patience 4 stopped it at epoch 8 of 18.
        config["train"]["patience"] = None
        config = apply_overrides(config, [*MIXED_RECIPE, *args.overrides])
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
    ``form_bodies`` (:data:`MIXED_FORM_BODIES`) of that many of the first training bodies (generated if
    missing)."""
    forms = bodies / "train-forms"
    if not all((forms / "forms" / form / "meshes" / "train").is_dir() for form in form_bodies):
        subprocess.run(
            [
                sys.executable,
                "-m",
                "zernet.cli",
                "bodies",
                str(forms),
                "--count",
                "100",
                "--n-test",
                "20",
                "--seed",
                "0",
                "--forms",
                ",".join(MIXED_FORM_BODIES),
                "--forms-split",
                "all",
            ],
            check=True,
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


def markdown(results: dict, args, scale: float) -> str:
    mixed = args.mixed
    lines = [
        "# Scans as users bring them: segmentation on every form of 20 held-out generated bodies",
        "",
        "zernet and FeaStNet trained on the original (clean, shared-topology) training bodies only; "
        "zernet-mixed: zernet trained on the original training bodies plus "
        + ", ".join(f"{form} forms of {count}" for form, count in mixed.items())
        + " of them, at one fixed scale (`patch.scale`) instead of per-shape area normalisation, with "
        + ", ".join(f"`{item}`" for item in MIXED_RECIPE)
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
        "| model | form | accuracy | drop | worst shape | by a boundary | there / elsewhere | refused | rings "
        "| s / shape |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
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
            lines.append(f"| {model} | {form} | " + " | ".join(cells) + " |")
    lines += ["", "Command: `" + " ".join(["python benchmarks/scans.py", *sys.argv[1:]]) + "`", ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    args = parse_args(argv)
    ensure_bodies(args.bodies)
    scale = training_scale(args.bodies, 15000.0)
    results = {}
    for model in args.models:
        run_dir = ensure_run(model, args.bodies, args.runs / model, args)
        results[model] = {}
        for form in args.forms:
            files = form_files(args.bodies, form)[: args.limit]
            picture = RESULTS / f"{args.out}{PICTURES[model]}_{form}.png" if model in PICTURES else None
            row = score_form(run_dir, args.bodies, files, scale if form == "partial" else None, picture)
            row["refine_rings"] = int(load_checkpoint(run_dir / "best.pt").get("refine_rings", 0))
            results[model][form] = row
            accuracy = "-" if row["accuracy"] is None else f"{100 * row['accuracy']:.2f} %"
            print(f"{model:9} {form:12} {accuracy:>9}  refused {len(row['refused'])}", flush=True)
    # Models measured by an earlier call with the same --out are kept (one model at a time fits a session).
    stored = RESULTS / f"{args.out}.json"
    if stored.is_file():
        earlier = json.loads(stored.read_text())["models"]
        results = {**{m: r for m, r in earlier.items() if m not in results}, **results}
    write_json(stored, {"models": results, "partial_scale": scale, "argv": sys.argv[1:]})
    atomic_write_bytes(RESULTS / f"{args.out}.md", markdown(results, args, scale).encode())
    print(markdown(results, args, scale))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
