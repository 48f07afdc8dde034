"""Training a template model (:mod:`zernet.matching.template`) on generated bodies in every form.

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

__all__ = ["FORMS", "rest_positions", "write_training_folder", "template_config", "init_provenance", "main"]

#: The forms every training body is also seen in (``zernet bodies --forms``).
FORMS = ("remeshed", "cloud", "cloud-noisy", "partial")
#: Forms of the test bodies in the run's test split (its own report; the matching benchmark is the measure).
TEST_FORMS = ("remeshed", "partial")
TOPOLOGY = "coarse-1229"
#: The model reads surfaces through a coarse copy of about this many vertices (its training resolution).
COARSE_VERTICES = 1500


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


def template_config(
    folder: Path, n_template: int, unit_scale: float, epochs: int, init_from: str | None, lr: float = 0.003
) -> dict:
    """The run configuration: a per-vertex classifier over the template's vertices, at one fixed scale (so a
    one-sided scan keeps its size), with positions and the heat kernel signature as inputs, seen by the head."""
    return {
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
    parser.add_argument("bodies", type=Path, help="generated bodies with their forms (written if missing)")
    parser.add_argument("run", type=Path, help="training run folder")
    parser.add_argument("--out", type=Path, required=True, help="the template model file to write")
    parser.add_argument("--count", type=int, default=500)
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument("--epochs", type=int, default=8)
    parser.add_argument("--lr", type=float, default=0.003, help="peak learning rate (cosine schedule)")
    parser.add_argument(
        "--poses", choices=("varied", "wide"), default="varied", help="the generated bodies' poses (zernet bodies)"
    )
    parser.add_argument("--init-from", default="pretrained:bodies-xyz-hks")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    from zernet.inference.model_file import load_checkpoint
    from zernet.matching.template import save_template_model

    # The commit the model is trained from, taken before the hours of training a later commit may land in.
    commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    if not (args.bodies / "forms" / FORMS[-1]).is_dir():
        command = [sys.executable, "-m", "zernet.cli", "bodies", str(args.bodies), "--count", str(args.count)]
        command += ["--n-test", "10", "--seed", str(args.seed), "--topology", TOPOLOGY, "--poses", args.poses]
        subprocess.run([*command, "--forms", ",".join(FORMS), "--forms-split", "all"], check=True)
    positions = rest_positions()
    folder = write_training_folder(args.bodies, args.bodies / "template-training", len(positions))
    import trimesh

    areas = [
        trimesh.load(p, process=False).area for p in sorted((args.bodies / "segmentation/meshes/train").glob("*.ply"))
    ]
    training_area = 15000.0  # the area the shipped backbone's patches were learnt at
    unit_scale = round(float(np.median(np.sqrt(training_area / np.asarray(areas)))), 1)
    config = template_config(folder, len(positions), unit_scale, args.epochs, args.init_from, args.lr)
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
        "training_area": training_area,
        "coarse_vertices": COARSE_VERTICES,
        "poses": args.poses,
        "init_from": init_provenance(args.init_from),
    }
    save_template_model(load_checkpoint(args.run / "run" / "best.pt"), positions, args.out, provenance)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
