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

    .venv/bin/python benchmarks/bench_denormals.py --run runs/bench_faust_ln14/correspondence-zernet --shapes 4

Writes ``benchmarks/results/bench_denormals.json``.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
from pathlib import Path

import torch

from zernet.io_utils import atomic_write_bytes
from zernet.training import load_checkpoint
from zernet.training.build import build_dataset
from zernet.training.config import read_config
from zernet.training.predict import model_from_checkpoint

sys.path.insert(0, str(Path(__file__).resolve().parent))
from step_timing import alternate, print_medians, seconds_per_step  # noqa: E402  (shared timing loop)

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results" / "bench_denormals.json"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--run", type=Path, required=True, help="a trained correspondence run folder")
    parser.add_argument("--checkpoint", default="last.pt")
    parser.add_argument("--shapes", type=int, default=4, help="training shapes per timed pass")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--output", type=Path, default=RESULTS)
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
    args.output.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(args.output, json.dumps(result, indent=2).encode())


if __name__ == "__main__":
    main()
