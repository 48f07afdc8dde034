"""Training steps on a streamed FAUST-sized data set: with and without reading the next step's shape ahead,
and with and without its operator matrices prepared there in the order the convolutions read.

A data set over ``zernet.data.preprocess.IN_MEMORY_VERTEX_LIMIT`` vertices (80 FAUST-sized bodies) keeps
nothing in memory: every step reads its shape back from the cache (shape file, 150 MB patch operator with
its checksum, features) and builds the torch matrices. ``zernet.training.epoch.train_one_epoch`` does that
for the next step on a background thread (:func:`zernet.threads.prefetched`) while the current one computes,
including the matrices in the frequency-grouped row order the harmonic convolutions ask for
(:func:`zernet.inference.batch.model_basis_orders`). This script times :func:`train_one_epoch` over the first
``--shapes`` training shapes of the generated bodies (``zernet bodies DIR --count 100 --n-test 20``, the
recipe of ``configs/bodies_correspondence.yaml``) three ways: as shipped; with the natural-order matrices
prepared ahead and the reordered ones built inside the first convolution's forward (training before
2026-12-03); and with the shapes read in turn. The variants alternate over ``--rounds`` rounds; the script
prints seconds per step (median over rounds) and the ratios. The results are the same every way (same
batches, same order); only the wall time differs.

    .venv/bin/python -m benchmarks.speed.bench_prefetch --data data/bodies-faust-100 --shapes 12 --rounds 2

Writes ``benchmarks/speed/results/bench_prefetch.json`` (``--out``).
"""

from __future__ import annotations

import torch

import zernet.training.epoch as epoch_module
from benchmarks.harness import (
    CACHE,
    REPO,
    SPEED_RESULTS,
    add_data,
    add_out,
    add_threads,
    arguments,
    result_file,
    write_json,
)
from benchmarks.speed.step_timing import alternate, print_medians, seconds_per_step
from zernet.inference import build_model_from_spec, model_spec
from zernet.training.build import build_dataset
from zernet.training.config import load_config, parse_config


def sequential(function, items):
    """What training did before the prefetch: each step's shapes read when the step starts."""
    return (function(item) for item in items)


def main() -> None:
    parser = arguments(__doc__)
    add_data(parser, REPO / "data" / "bodies-faust-100", "folder written by `zernet bodies` (FAUST-sized, 100 bodies)")
    parser.add_argument("--shapes", type=int, default=12, help="training shapes per timed pass")
    parser.add_argument("--rounds", type=int, default=2)
    add_threads(parser, default=2)
    add_out(parser, SPEED_RESULTS / "bench_prefetch")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    config = load_config(REPO / "configs" / "bodies_correspondence.yaml")
    config["data"].update(
        {
            "root": str(args.data / "correspondence"),
            "train_indices": list(range(80)),
            "test_indices": list(range(80, 100)),
        }
    )
    config["train"].update({"threads": args.threads, "device": "cpu"})
    config["cache_dir"] = str(CACHE)
    config = parse_config(config)
    dataset = build_dataset(config, progress=False, workers=1)
    if dataset.in_memory:
        raise SystemExit(f"{args.data}: the data set fits in memory, nothing is streamed (use 100 FAUST-sized bodies)")
    shapes = list(dataset.splits["train"])[: args.shapes]
    spec = model_spec(config.model, dataset.in_channels, dataset.num_classes, dataset.patch_configs)
    model = build_model_from_spec(spec)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.train.lr)
    shipped_reader, shipped_orders = epoch_module.prefetched, epoch_module.model_basis_orders

    def timed(reader, orders) -> float:
        epoch_module.prefetched, epoch_module.model_basis_orders = reader, orders
        try:
            return seconds_per_step(model, optimizer, dataset, shapes, 1, config.train)
        finally:
            epoch_module.prefetched, epoch_module.model_basis_orders = shipped_reader, shipped_orders

    def natural_order(model):
        return ()  # the batch prepares no reordered matrices: the first forward builds them

    timed(shipped_reader, shipped_orders)  # warm-up: first products, allocator
    times = alternate(
        {
            "sequential": lambda: timed(sequential, natural_order),
            "prefetched, reordered in forward": lambda: timed(shipped_reader, natural_order),
            "prefetched": lambda: timed(shipped_reader, shipped_orders),
        },
        args.rounds,
    )
    medians, ratio = print_medians(
        f"{len(shapes)} FAUST-sized training shapes (streamed), {args.threads} threads, {args.rounds} rounds",
        "reading",
        times,
        faster="prefetched",
    )
    prepared = medians["prefetched, reordered in forward"] / medians["prefetched"]
    print(f"steps prefetched: {prepared:.2f}x as fast as with the reordering inside the forward pass")
    result = {
        "shapes": len(shapes),
        "threads": args.threads,
        "rounds": args.rounds,
        "seconds_per_step": times,
        "median_seconds_per_step": medians,
        "speedup": ratio,
        "speedup_prepared_orders": prepared,
    }
    write_json(result_file(args.out, ".json"), result)


if __name__ == "__main__":
    main()
