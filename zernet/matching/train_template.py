"""Training a template model (:mod:`zernet.matching.template`) on generated bodies, or fine-tuning it on registered scans.

    python -m zernet.matching.train_template data/template-bodies runs/template --out bodies_template.pt

1. ``zernet bodies BODIES --count 500 --n-test 10 --topology coarse-1229 --forms remeshed,cloud,cloud-noisy,
   partial --forms-split all`` (skipped when BODIES already holds them);
2. a training folder of links (:func:`write_training_folder`): every training body as generated and in each
   form, labelled with the template vertex of each vertex or point (the forms' ``correspondence`` files);
   the test split holds the test bodies as generated, remeshed and one-sided;
3. ``zernet train`` with :func:`template_config` (a segmentation run whose classes are the template's
   vertices), from the shipped backbone ``pretrained:bodies-xyz-hks`` unless ``--init-from`` says otherwise;
4. the run's best checkpoint written as a template model file with the template's rest positions
   (:func:`rest_positions`) and its provenance (:func:`zernet.matching.template.save_template_model`).

Fine-tuning on real people (``--registrations``): a folder of registered scans that share one triangulation
(FAUST's training registrations, a user's own registered scans) has a correspondence among its scans but
none to the template. :func:`consensus_labels` gives it one: the template model to be fine-tuned reads every
scan, and each registration vertex takes the template vertex nearest the per-vertex median of its template
positions over all the scans, so the scans the model reads wrongly (an arm raised overhead read as the other
arm) are outvoted by those it reads right. :func:`write_registration_folder` writes each scan as the model
reads it (its coarse copy at the model's area, turned into the model's frame) with those labels, and the run
makes the other forms itself (``data.forms``, :data:`REGISTRATION_FORMS`):

    python -m zernet.matching.train_template SCANS runs/template-real --registrations --out real_template.pt
"""

from __future__ import annotations

import argparse
import hashlib
import subprocess
import sys
from pathlib import Path

import numpy as np
import yaml

from zernet.io_utils import atomic_write_bytes

__all__ = [
    "FORMS",
    "REGISTRATION_FORMS",
    "rest_positions",
    "write_training_folder",
    "consensus_labels",
    "write_registration_folder",
    "template_config",
    "init_provenance",
    "main",
]

#: The forms every training body is also seen in (``zernet bodies --forms``).
FORMS = ("remeshed", "cloud", "cloud-noisy", "partial")
#: Forms of the test bodies in the run's test split (its own report; the matching benchmark is the measure).
TEST_FORMS = ("remeshed", "partial")
TOPOLOGY = "coarse-1229"
#: The model reads surfaces through a coarse copy of about this many vertices (its training resolution).
COARSE_VERTICES = 1500
#: --registrations: the forms each scan is also trained in (``data.forms`` rates, made by the run).
REGISTRATION_FORMS = {"remeshed": 0.5, "cloud": 1.0, "cloud-noisy": 1.0, "partial": 1.0}
#: Registration file suffixes read by --registrations.
REGISTRATION_SUFFIXES = (".ply", ".obj", ".off", ".stl")


def rest_positions(topology: str = TOPOLOGY, cache_dir: str = ".zernet-cache") -> np.ndarray:
    """(V, 3) the template vertices on the body model's default person in its rest pose (metres, y up): the
    positions a template model's classes stand for."""
    from zernet.data.bodies.generator import _Z_UP_TO_Y_UP, BodyGenerator

    generator = BodyGenerator(topology, "rest", 0, cache_dir)
    return generator.topology().place(generator.pose_model({}, {})) @ _Z_UP_TO_Y_UP.T


def write_training_folder(bodies: Path, out: Path, n_template: int) -> Path:
    """The training folder (module docstring, step 2) under ``out``: ``meshes/{train,test}`` links and
    ``labels/{train,test}`` template-vertex files."""
    for split in ("train", "test"):
        (out / "meshes" / split).mkdir(parents=True, exist_ok=True)
        (out / "labels" / split).mkdir(parents=True, exist_ok=True)
        for mesh in sorted((bodies / "segmentation" / "meshes" / split).glob("*.ply")):
            links = [(mesh, None, mesh.name)]
            for form in FORMS if split == "train" else TEST_FORMS:
                labels = bodies / "forms" / form / "correspondence" / split / f"{mesh.stem}.txt"
                links.append(
                    (bodies / "forms" / form / "meshes" / split / mesh.name, labels, f"{mesh.stem}_{form}.ply")
                )
            for source, labels, name in links:
                link = out / "meshes" / split / name
                if not link.exists():
                    link.symlink_to(source.resolve())
                label_path = out / "labels" / split / f"{Path(name).stem}.txt"
                if labels is None:  # the body as generated: vertex i is template vertex i
                    atomic_write_bytes(label_path, "".join(f"{i}\n" for i in range(n_template)).encode())
                elif not label_path.exists():
                    label_path.symlink_to(labels.resolve())
    return out


def consensus_labels(model, surfaces: list, cache_dir=None) -> dict:
    """The template vertex of every vertex of registered scans that share one triangulation (module docstring).

    Returns ``{"labels": (V,) int64 template vertex per registration vertex, "rotations": (S, 3, 3) the turn
    of each scan into the model's frame (as :func:`~zernet.matching.template.template_shape` found it),
    "spread": (S,) each scan's 95th-percentile distance (template units) from the consensus}``: a scan far
    from the others was read wrongly, in part or whole, and outvoted."""
    from scipy.spatial import cKDTree

    from zernet.matching.template import template_shape

    if len(surfaces) < 3:
        raise ValueError(f"a consensus needs at least 3 registered scans, got {len(surfaces)}")
    first = surfaces[0]
    for surface in surfaces[1:]:
        if surface.faces is None or first.faces is None or not np.array_equal(surface.faces, first.faces):
            raise ValueError(
                f"{surface.name}: registered scans must share one triangulation (the faces of {first.name}); "
                "scans in their own meshing have no correspondence to vote with"
            )
    read = [template_shape(model, surface, cache_dir=cache_dir) for surface in surfaces]
    positions = np.stack([shape.positions for shape in read])  # (S, V, 3)
    consensus = np.median(positions, axis=0)
    _, labels = cKDTree(model.template_positions).query(consensus)
    spread = np.percentile(np.linalg.norm(positions - consensus[None], axis=2), 95, axis=1)
    return {
        "labels": np.asarray(labels, dtype=np.int64),
        "rotations": np.stack([shape.rotation for shape in read]),
        "spread": spread,
    }


def write_registration_folder(model, surfaces: list, labels: np.ndarray, rotations: np.ndarray, out: Path) -> Path:
    """The training folder of registered scans under ``out`` (``meshes/train``, ``labels/train``): each scan
    as the template model reads it (scaled to the model's area, its coarse copy, turned into the model's frame
    by its rotation in ``rotations``), each coarse vertex labelled with ``labels`` of the registration vertex
    nearest it."""
    import warnings

    import trimesh
    from scipy.spatial import cKDTree

    from zernet.geometry import Surface, SurfaceWarning, coarsen_surface

    for kind in ("meshes", "labels"):
        (out / kind / "train").mkdir(parents=True, exist_ok=True)
    for surface, rotation in zip(surfaces, rotations):
        scaled = Surface(surface.vertices * np.sqrt(model.area / surface.area), surface.faces, name=surface.name)
        read = scaled
        if model.coarse_vertices and scaled.n_vertices > 1.5 * model.coarse_vertices:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", SurfaceWarning)  # the copy is the matcher's own, as in matching
                read = coarsen_surface(scaled, model.coarse_vertices).surface
        _, nearest = cKDTree(scaled.vertices).query(read.vertices)
        stem = Path(surface.name).stem
        mesh = trimesh.Trimesh(read.vertices @ np.asarray(rotation).T, read.faces, process=False)
        atomic_write_bytes(out / "meshes" / "train" / f"{stem}.ply", mesh.export(file_type="ply"))
        atomic_write_bytes(
            out / "labels" / "train" / f"{stem}.txt", "".join(f"{i}\n" for i in labels[nearest]).encode()
        )
    return out


def template_config(
    folder: Path,
    n_template: int,
    unit_scale: float,
    epochs: int,
    init_from: str | None,
    lr: float = 0.003,
    forms: dict | None = None,
) -> dict:
    """The run configuration: a per-vertex classifier over the template's vertices, at one fixed scale (so a
    one-sided scan keeps its size), with positions and the heat kernel signature as inputs, seen by the head.
    ``forms``: ``data.forms`` rates, the forms the run makes of its training shapes (None: the folder holds
    them already, as :func:`write_training_folder` writes them)."""
    config = {
        "data": {
            "kind": "segmentation",
            "meshes": str(folder / "meshes"),
            "labels": str(folder / "labels"),
            "num_classes": n_template,
            "label_base": 0,
            "label_kind": "vertex",
            "features": "xyz+hks",
            "val_count": 8,
        },
        "patch": {
            "scale": unit_scale,
            "scales": [
                {
                    "r0": 5.5,
                    "n_samples": 12000,
                    "n_max": 5,
                    "inner_radius": 1.375,
                    "subtract_center": True,
                    "ridge": 0.01,
                    "backend": "front",
                }
            ],
        },
        "model": {"name": "zernet", "widths": [64, 128, 256, 512], "norm": "layer", "input_skip": True},
        "train": {"epochs": epochs, "lr": lr, "lr_schedule": "cosine", "init_from": init_from},
        "eval": {"renders": 0, "refine_rings": [0]},
    }
    if forms:
        config["data"]["forms"] = dict(forms)
    return config


def init_provenance(init_from: str | None) -> dict | None:
    """What a template model was fine-tuned from: a template model file's name, sha256 and own provenance
    (so a chain of fine-tunes can be followed back to its first training), or the backbone's name."""
    if init_from is None:
        return None
    path = Path(init_from)
    if not path.is_file():
        return {"name": init_from}
    from zernet.inference.model_file import read_model_file

    payload = read_model_file(path)
    return {
        "file": path.name,
        "sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
        "provenance": payload.get("provenance"),
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "bodies",
        type=Path,
        help="generated bodies with their forms (written if missing), or with --registrations a folder of registered "
        "scans that share one triangulation",
    )
    parser.add_argument("run", type=Path, help="training run folder")
    parser.add_argument("--out", type=Path, required=True, help="the template model file to write")
    parser.add_argument(
        "--registrations",
        action="store_true",
        help="fine-tune a template model (--init-from, default the shipped one) on registered scans (module docstring)",
    )
    parser.add_argument("--count", type=int, default=500)
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument("--epochs", type=int, default=None, help="default 8, or 10 with --registrations")
    parser.add_argument(
        "--lr",
        type=float,
        default=None,
        help="peak learning rate (cosine schedule); default 3e-3, or 1e-3 with --registrations",
    )
    parser.add_argument(
        "--poses", choices=("varied", "wide"), default="varied", help="the generated bodies' poses (zernet bodies)"
    )
    parser.add_argument(
        "--init-from",
        default=None,
        help="default pretrained:bodies-xyz-hks, or the shipped template model with --registrations",
    )
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    from zernet.inference.model_file import load_checkpoint
    from zernet.matching.template import PRETRAINED_TEMPLATE_MODEL, save_template_model

    # The commit the model is trained from, taken before the hours of training a later commit may land in.
    commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    if args.registrations:
        init_from = str(PRETRAINED_TEMPLATE_MODEL) if args.init_from is None else args.init_from
        epochs, lr = args.epochs or 10, args.lr or 0.001
        config, positions, details = _registration_config(args.bodies, args.run, init_from, epochs, lr)
    else:
        init_from = args.init_from or "pretrained:bodies-xyz-hks"
        epochs, lr = args.epochs or 8, args.lr or 0.003
        config, positions, details = _generated_config(args, init_from, epochs, lr)
    args.run.mkdir(parents=True, exist_ok=True)
    config_path = args.run / "template.yaml"
    atomic_write_bytes(config_path, yaml.safe_dump(config, sort_keys=False).encode())
    command = [sys.executable, "-m", "zernet.cli", "train", str(config_path), "--run-dir", str(args.run / "run")]
    subprocess.run([*command, "--set", f"train.threads={args.threads}", "--no-progress"], check=True)
    provenance = {
        "what": "ZerNet template classifier (1,229 template vertices) for matching human bodies",
        "command": "python -m zernet.matching.train_template " + " ".join(argv or sys.argv[1:]),
        "commit": commit,
        "config": config,
        "training_area": TRAINING_AREA,
        "coarse_vertices": COARSE_VERTICES,
        "init_from": init_provenance(init_from),
        **details,
    }
    save_template_model(load_checkpoint(args.run / "run" / "best.pt"), positions, args.out, provenance)
    print(f"wrote {args.out}")
    return 0


#: The area the shipped backbone's patches were learnt at, and every template model reads surfaces at.
TRAINING_AREA = 15000.0


def _generated_config(args, init_from: str, epochs: int, lr: float) -> tuple[dict, np.ndarray, dict]:
    """Generated bodies (written if missing) in every form: (run config, template positions, provenance)."""
    import trimesh

    if not (args.bodies / "forms" / FORMS[-1]).is_dir():
        command = [sys.executable, "-m", "zernet.cli", "bodies", str(args.bodies), "--count", str(args.count)]
        command += ["--n-test", "10", "--seed", str(args.seed), "--topology", TOPOLOGY, "--poses", args.poses]
        subprocess.run([*command, "--forms", ",".join(FORMS), "--forms-split", "all"], check=True)
    positions = rest_positions()
    folder = write_training_folder(args.bodies, args.bodies / "template-training", len(positions))
    areas = [
        trimesh.load(p, process=False).area for p in sorted((args.bodies / "segmentation/meshes/train").glob("*.ply"))
    ]
    unit_scale = round(float(np.median(np.sqrt(TRAINING_AREA / np.asarray(areas)))), 1)
    return template_config(folder, len(positions), unit_scale, epochs, init_from, lr), positions, {"poses": args.poses}


def _registration_config(
    scans: Path, run: Path, init_from: str, epochs: int, lr: float
) -> tuple[dict, np.ndarray, dict]:
    """Registered scans labelled by consensus (module docstring): (run config, template positions, provenance)."""
    import json

    from zernet.geometry import SurfaceError, read_surface
    from zernet.matching.template import load_template_model

    if not scans.is_dir():
        raise SystemExit(f"{scans}: no such folder of registered scans")
    files = sorted(path for path in scans.iterdir() if path.suffix.lower() in REGISTRATION_SUFFIXES)
    if not files:
        raise SystemExit(f"{scans}: no registered scans ({', '.join(REGISTRATION_SUFFIXES)}) in this folder")
    try:  # what is wrong with a scan or the model file is the user's to fix: said by name, not as a traceback
        model = load_template_model(init_from)  # a fine-tune starts from, and is labelled by, a template model
        surfaces = [read_surface(path) for path in files]
        print(f"reading {len(surfaces)} registered scans with {init_from} for their consensus labels", flush=True)
        consensus = consensus_labels(model, surfaces, cache_dir=run / "cache")
    except (ValueError, SurfaceError) as error:
        raise SystemExit(f"train_template --registrations {scans}: {error}") from None
    spread = {path.name: round(float(value), 4) for path, value in zip(files, consensus["spread"])}
    run.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(run / "consensus.json", json.dumps({"spread_p95": spread}, indent=1).encode())
    outvoted = [name for name, value in spread.items() if value > OUTVOTED_SPREAD]
    print(
        f"consensus: {len(outvoted)} of {len(surfaces)} scans read partly wrong (95th percentile beyond "
        f"{OUTVOTED_SPREAD} template units of the consensus) and outvoted: {', '.join(outvoted) or 'none'}",
        flush=True,
    )
    folder = write_registration_folder(
        model, surfaces, consensus["labels"], consensus["rotations"], run / "template-training"
    )
    config = template_config(folder, len(model.template_positions), 1.0, epochs, init_from, lr, REGISTRATION_FORMS)
    # A few scans validate and one or more are scored by the run itself; the matching benchmark measures.
    config["data"].update(val_count=max(1, min(8, len(surfaces) // 6)), test_fraction=0.05)
    config["cache_dir"] = str(run / "cache")
    details = {"registrations": {"folder": scans.name, "scans": len(surfaces), "outvoted": outvoted}}
    return config, np.asarray(model.template_positions), details


#: A scan whose 95th-percentile distance from the consensus exceeds this (template units: metres on the
#: template's rest body) was read wrongly in part (a limb) or whole; reported, and outvoted by the median.
OUTVOTED_SPREAD = 0.1


if __name__ == "__main__":
    sys.exit(main())
