"""How much the correspondence refinement gives: the neighbours' agreement against the ring average it replaced.

For one trained correspondence run (its selected model), on its validation split, its test split and, if given,
the unseen people of ``benchmarks.experiments.few_people`` (``--unseen``): exact accuracy and the share within 1 % of the
geodesic diameter, unrefined and refined over 1, 2 and 3 rings by

* the ring average, ``A_shape · P · A_templateᵀ`` (what ``zernet.inference.refine`` did until 0.2; written out
  here as the baseline), and
* the neighbours' agreement, :func:`zernet.inference.refine.refine_correspondence` (what it does now).

and the median seconds each refinement takes per shape (on the run's device, ``--threads`` CPU threads). No
global step (``eval.refine_spectral``) is applied: the figures compare the local step alone. Writes
``benchmarks/experiments/results/refinement.{json,md}`` (``--out``).

    .venv/bin/python -m benchmarks.experiments.refinement --run runs/fp7/more-people-template-matched \\
        --unseen data/people-unseen/correspondence --threads 1
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.harness import (
    EXPERIMENT_RESULTS,
    add_device,
    add_out,
    add_threads,
    arguments,
    markdown_table,
    result_file,
    write_json,
    write_markdown,
)
from zernet.inference import load_checkpoint
from zernet.inference.predict import model_from_checkpoint, predict_record
from zernet.inference.refine import refine_correspondence, ring_tensor
from zernet.inference.runtime import resolve_device
from zernet.metrics import GeodesicErrors
from zernet.training import build_dataset, parse_config

RINGS = (1, 2, 3)


def ring_averaged(probabilities: torch.Tensor, faces: np.ndarray, rings: int) -> torch.Tensor:
    """The baseline: ``A · P · Aᵀ`` with ``A`` the ring average of the shared connectivity."""
    average = ring_tensor(faces, probabilities.shape[0], rings, probabilities.device, average=True)
    return (average @ (average @ probabilities).T.contiguous()).T


def agreement(probabilities: torch.Tensor, faces: np.ndarray, rings: int) -> torch.Tensor:
    """What zernet does: the neighbours' agreement, the shape and the template sharing ``faces``."""
    return refine_correspondence(probabilities, faces, faces, rings)


def split_datasets(checkpoint: dict, unseen: Path | None) -> list[tuple[str, object, str]]:
    """(label, data set, split) for the run's validation and test splits and the unseen people."""
    config = checkpoint["config"]
    own = build_dataset(parse_config(config), progress=False)
    splits = [("validation", own, "val"), ("test", own, "test")]
    if unseen is not None:
        count = len(sorted((unseen / "training" / "registrations").glob("tr_reg_*.ply")))
        data = {**config["data"], "root": str(unseen), "train_indices": [], "test_indices": f"0:{count}"}
        unseen_set = build_dataset(parse_config({**config, "data": {**data, "val_count": 0}}), progress=False)
        splits.insert(1, ("unseen people", unseen_set, "test"))
    return splits


def score_split(members, dataset, split: str, device: torch.device) -> dict:
    """Exact accuracy and share within 1 % of the diameter of every method on one split."""
    hits: dict[str, int] = {}
    within: dict[str, int] = {}
    seconds: dict[str, list[float]] = {}
    total = 0
    for i in dataset.splits[split]:
        record = dataset[i]
        _, probabilities = predict_record(members, record, device)
        probabilities = torch.from_numpy(probabilities).to(device)  # refined where the run computes
        faces, target = record.surface.faces, np.asarray(record.target)
        geodesics = GeodesicErrors(record.surface)
        predictions = {"unrefined": probabilities.argmax(dim=1).cpu().numpy()}
        for rings in RINGS:
            for name, refine in (
                (f"average, {rings} ring(s)", ring_averaged),
                (f"agreement, {rings} ring(s)", agreement),
            ):
                start = time.perf_counter()
                predictions[name] = refine(probabilities, faces, rings).argmax(dim=1).cpu().numpy()
                seconds.setdefault(name, []).append(time.perf_counter() - start)
        for name, pred in predictions.items():
            hits[name] = hits.get(name, 0) + int((pred == target).sum())
            within[name] = within.get(name, 0) + int((geodesics(pred, target) <= 0.01).sum())
        total += len(target)
        print(f"  {record.name}: unrefined {np.mean(predictions['unrefined'] == target):.4f}", flush=True)
    return {
        name: {
            "exact": hits[name] / total,
            "within_1pct": within[name] / total,
            "median_seconds_per_shape": statistics.median(seconds[name]) if name in seconds else 0.0,
        }
        for name in hits
    }


def markdown(result: dict) -> list[str]:
    names = list(next(iter(result["splits"].values())))
    labels = list(result["splits"])
    lines = [
        "# Correspondence refinement: the neighbours' agreement against the ring average",
        "",
        f"Run `{result['run']}` (its selected model); {result['seconds']:.0f} s.",
        "Exact accuracy / share within 1 % of the geodesic diameter, no global step.",
        "",
    ]
    rows = []
    for name in names:
        cells = [
            f"{100 * result['splits'][label][name]['exact']:.2f} / {100 * result['splits'][label][name]['within_1pct']:.2f} %"
            for label in labels
        ]
        timing = statistics.median(result["splits"][label][name]["median_seconds_per_shape"] for label in labels)
        rows.append([name, *cells, f"{timing:.2f}"])
    return lines + markdown_table(["refinement", *labels, "median seconds per shape"], rows)


def main() -> None:
    parser = arguments(__doc__)
    parser.add_argument("--run", type=Path, required=True, help="a correspondence run folder (its best.pt)")
    parser.add_argument("--unseen", type=Path, default=None, help="FAUST-layout folder of unseen people")
    add_threads(parser)
    add_device(parser)
    add_out(parser, EXPERIMENT_RESULTS / "refinement")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    checkpoint = load_checkpoint(args.run / "best.pt")
    if not checkpoint.get("correspondence"):
        parser.error(f"{args.run} is not a correspondence run")
    device = resolve_device(args.device or checkpoint["config"]["train"]["device"])
    members = [(model_from_checkpoint(checkpoint, device), checkpoint)]
    start = time.perf_counter()
    result = {"run": str(args.run), "splits": {}}
    for label, dataset, split in split_datasets(checkpoint, args.unseen):
        print(f"{label} ...", flush=True)
        result["splits"][label] = score_split(members, dataset, split, device)
    result["seconds"] = time.perf_counter() - start
    write_json(result_file(args.out, ".json"), result)
    lines = markdown(result)
    write_markdown(result_file(args.out, ".md"), lines)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
