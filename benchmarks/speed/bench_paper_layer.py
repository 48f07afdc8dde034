"""The paper's own layer against zernet's, on the weights of one trained run: the same scores, and the cost.

The paper's formulation (``model.name: paper-zernet``, :class:`zernet.nn.models.PaperZerNet`) re-fits every
patch by least squares in every layer and step and turns ``s`` explicit kernel copies; zernet's
:class:`~zernet.nn.models.ZerNet` applies the same fit as a sparse operator computed once per surface and
rotates the kernel in its harmonic form. With ``pooling: max`` both compute the same map (to rounding; the
tests check it to 1e-9 in float64), and their state dicts are interchangeable. So a run of the zernet model
on the paper's patches (``patch.scales.*.patch_size: 50``, the paper's 50 nearest samples) trains the paper's
formulation at zernet's speed, and this script shows both halves of that claim on the run's own weights:

1. **scores**: the run's selected model (``best.pt``), loaded into both networks, scored on the test split
   (exact accuracy and the share within 1 % of the geodesic diameter, refined over the rings the run chose),
   and the largest difference of their predicted probabilities on the first test shape;
2. **cost**: ``train_one_epoch`` over ``--shapes`` training shapes with each network, alternating over
   ``--rounds`` rounds (the weights restored before every pass, so both compute the same steps): seconds per
   step, their ratio, and the run's mean epoch time scaled by it (what the run would have taken with the
   paper's layer).

    .venv/bin/python -m benchmarks.speed.bench_paper_layer --run runs/faust340_paper_patches --shapes 4 --rounds 2

Writes ``benchmarks/speed/results/bench_paper_layer.json`` (``--out``).
"""

from __future__ import annotations

import argparse
import copy
import statistics
from pathlib import Path

import torch

from benchmarks.harness import SPEED_RESULTS, add_out, add_threads, arguments, result_file, write_json
from benchmarks.speed.step_timing import alternate, print_medians, seconds_per_step
from zernet.inference import load_checkpoint
from zernet.inference.predict import model_from_checkpoint, predict_record
from zernet.training.build import build_dataset
from zernet.training.config import read_config
from zernet.training.evaluation import evaluate_members

#: The two networks, the paper's first (the timing table's ratio is the paper's step over zernet's).
LAYERS = {"paper (per-call fit)": "paper-zernet", "zernet (operator)": "zernet"}


def parse_args(argv=None) -> argparse.Namespace:
    parser = arguments(__doc__)
    parser.add_argument(
        "--run",
        type=Path,
        required=True,
        help="a finished run folder of the zernet (or paper-zernet) model, pooling max",
    )
    parser.add_argument("--shapes", type=int, default=4, help="training shapes per timed pass")
    parser.add_argument("--rounds", type=int, default=2)
    add_threads(parser, default=2)
    parser.add_argument("--no-scores", action="store_true", help="only time the steps")
    add_out(parser, SPEED_RESULTS / "bench_paper_layer")
    return parser.parse_args(argv)


def with_layer(checkpoint: dict, name: str) -> dict:
    """The checkpoint with its model built as ``name`` (``zernet`` or ``paper-zernet``): same weights."""
    return dict(checkpoint, model_spec=dict(checkpoint["model_spec"], name=name))


def scores(checkpoint: dict, dataset, device: torch.device) -> dict:
    """Test scores of the checkpoint's weights in both networks, and the largest difference of their
    probabilities on the first test shape."""
    test = list(dataset.splits["test"])
    rings = int(checkpoint.get("refine_rings", 0))
    result = {"refine_rings": rings, "test_shapes": len(test)}
    probabilities = []
    for label, name in LAYERS.items():
        model = model_from_checkpoint(with_layer(checkpoint, name), device).eval()
        with torch.no_grad():
            metrics, _ = evaluate_members(
                [(model, checkpoint)], dataset, test, device, progress=True, keep=0, refine_rings=rings
            )
            probabilities.append(predict_record([(model, checkpoint)], dataset[test[0]], device)[1])
        unrefined = metrics.get("unrefined_summary") or metrics["summary"]
        result[label] = {
            "accuracy": metrics["summary"]["accuracy"],
            "unrefined_accuracy": unrefined["accuracy"],
            "within_0.01": metrics["summary"].get("within_0.01"),
        }  # correspondence only
    result["max_probability_difference"] = float(abs(probabilities[0] - probabilities[1]).max())
    return result


def main(argv=None) -> None:
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    for name in ("config.yaml", "best.pt"):
        if not (args.run / name).is_file():
            raise SystemExit(f"{args.run}: no {name} here; --run must be a finished training run folder")
    config = read_config(args.run / "config.yaml")
    if config.model.name not in LAYERS.values() or config.model.options.get("pooling", "max") != "max":
        raise SystemExit(
            f"{args.run}: a {config.model.name} model with pooling "
            f"{config.model.options.get('pooling')!r}; the paper's layer is zernet's with pooling max"
        )
    dataset = build_dataset(config, progress=False, workers=1)
    checkpoint = load_checkpoint(args.run / "best.pt")
    device = torch.device("cpu")
    result = {
        "run": str(args.run),
        "threads": args.threads,
        "patch_size": [scale.get("patch_size") for scale in config.patch.scales],
    }
    if not args.no_scores:
        result["scores"] = scores(checkpoint, dataset, device)
        for label in LAYERS:
            s = result["scores"][label]
            within = "" if s["within_0.01"] is None else f", within 1 % {s['within_0.01']:.4f}"
            print(f"{label:22} test accuracy {s['accuracy']:.4f} (unrefined {s['unrefined_accuracy']:.4f}){within}")
        print(
            f"largest difference of a probability on {dataset.names[dataset.splits['test'][0]]}: "
            f"{result['scores']['max_probability_difference']:.2e}"
        )

    shapes = list(dataset.splits["train"])[: args.shapes]
    epoch = checkpoint["state"]["epoch"]
    models = {label: model_from_checkpoint(with_layer(checkpoint, name), device) for label, name in LAYERS.items()}
    weights = copy.deepcopy(checkpoint["model"])

    def timed(label: str) -> float:
        model = models[label]
        model.load_state_dict(weights)
        optimizer = torch.optim.Adam(model.parameters(), lr=config.train.lr)
        return seconds_per_step(model, optimizer, dataset, shapes, epoch, config.train)

    for label in LAYERS:  # warm-up: operator files, allocator, the paper's patch tensors
        timed(label)
    times = alternate({label: (lambda label=label: timed(label)) for label in LAYERS}, args.rounds)
    medians, ratio = print_medians(
        f"{len(shapes)} training shapes of {args.run}, {args.threads} threads, {args.rounds} rounds",
        "layer",
        times,
        faster="zernet (operator)",
    )
    epoch_seconds = [h["seconds"] for h in checkpoint["state"]["history"]]
    result.update(
        {
            "shapes": len(shapes),
            "rounds": args.rounds,
            "seconds_per_step": times,
            "median_seconds_per_step": medians,
            "paper_step_over_zernet_step": ratio,
        }
    )
    if epoch_seconds:
        mean = statistics.mean(epoch_seconds)
        result["run_epoch_seconds"] = epoch_seconds
        result["paper_layer_epoch_seconds_estimate"] = mean * ratio
        print(f"the run's epochs: {mean:.0f} s on average; with the paper's layer about {mean * ratio:.0f} s")
    write_json(result_file(args.out, ".json"), result)


if __name__ == "__main__":
    main()
