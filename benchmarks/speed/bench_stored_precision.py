"""Does the precision the operators are held in change a trained model's accuracy? One run, its shapes
predicted with the patch operators held in float32, float16 (the default) and bfloat16.

``PatchConfig.precision`` rounds the fitted operator's values; the layers compute in float32 whatever it is.
This benchmark takes a trained run (``--run``: its folder or checkpoint) and predicts ``--meshes`` with its
patch settings in each ``--precisions``, everything else as the run chose (its refinement included):

* ``--kind correspondence``: meshes in the template's vertex order (FAUST registrations): the truth of vertex
  ``i`` is ``i``; exact accuracy unrefined and refined.
* ``--kind segmentation``: ``--labels DIR`` holds ``<mesh stem>.txt`` per-vertex labels (``--label-base``,
  1 for FAUST's segmentation labels); accuracy unrefined and refined.

Accuracy is pooled over the vertices of all meshes. Prints a table and writes
``benchmarks/speed/results/bench_stored_precision.json`` (``--out``): figures only, never a shape or a label.

    .venv/bin/python -m benchmarks.speed.bench_stored_precision --run runs/faust --kind correspondence \\
        --meshes ~/data/MPI-FAUST/training/registrations/tr_reg_06?.ply --cache-dir /tmp/cache
"""

from __future__ import annotations

import copy
import tempfile
from pathlib import Path

import numpy as np
import torch

from benchmarks.harness import SPEED_RESULTS, add_out, add_threads, arguments, result_file, write_json
from zernet.data.segmentation import read_labels
from zernet.geometry import load_surface
from zernet.inference import predict
from zernet.inference.model_file import load_checkpoint

PRECISIONS = ("float32", "float16", "bfloat16")


def checkpoint_in(precision: str, checkpoint: dict, folder: Path) -> Path:
    """The checkpoint with every patch setting held in ``precision``, written to ``folder``."""
    changed = copy.copy(checkpoint)
    changed["preprocess"] = copy.deepcopy(checkpoint["preprocess"])
    for config in changed["preprocess"]["patch_configs"]:
        config["precision"] = precision
    path = folder / f"{precision}.pt"
    torch.save(changed, path)
    return path


def truth_of(mesh: Path, kind: str, labels: Path | None, base: int, n_vertices: int) -> np.ndarray:
    if kind == "correspondence":
        return np.arange(n_vertices)
    values = read_labels(labels / f"{mesh.stem}.txt").astype(np.int64) - base
    if len(values) != n_vertices:
        raise SystemExit(f"{labels / (mesh.stem + '.txt')}: {len(values)} labels for {n_vertices} vertices")
    return values


def main() -> None:
    parser = arguments(__doc__)
    parser.add_argument("--run", type=Path, required=True, help="a trained run folder or checkpoint file")
    parser.add_argument("--kind", choices=("correspondence", "segmentation"), required=True)
    parser.add_argument("--meshes", type=Path, nargs="+", required=True)
    parser.add_argument("--labels", type=Path, default=None, help="segmentation: folder of <stem>.txt labels")
    parser.add_argument("--label-base", type=int, default=1)
    parser.add_argument("--precisions", nargs="+", default=list(PRECISIONS), choices=PRECISIONS)
    parser.add_argument("--cache-dir", type=Path, required=True, help="operator cache (outside the repo)")
    add_threads(parser, default=2)
    add_out(parser, SPEED_RESULTS / "bench_stored_precision")
    args = parser.parse_args()
    if args.kind == "segmentation" and args.labels is None:
        raise SystemExit("--kind segmentation needs --labels DIR")
    torch.set_num_threads(args.threads)

    run_file = args.run / "best.pt" if args.run.is_dir() else args.run
    checkpoint = load_checkpoint(run_file)
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for precision in args.precisions:
            model_file = checkpoint_in(precision, checkpoint, Path(folder))
            right = {"unrefined": 0, "refined": 0}
            total = 0
            for mesh in args.meshes:
                surface = load_surface(mesh)
                truth = truth_of(mesh, args.kind, args.labels, args.label_base, surface.n_vertices)
                off = {"refine_rings": 0, **({"refine_spectral": 0} if args.kind == "correspondence" else {})}
                unrefined = predict(model_file, surface, cache_dir=args.cache_dir, **off)
                refined = predict(model_file, surface, cache_dir=args.cache_dir)
                right["unrefined"] += int((unrefined == truth).sum())
                right["refined"] += int((refined == truth).sum())
                total += len(truth)
            row = {"precision": precision, **{name: count / total for name, count in right.items()}}
            rows.append(row)
            print(
                f"{precision:<9} unrefined {100 * row['unrefined']:.2f} %  refined {100 * row['refined']:.2f} %",
                flush=True,
            )
    reference = rows[0]
    for row in rows:
        row["points_from_first"] = {name: 100 * (row[name] - reference[name]) for name in ("unrefined", "refined")}
    write_json(
        result_file(args.out, ".json"),
        {
            "kind": args.kind,
            "run": run_file.parent.name if run_file.name == "best.pt" else run_file.name,
            "meshes": [mesh.name for mesh in args.meshes],
            "vertices": total,
            "rows": rows,
        },
    )


if __name__ == "__main__":
    main()
