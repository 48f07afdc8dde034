"""Training steps of a nearly converged correspondence model, with denormal floats flushed to zero and without.

Late in a FAUST-sized correspondence run the model is confident: most of the 6,890 softmax probabilities of
a vertex are below float32's smallest normal number (~1.2e-38), so the gradient of the output layer is full
of denormals, and x86 CPUs compute on those through a slow path. ``zernet.training.flush_denormals`` (training runs
its epochs inside it) makes the CPU read and write them as zero.
This script loads the weights of a trained run (``--run``, e.g. the last checkpoint of a 14-epoch run of
``configs/bodies_correspondence.yaml``), and times ``train_one_epoch`` over its first ``--shapes`` training
shapes with the flag off and on, alternating over ``--rounds`` rounds, on one thread (the flag is per thread;
one thread keeps the comparison in one process). The weights are restored before every pass, so every pass
computes the same steps. Prints seconds per step (median over rounds) and their ratio.

    .venv/bin/python -m benchmarks.speed.bench_denormals --run runs/bench_faust_ln14/correspondence-zernet --shapes 4

Writes ``benchmarks/speed/results/bench_denormals.json`` (``--out``).
"""

from __future__ import annotations

import copy
from pathlib import Path

import torch

from benchmarks.harness import SPEED_RESULTS, add_out, arguments, result_file, write_json
from benchmarks.speed.step_timing import alternate, print_medians, seconds_per_step
from zernet.inference import load_checkpoint
from zernet.inference.predict import model_from_checkpoint
from zernet.training.build import build_dataset
from zernet.training.config import read_config


def main() -> None:
    parser = arguments(__doc__)
    parser.add_argument("--run", type=Path, required=True, help="a trained correspondence run folder")
    parser.add_argument("--checkpoint", default="last.pt")
    parser.add_argument("--shapes", type=int, default=4, help="training shapes per timed pass")
    parser.add_argument("--rounds", type=int, default=2)
    add_out(parser, SPEED_RESULTS / "bench_denormals")
    args = parser.parse_args()
    torch.set_num_threads(1)
    for name in ("config.yaml", args.checkpoint):
        if not (args.run / name).is_file():
            raise SystemExit(f"{args.run}: no {name} here; --run must be a finished training run folder")

    config = read_config(args.run / "config.yaml")
    dataset = build_dataset(config, progress=False, workers=1)
    shapes = list(dataset.splits["train"])[: args.shapes]
    checkpoint = load_checkpoint(args.run / args.checkpoint)
    epoch = checkpoint["state"]["epoch"]  # the steps use that epoch's learning rate
    model = model_from_checkpoint(checkpoint, torch.device("cpu"))
    weights = copy.deepcopy(model.state_dict())

    def timed(flush: bool) -> float:
        torch.set_flush_denormal(flush)
        model.load_state_dict(weights)
        optimizer = torch.optim.Adam(model.parameters(), lr=config.train.lr)
        return seconds_per_step(model, optimizer, dataset, shapes, epoch, config.train)

    if not torch.set_flush_denormal(True):
        raise SystemExit("this CPU has no flush-to-zero mode: nothing to compare")
    timed(True)  # warm-up: first products, allocator, operator cache
    times = alternate({"denormals kept": lambda: timed(False), "flushed to zero": lambda: timed(True)}, args.rounds)
    medians, ratio = print_medians(
        f"{len(shapes)} training shapes of {args.run} (weights after epoch {epoch}), 1 thread, {args.rounds} rounds",
        "denormals",
        times,
        faster="flushed to zero",
    )
    result = {
        "run": str(args.run),
        "epoch": epoch,
        "shapes": len(shapes),
        "threads": 1,
        "rounds": args.rounds,
        "seconds_per_step": times,
        "median_seconds_per_step": medians,
        "speedup": ratio,
    }
    write_json(result_file(args.out, ".json"), result)


if __name__ == "__main__":
    main()
