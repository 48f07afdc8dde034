"""Scans as users bring them: one segmentation model, trained on clean generated bodies, on every other form.

In one run, on the same generated FAUST-sized bodies (``zernet bodies OUT --forms all``: 80 training bodies
with 8 carved for validation, 20 test bodies, each test body also remeshed, decimated with the
non-manifold edges a simplifier leaves, sampled as a uniform cloud and as a half-density noisy cloud of
uneven density, and cut to a partial scan; ground truth through the position on the original body):

1. trains each model in ``--models`` (a run folder per model under ``--runs``; an existing run with a
   ``best.pt`` is reused) with ``configs/bodies_segmentation.yaml``, changing only the data folders, the
   model name and the epochs, with ``data.forms={}`` (the bodies as given); ``zernet-mixed`` trains with the
   scaling and the recipe of ``configs/recipes/scans.yaml`` instead, forms of its training bodies among them
   (``MODELS``);
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

With ``--real DIR`` (FAUST's segmentation scans of people 0-7, ``DIR/meshes/tr_reg_XXX.ply`` and
``DIR/labels/tr_reg_XXX.txt``, kept outside the repository) it checks the shipped recipe on real people
instead: ``configs/segmentation.yaml`` trained on people 0-5 as shipped (forms of its training scans) and
with ``data.forms={}`` (the two side by side, one process each), both scored on people 6-7 in every form
made from their scans plus the scans' own vertices as a cloud, written to ``scans_real.json`` and
``scans_real.md`` beside the generated bodies' figures of ``scans.json``:

    .venv/bin/python -m benchmarks.experiments.scans --real ~/real/faust_seg --runs ~/runs/scans-real --epochs 6
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
from zernet.data.source import ShapeSource
from zernet.data.training_forms import load_form
from zernet.geometry import Surface, read_surface
from zernet.inference import load_checkpoint
from zernet.inference.predict import predict
from zernet.training import load_config
from zernet.training.config import apply_overrides
from zernet.viz import render_comparison

#: The mixed recipe: ``base`` and ``recipes["zernet-mixed"]`` (--set overrides).
BOOK = yaml.safe_load((RECIPES / "scans.yaml").read_text())
CONFIG = REPO / BOOK["base"]
FORMS = ("original", "remeshed", "decimated", "cloud", "cloud-noisy", "partial")
#: zernet and FeaStNet (the same widths and dropout) trained on the original bodies; zernet-mixed: zernet
#: trained from scratch on the original training bodies plus forms of them (data.forms), at one fixed scale,
#: with the recipe of configs/recipes/scans.yaml.
MODELS = ("zernet", "feastnet", "zernet-mixed")
#: Models whose predictions are drawn, and the suffix of their pictures' names.
PICTURES = {"zernet": "", "zernet-mixed": "_mixed"}
#: Model options only zernet takes.
ZERNET_ONLY = ("angular_resolution", "pooling")

#: The real-people check (--real): the shipped segmentation configuration trained as shipped (forms of its
#: training scans) and, the baseline, on the scans alone. FAUST scan XXX shows person XXX // 10: people 0-5
#: train (the configuration carves its validation scans from them), people 6-7 are scored.
REAL_CONFIG = REPO / "configs" / "segmentation.yaml"
REAL_MODELS = {"forms": [], "meshes": ["data.forms={}"]}
REAL_MODEL_NAMES = {"forms": "shipped (forms)", "meshes": "meshes only"}
REAL_TRAINED = range(0, 60)
REAL_SCORED = range(60, 80)
#: Seed of the scored scans' forms (plus the scan's number).
REAL_FORM_SEED = 5300
#: The parts of FAUST's segmentation labels, in the order of their values 1-8 (Maron et al.'s; read off the
#: scans: 1 lies above the shoulders, 2 at the ends of the arms, 8 at the ends of the legs).
REAL_PART_NAMES = ("head", "hand", "lower arm", "upper arm", "torso", "upper leg", "lower leg", "foot")
#: Parts where a cloud's triangulation may join what the surface keeps apart (fingers, the lips).
EXTREMITIES = (REAL_PART_NAMES.index("head"), REAL_PART_NAMES.index("hand"))
#: The generated bodies' models shown beside the real people (from scans.json): meshes only, and with forms.
GENERATED_BESIDE = {"zernet": "meshes only", "zernet-mixed": "mixed recipe (forms)"}


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
    parser.add_argument(
        "--limit", type=int, default=None, help="only the first N test bodies (--real: scans, people 6 and 7 in turn)"
    )
    add_out(parser, EXPERIMENT_RESULTS / "scans")
    parser.add_argument(
        "--set",
        nargs="+",
        default=[],
        metavar="KEY=VALUE",
        dest="overrides",
        help="zernet-mixed and the --real runs: change their configuration, as 'zernet train --set' does "
        "(e.g. data.features=xyz+normals+hks model.input_skip=true)",
    )
    parser.add_argument(
        "--real",
        type=Path,
        default=None,
        metavar="DIR",
        help="instead of generated bodies: the real-people check on FAUST's segmentation scans of people 0-7, "
        "DIR/meshes/tr_reg_XXX.ply and DIR/labels/tr_reg_XXX.txt (see REAL_MODELS)",
    )
    parser.add_argument(
        "--cache-dir",
        type=Path,
        default=None,
        help="--real: the runs' and the scoring's cache (default: RUNS/cache)",
    )
    parser.add_argument(
        "--refine-rings",
        type=int,
        default=None,
        metavar="N",
        help="--real: score with this refinement (rings averaged where the network is unsure; 0: none) instead "
        "of what each run chose on its validation meshes",
    )
    return parser.parse_args(argv)


def ensure_run(model: str, bodies: Path, run_dir: Path, args) -> Path:
    """Train ``model`` (see :data:`MODELS`) unless ``run_dir`` already holds a trained run."""
    if (run_dir / "best.pt").is_file():
        return run_dir
    config = load_config(CONFIG)
    segmentation = bodies / "segmentation"
    config["data"].update(meshes=str(segmentation / "meshes"), labels=str(segmentation / "labels"))
    config["train"].update(epochs=args.epochs, threads=args.threads)
    config["eval"]["renders"] = 0
    # The shipped configuration trains on forms of its training bodies; these models train on the bodies alone.
    config["data"]["forms"] = {}
    if model == "feastnet":
        config["model"] = {key: value for key, value in config["model"].items() if key not in ZERNET_ONLY}
        config["model"]["name"] = "feastnet"
    if model == "zernet-mixed":
        config["patch"]["scale"] = training_scale(bodies, config["patch"].pop("area"))
        config = apply_overrides(config, [*BOOK["recipes"]["zernet-mixed"], *args.overrides])
    if start_training(config, run_dir, args.threads).wait() != 0:
        raise SystemExit(f"training {model} failed: see {run_dir / 'train.log'}")
    return run_dir


def start_training(config: dict, run_dir: Path, threads: int) -> subprocess.Popen:
    """``zernet train`` of ``config`` into ``run_dir`` started in its own process (its configuration written
    beside the run folder)."""
    path = run_dir.parent / f"{run_dir.name}.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(config))
    command = [sys.executable, "-m", "zernet.cli", "train", str(path), "--run-dir", str(run_dir)]
    return subprocess.Popen([*command, "--no-progress", "--workers", str(threads)])


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
    lines = [
        "# Scans as users bring them: segmentation on every form of 20 held-out generated bodies",
        "",
        "zernet and FeaStNet trained on the original (clean, shared-topology) training bodies only; "
        "zernet-mixed: zernet trained on the original training bodies plus forms of them, at one fixed scale "
        "(`patch.scale`) instead of per-shape area normalisation, with "
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
    if args.real is not None:
        return real_people(args)
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


# The real-people check (--real): the shipped segmentation recipe on real people, in every form.


def real_people(args) -> int:
    """Train both :data:`REAL_MODELS` on people 0-5 (side by side), score them on people 6-7 in every form,
    write ``<out>_real.json`` and ``<out>_real.md`` beside the generated bodies' figures."""
    run_dirs = ensure_real_runs(args)
    cache_dir = args.cache_dir or args.runs / "cache"
    scored = sorted(REAL_SCORED, key=lambda number: (number % 10, number))[: args.limit]
    tallies = {model: {form: FormTally() for form in [*args.forms, "vertices"]} for model in REAL_MODELS}
    for number in scored:
        for form, (surface, truth) in real_forms(args.real, number, args.forms).items():
            for model, run_dir in run_dirs.items():
                tally = tallies[model][form]
                started = time.perf_counter()
                try:
                    prediction = predict(run_dir, surface, cache_dir=cache_dir, refine_rings=args.refine_rings)
                except Exception as error:  # a refusal is a result here: count it and say why
                    tally.refused.append(f"tr_reg_{number:03d}: {type(error).__name__}: {error}")
                    continue
                tally.add(prediction, truth, time.perf_counter() - started)
                print(f"{model:12} tr_reg_{number:03d} {form:12} {100 * tally.per_shape[-1]:6.2f} %", flush=True)
    results = {model: {form: tally.row() for form, tally in forms.items()} for model, forms in tallies.items()}
    training = {}
    for model, run_dir in run_dirs.items():
        checkpoint = load_checkpoint(run_dir / "best.pt")
        final = load_checkpoint(run_dir / "last.pt")["state"]  # the whole run, not up to its best epoch
        training[model] = {"seconds": float(final["train_seconds"]), "epochs": int(final["epoch"])}
        chosen = checkpoint.get("refine_rings", 0) if args.refine_rings is None else args.refine_rings
        for row in results[model].values():
            row["refine_rings"] = int(chosen)
    stored = result_file(args.out, ".json")
    generated = json.loads(stored.read_text())["models"] if stored.is_file() else {}
    write_json(
        result_file(args.out, "_real.json"),
        {
            "models": results,
            "training": training,
            "overrides": args.overrides,
            "refine_rings_override": args.refine_rings,
            "scored_scans": [f"tr_reg_{number:03d}" for number in scored],
            "epochs": args.epochs,
        },
    )
    lines = real_markdown(results, generated, scored, args, training)
    write_markdown(result_file(args.out, "_real.md"), lines)
    print("\n".join(lines))
    return 0


def ensure_real_runs(args) -> dict[str, Path]:
    """The run folder of each of :data:`REAL_MODELS`, trained on people 0-5 (both at once, one process
    each) unless the folder already holds a trained run."""
    data = args.runs / "real-data"
    for number in [*REAL_TRAINED, *REAL_SCORED]:
        split = "train" if number in REAL_TRAINED else "test"
        for kind, suffix in (("meshes", ".ply"), ("labels", ".txt")):
            link = data / kind / split / f"tr_reg_{number:03d}{suffix}"
            link.parent.mkdir(parents=True, exist_ok=True)
            if not link.exists():
                link.symlink_to((args.real / kind / link.name).resolve())
    run_dirs = {model: args.runs / f"real-{model}" for model in REAL_MODELS}
    started = {}
    for model, overrides in REAL_MODELS.items():
        if (run_dirs[model] / "best.pt").is_file():
            continue
        config = load_config(REAL_CONFIG)
        config["data"].update(meshes=str(data / "meshes"), labels=str(data / "labels"))
        config["train"].update(epochs=args.epochs, threads=args.threads)
        config["eval"]["renders"] = 0
        config["cache_dir"] = str(args.cache_dir or args.runs / "cache")
        config = apply_overrides(config, [*overrides, *args.overrides])
        started[model] = start_training(config, run_dirs[model], args.threads)
    failed = [model for model, process in started.items() if process.wait() != 0]
    if failed:
        raise SystemExit(f"training {', '.join(failed)} failed: see train.log in {args.runs}")
    return run_dirs


def real_forms(real: Path, number: int, forms) -> dict[str, tuple[Surface, np.ndarray]]:
    """Scan ``number`` in each of ``forms`` and as its own vertices without the faces (``"vertices"``, the
    cloud the issue measured): (surface, 0-based label per vertex or point). A form is made as ``data.forms``
    makes forms of training shapes (:func:`~zernet.data.training_forms.load_form`, the generator of
    :mod:`zernet.data.bodies.forms`, seeded by the scan's number): each of its vertices or points takes the
    label of the scan vertex it comes from. Its "cloud" samples the surface uniformly by area (as many points
    as vertices), so it holds fewer points on the hands and the face than the registration's vertices do."""
    name = f"tr_reg_{number:03d}"
    surface = read_surface(real / "meshes" / f"{name}.ply")
    labels = np.loadtxt(real / "labels" / f"{name}.txt", dtype=np.int64) - 1  # the files count parts from 1
    source = ShapeSource(name=name, load=lambda: (surface, labels))
    made = {}
    for form in forms:
        made[form] = (surface, labels) if form == "original" else load_form(source, form, REAL_FORM_SEED + number)
    made["vertices"] = (Surface(surface.vertices, None, name=f"{name} (vertices)"), labels)
    return made


class FormTally:
    """Pooled counts of one model on one form: right points overall and per true part, per scan, seconds."""

    def __init__(self):
        self.right = np.zeros(len(REAL_PART_NAMES), dtype=np.int64)
        self.points = np.zeros(len(REAL_PART_NAMES), dtype=np.int64)
        self.per_shape: list[float] = []
        self.seconds: list[float] = []
        self.refused: list[str] = []

    def add(self, prediction: np.ndarray, truth: np.ndarray, seconds: float) -> None:
        parts = len(REAL_PART_NAMES)
        self.right += np.bincount(truth[prediction == truth], minlength=parts)
        self.points += np.bincount(truth, minlength=parts)
        self.per_shape.append(float((prediction == truth).mean()))
        self.seconds.append(seconds)

    def row(self) -> dict:
        extremities = np.isin(np.arange(len(REAL_PART_NAMES)), EXTREMITIES)
        return {
            "accuracy": share(self.right.sum(), self.points.sum()),
            "accuracy_head_and_hands": share(self.right[extremities].sum(), self.points[extremities].sum()),
            "accuracy_elsewhere": share(self.right[~extremities].sum(), self.points[~extremities].sum()),
            "head_and_hands_share": share(self.points[extremities].sum(), self.points.sum()),
            "accuracy_per_part": {
                name: share(right, points) for name, right, points in zip(REAL_PART_NAMES, self.right, self.points)
            },
            "shapes": len(self.per_shape),
            "vertices": int(self.points.sum()),
            "per_shape_min": min(self.per_shape) if self.per_shape else None,
            "refused": self.refused,
            "seconds_per_shape_median": float(np.median(self.seconds)) if self.seconds else None,
        }


def share(part: int, whole: int) -> float | None:
    """``part / whole`` as a float, None for an empty whole."""
    return float(part / whole) if whole else None


def real_markdown(results: dict, generated: dict, scored: list[int], args, training: dict) -> list[str]:
    """The lines of ``scans_real.md``: the real people's table, then the generated bodies' (``scans.json``),
    and each real run's training time."""
    lines = [
        "# The real-people check: segmentation of real scans in every form",
        "",
        f"`configs/segmentation.yaml` as shipped (`data.forms` on) and the same with `data.forms={{}}` (meshes "
        f"only){' with ' + ', '.join(f'`{item}`' for item in args.overrides) if args.overrides else ''}, trained on "
        f"FAUST's segmentation scans of people 0-5 (tr_reg_000-059; {args.epochs} epochs, {args.threads} "
        f"thread(s) each), scored on {len(scored)} scans of people 6-7 (tr_reg_060-079) in every form: the "
        "registration mesh and forms of it made as `data.forms` makes them (`zernet/data/bodies/forms.py` through "
        "`zernet.data.training_forms.load_form`: remeshed, decimated, a cloud sampled uniformly by area with as "
        "many points as vertices, half as many points with 2 mm of noise, one-sided) and the scan's own vertices "
        "as a cloud (*vertices*: denser on the hands and face than a uniform cloud), each point labelled by the "
        "scan vertex it comes from, predicted by "
        "`zernet.inference.predict` as given (area-normalised, "
        + ("the run's refinement" if args.refine_rings is None else f"refined over {args.refine_rings} rings")
        + "). Accuracy pooled over the "
        "points; *drop*: points below the mesh; *head+hands / rest*: accuracy on the points of those parts "
        "(where a cloud's triangulation can bridge fingers or close the mouth) and on the others.",
        "",
    ]
    header = ["data", "model", "form", "accuracy", "drop", "worst scan", "head+hands / rest", "refused", "rings"]
    rows = []
    for model, forms in results.items():
        mesh = forms.get("original", {}).get("accuracy")
        for form, row in forms.items():
            accuracy = row["accuracy"]
            drop = "" if None in (accuracy, mesh) or form == "original" else f"{100 * (mesh - accuracy):.1f}"
            rows.append(
                [
                    "real",
                    REAL_MODEL_NAMES[model],
                    form,
                    percent(accuracy, 2),
                    drop,
                    percent(row["per_shape_min"]),
                    f"{percent(row['accuracy_head_and_hands'])} / {percent(row['accuracy_elsewhere'])}",
                    f"{len(row['refused'])} / {row['shapes'] + len(row['refused'])}",
                    str(row["refine_rings"]),
                ]
            )
    for model, name in GENERATED_BESIDE.items():
        forms = generated.get(model, {})
        mesh = forms.get("original", {}).get("accuracy")
        for form, row in forms.items():
            accuracy = row["accuracy"]
            drop = "" if None in (accuracy, mesh) or form == "original" else f"{100 * (mesh - accuracy):.1f}"
            refused = f"{len(row['refused'])} / {row['shapes'] + len(row['refused'])}"
            rows.append(["generated", name, form, percent(accuracy, 2), drop, percent(row["per_shape_min"]), "-"])
            rows[-1] += [refused, str(row.get("refine_rings", 0))]
    times = "; ".join(
        f"{REAL_MODEL_NAMES[model]} {row['epochs']} epochs in {row['seconds'] / 60:.1f} min"
        for model, row in training.items()
    )
    return [*lines, *markdown_table(header, rows, align="lllrrrrrr"), "", f"Training time (wall clock): {times}."]


if __name__ == "__main__":
    raise SystemExit(main())
