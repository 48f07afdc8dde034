"""Scaling benchmark: preprocessing throughput against worker processes, DDP training speed against ranks.

1. Preprocessing: the built-in synthetic creatures go through :func:`zernet.data.preprocess.preprocess_shapes`
   (load, validate, normalise, geodesic polar coordinates, patch operators, cache write) into a fresh cache
   with 1, 2, ... worker processes; reported as shapes per minute. Workers start from a fork server that
   imports torch and zernet once; that start-up is measured once, apart.
2. Training: ``torchrun --standalone --nproc_per_node W -m zernet.cli train`` on the same (now cached)
   shapes with W = 1, 2, ... gloo ranks on the CPU. Each rank runs ``ceil(n_train / W)`` optimiser steps per
   epoch, so steps/s is per rank and shapes/s = steps/s × W is the throughput. The time is the run's own
   ``train_seconds`` (epochs only; no validation split, start-up and evaluation excluded).

Prints a table and writes ``benchmarks/speed/results/bench_scaling.json`` (``--out``)::

    .venv/bin/python -m benchmarks.speed.bench_scaling                # defaults: 8 shapes of 1000 vertices
    .venv/bin/python -m benchmarks.speed.bench_scaling --shapes 16 --vertices 1500 --workers 1 2 4 --ranks 1 2 4

On a machine shared with other jobs the numbers move with the load; the load average is recorded.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from functools import partial
from pathlib import Path

import yaml

from benchmarks.harness import REPO, SPEED_RESULTS, add_out, arguments, markdown_table, result_file, write_json
from zernet.data.preprocess import ShapeSource, preprocess_shapes
from zernet.data.synthetic import SYNTHETIC_AREA, load_creature
from zernet.inference import load_checkpoint
from zernet.operators import PatchConfig
from zernet.training import build_dataset, resolve_config


def creature_sources(n_shapes: int, n_vertices: int) -> list[ShapeSource]:
    return [
        ShapeSource(
            f"creature_{i:03d}",
            partial(load_creature, i, n_vertices, True, "segmentation"),
            key=f"bench-{i}-{n_vertices}",
        )
        for i in range(n_shapes)
    ]


def _noop() -> int:
    return os.getpid()


def warm_up_workers() -> float:
    """Start the worker machinery once (the fork server imports torch and zernet); returns its seconds.

    It is paid once per process, however many shapes follow, so it is reported apart from the throughput.
    """
    from concurrent.futures import ProcessPoolExecutor

    from zernet.data.pool import pool_context, worker_init

    started = time.perf_counter()
    with ProcessPoolExecutor(1, mp_context=pool_context(), initializer=worker_init) as pool:
        pool.submit(_noop).result()
    return time.perf_counter() - started


def bench_preprocess(sources, configs, workers: int) -> dict:
    with tempfile.TemporaryDirectory(prefix="zernet-bench-") as cache:
        started = time.perf_counter()
        failures = preprocess_shapes(sources, configs, cache, SYNTHETIC_AREA, workers=workers, progress=False)
        seconds = time.perf_counter() - started
    if failures:
        raise RuntimeError(f"preprocessing failed: {failures}")
    return {
        "workers": workers,
        "shapes": len(sources),
        "seconds": seconds,
        "shapes_per_minute": 60.0 * len(sources) / seconds,
    }


def bench_ddp(config: dict, n_train: int, ranks: int, folder: Path) -> dict:
    config_path = folder / f"ddp{ranks}.yaml"
    config_path.write_text(yaml.safe_dump(config))
    run_dir = folder / f"run{ranks}"
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")
    }
    env.update(OMP_NUM_THREADS="1", PYTHONPATH=str(REPO) + os.pathsep + env.get("PYTHONPATH", ""))
    command = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        "--nproc_per_node",
        str(ranks),
        "-m",
        "zernet.cli",
        "train",
        str(config_path),
        "--run-dir",
        str(run_dir),
        "--no-progress",
        "--workers",
        "0",
        "--overwrite",
    ]
    result = subprocess.run(command, env=env, capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"torchrun with {ranks} ranks failed:\n{result.stdout[-2000:]}\n{result.stderr[-2000:]}")
    state = load_checkpoint(run_dir / "last.pt")["state"]
    steps = state["epoch"] * -(-n_train // ranks)
    seconds = state["train_seconds"]
    return {
        "ranks": ranks,
        "epochs": state["epoch"],
        "steps_per_rank": steps,
        "seconds": seconds,
        "steps_per_second": steps / seconds,
        "shapes_per_second": steps * ranks / seconds,
    }


def main(argv=None) -> int:
    parser = arguments(__doc__)
    parser.add_argument("--shapes", type=int, default=8)
    parser.add_argument("--vertices", type=int, default=1000)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--ranks", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--epochs", type=int, default=4)
    add_out(parser, SPEED_RESULTS / "bench_scaling")
    args = parser.parse_args(argv)

    # The demo's patch density (about 79 samples per patch disk) at a size that keeps the benchmark short.
    patch = {"r0": 2.5, "n_samples": 4000, "patch_size": 50, "n_max": 5}
    configs = [PatchConfig(**patch)]
    sources = creature_sources(args.shapes, args.vertices)

    startup = warm_up_workers()
    print(f"worker start-up (once per process): {startup:.1f} s", flush=True)
    preprocess = []
    for workers in args.workers:
        row = bench_preprocess(sources, configs, workers)
        preprocess.append(row)
        print(f"preprocess workers={workers}: {row['shapes_per_minute']:.1f} shapes/min", flush=True)

    n_test = 1
    train_config = {
        "data": {
            "kind": "synthetic",
            "task": "segmentation",
            "n_shapes": args.shapes,
            "n_vertices": args.vertices,
            "test_fraction": n_test / args.shapes,
            "val_count": 0,
            "seed": 0,
        },
        "patch": {"scales": [patch]},
        "model": {"name": "zernet", "widths": [16, 32, 32], "angular_resolution": 4, "dropout": 0.1},
        "train": {"epochs": args.epochs, "seed": 0, "threads": 1, "lr": 5e-3, "patience": None},
        "eval": {"renders": 0, "plots": False},
    }
    training = []
    with tempfile.TemporaryDirectory(prefix="zernet-bench-ddp-") as folder:
        folder = Path(folder)
        train_config["cache_dir"] = str(folder / "cache")
        # Fill the cache once, here, so every torchrun measures training only.
        build_dataset(resolve_config(train_config), progress=False, workers=max(args.workers))
        for ranks in args.ranks:
            row = bench_ddp(train_config, args.shapes - n_test, ranks, folder)
            training.append(row)
            print(
                f"ddp ranks={ranks}: {row['steps_per_second']:.2f} steps/s per rank, "
                f"{row['shapes_per_second']:.2f} shapes/s",
                flush=True,
            )

    base_pre, base_train = preprocess[0], training[0]
    print()
    print(f"preprocessing: {args.shapes} creatures of {args.vertices} vertices, n_samples {patch['n_samples']}")
    print(f"(worker start-up, paid once per process and not included: {startup:.1f} s)")
    rows = [
        [
            row["workers"],
            f"{row['seconds']:.1f}",
            f"{row['shapes_per_minute']:.1f}",
            f"{row['shapes_per_minute'] / base_pre['shapes_per_minute']:.2f}x",
        ]
        for row in preprocess
    ]
    print("\n".join(markdown_table(["workers", "seconds", "shapes/min", "speed-up"], rows, align="rrrr")))
    print()
    print(f"DDP training (gloo, CPU, 1 thread per rank): {args.shapes - n_test} training shapes, {args.epochs} epochs")
    rows = [
        [
            row["ranks"],
            row["steps_per_rank"],
            f"{row['seconds']:.2f}",
            f"{row['steps_per_second']:.2f}",
            f"{row['shapes_per_second']:.2f}",
            f"{row['shapes_per_second'] / base_train['shapes_per_second']:.2f}x",
        ]
        for row in training
    ]
    header = ["ranks", "steps/rank", "seconds", "steps/s (per rank)", "shapes/s", "speed-up"]
    print("\n".join(markdown_table(header, rows, align="rrrrrr")))

    report = {
        "settings": {"shapes": args.shapes, "vertices": args.vertices, "patch": patch, "epochs": args.epochs},
        "worker_startup_seconds": startup,
        "preprocess": preprocess,
        "ddp_training": training,
    }
    write_json(result_file(args.out, ".json"), report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
