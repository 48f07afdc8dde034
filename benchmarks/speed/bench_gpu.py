"""Where a training step's time goes, for each residency level (issue 34): on the CPU always, on CUDA when
present; and the CPU epoch before and after the changes of issue 34, side by side.

The data set is read back from its cache on every access (``IN_MEMORY_VERTEX_LIMIT`` set to 0), as the 80
FAUST-size shapes of the recipe are, however few shapes are timed: ``stream`` then reads every step's shape.

For the shipped correspondence recipe (``configs/bodies_correspondence.yaml``: single-scale ZerNet, widths
64-128-256-512, a 6,890-way output on FAUST-size bodies) on generated bodies written as files
(``zernet bodies DIR --topology faust``, ``--data DIR``) or generated in the run (``--topology coarse-615``
keeps a CPU run short):

1. **per step**, each phase timed alone (the device synchronised after each): *load* (the step's record
   from the :class:`~zernet.training.residency.ShapeStore`: nothing when held on the device, a copy to the
   device when held on the host, a read of the cache when streamed), *copy* (the batch: operators prepared
   where they are not yet, features, targets and operators moved to the device), *forward*, *backward*,
   *optimiser*. ``busy`` is the share of forward + backward + optimiser in the step;
2. **the epoch** as training runs it (:func:`~zernet.training.epoch.train_one_epoch` with its read-ahead,
   then :func:`~zernet.training.epoch.validate`), and the time to read and prepare the held shapes first;
3. with ``--before DIR`` (a checkout of the code before issue 34, e.g. ``git worktree add DIR a0d7bb3``):
   ``zernet train`` of the same configuration for ``--ab-epochs`` epochs by each checkout, alternating over
   ``--ab-rounds`` rounds, each with a cache of its own format; the epoch seconds come from the runs'
   checkpoints.

    .venv/bin/python -m benchmarks.speed.bench_gpu --data /tmp/bodies --train 8 --val 2 \\
        [--levels stream host device] [--before /tmp/zernet-before] [--device cpu|cuda]
    .venv/bin/python -m benchmarks.speed.bench_gpu --topology coarse-615 --train 8 --val 2   # generated in the run

Writes ``benchmarks/speed/results/bench_gpu.json`` and ``.md`` (``--out`` to change), with the device's name.
"""

from __future__ import annotations

import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
import yaml

import zernet.data.preprocess as preprocess
from benchmarks.harness import (
    CACHE,
    REPO,
    SPEED_RESULTS,
    add_data,
    add_device,
    add_out,
    add_threads,
    arguments,
    commit,
    markdown_table,
    result_file,
    write_json,
    write_markdown,
)
from zernet.distributed import DistributedContext
from zernet.inference import build_model_from_spec, model_spec
from zernet.inference.batch import Batch, model_basis_orders, model_directional_order
from zernet.training.build import build_dataset
from zernet.training.config import load_config, parse_config
from zernet.training.epoch import Objective, train_one_epoch, validate
from zernet.training.losses import compute_loss
from zernet.training.residency import ShapeStore

CORRESPONDENCE = Objective("classification", "cross_entropy", None, None)
PHASES = ("load", "copy", "forward", "backward", "optimiser")


def device_name(device: torch.device) -> str:
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return f"{line.split(':', 1)[1].strip()} ({torch.get_num_threads()} threads)"
    except OSError:
        pass
    return f"{platform.processor() or 'cpu'} ({torch.get_num_threads()} threads)"


def run_config(
    data: Path | None, topology: str, n_train: int, n_val: int, n_test: int, cache_dir: Path, device: str, threads: int
) -> dict:
    """The shipped correspondence recipe on ``n_train + n_val`` training and ``n_test`` test bodies: read from
    the files of ``data`` (FAUST layout, 6,890 vertices), or generated in the run (``topology``)."""
    config = load_config(REPO / "configs" / "bodies_correspondence.yaml")
    if data is not None:
        config["data"].update(
            {
                "root": str(data / "correspondence"),
                "train_indices": f"0:{n_train + n_val}",
                "test_indices": f"{n_train + n_val}:{n_train + n_val + n_test}",
                "val_count": n_val,
            }
        )
    else:
        config["data"] = {
            "kind": "bodies",
            "task": "correspondence",
            "topology": topology,
            "seed": 0,
            "count": n_train + n_val + n_test,
            "n_test": n_test,
            "val_count": n_val,
            "features": "xyz",
        }
    config["train"].update({"device": device, "threads": threads, "epochs": 1})
    config["eval"].update({"renders": 0, "plots": False, "refine_rings": [0, 1]})
    config["cache_dir"] = str(cache_dir)
    return config


def synchronise(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def phase_times(model, optimizer, store: ShapeStore, indices, device) -> dict[str, list[float]]:
    """Seconds of each phase (:data:`PHASES`) of one step per shape, every phase timed alone."""
    times = {phase: [] for phase in PHASES}
    directional, orders = model_directional_order(model), model_basis_orders(model)
    model.train()
    for i in indices:
        marks = [time.perf_counter()]
        record = store[i]
        synchronise(device)
        marks.append(time.perf_counter())
        batch = Batch([record], device, None, None, directional, orders)
        synchronise(device)
        marks.append(time.perf_counter())
        optimizer.zero_grad(set_to_none=True)
        loss = compute_loss("cross_entropy", model(batch.features, batch.geometry).float(), batch.target, None)
        synchronise(device)
        marks.append(time.perf_counter())
        loss.backward()
        synchronise(device)
        marks.append(time.perf_counter())
        optimizer.step()
        synchronise(device)
        marks.append(time.perf_counter())
        for phase, start, stop in zip(PHASES, marks, marks[1:]):
            times[phase].append(stop - start)
    return times


def bench_level(level: str, config, dataset, spec, device, rounds: int) -> dict:
    """One residency level: its set-up, the per-step phases and the epoch as training runs it."""
    torch.manual_seed(0)
    model = build_model_from_spec(spec).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.train.lr)
    train, val = list(dataset.splits["train"]), list(dataset.splits["val"])
    started = time.perf_counter()
    store = ShapeStore(dataset, train + val, level, device, model_directional_order(model), model_basis_orders(model))
    setup = time.perf_counter() - started
    phase_times(model, optimizer, store, train[:1], device)  # warm-up: allocator, first products
    phases = {phase: [] for phase in PHASES}
    for _ in range(rounds):
        for phase, values in phase_times(model, optimizer, store, train, device).items():
            phases[phase] += values
    means = {phase: statistics.mean(values) for phase, values in phases.items()}
    step = sum(means.values())
    epochs = []
    for epoch in range(1, rounds + 1):
        synchronise(device)
        started = time.perf_counter()
        train_one_epoch(
            model,
            model,
            optimizer,
            store,
            train,
            epoch,
            config.train,
            CORRESPONDENCE,
            DistributedContext(device=device),
            progress=False,
        )
        validate(model, store, val, device, CORRESPONDENCE)
        synchronise(device)
        epochs.append(time.perf_counter() - started)
    return {
        "level": store.level,
        "reason": store.reason,
        "held_gb": store.held_bytes / 1e9,
        "setup_s": setup,
        "phase_ms": {phase: 1e3 * value for phase, value in means.items()},
        "step_ms": 1e3 * step,
        "busy": (means["forward"] + means["backward"] + means["optimiser"]) / step,
        "epoch_s": epochs,
        "epoch_median_s": statistics.median(epochs),
    }


def epoch_seconds_of_run(
    checkout: Path, config: dict, run_dir: Path, epochs: int, threads: int
) -> tuple[list[float], float]:
    """``zernet train`` by the code in ``checkout`` (its data set streamed, as a FAUST-size one is): the
    seconds of each epoch (from its last.pt) and of the whole command (start-up, holding the shapes, the
    final evaluation included)."""
    with tempfile.NamedTemporaryFile("w", suffix=".yaml", delete=False) as handle:
        yaml.safe_dump(config, handle)
    train_arguments = [
        "train",
        handle.name,
        "--run-dir",
        str(run_dir),
        "--overwrite",
        "--no-progress",
        "--set",
        f"train.epochs={epochs}",
        f"train.threads={threads}",
    ]
    code = (
        "import sys, zernet.data.preprocess as p; p.IN_MEMORY_VERTEX_LIMIT = 0; from zernet.cli import main; "
        f"sys.exit(main({train_arguments!r}))"
    )
    command = [sys.executable, "-c", code]
    started = time.perf_counter()
    subprocess.run(command, cwd=checkout, check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - started
    state = torch.load(run_dir / "last.pt", map_location="cpu", weights_only=True)["state"]
    return [float(entry["seconds"]) for entry in state["history"]], wall


def before_after(before: Path, after: Path, config: dict, work: Path, epochs: int, rounds: int, threads: int) -> dict:
    """The CPU epoch of the same configuration by the code before and after issue 34, alternating."""
    sides = {"before": before, "after": after}
    seconds = {side: [] for side in sides}
    walls = {side: [] for side in sides}
    for side, checkout in sides.items():  # fill each side's cache (its own format) before timing
        side_config = dict(config, cache_dir=str(work / f"cache-{side}"))
        epoch_seconds_of_run(checkout, side_config, work / f"warm-{side}", 1, threads)
    for _ in range(rounds):
        for side, checkout in sides.items():
            side_config = dict(config, cache_dir=str(work / f"cache-{side}"))
            epochs_s, wall = epoch_seconds_of_run(checkout, side_config, work / f"run-{side}", epochs, threads)
            seconds[side] += epochs_s
            walls[side].append(wall)
    medians = {side: statistics.median(values) for side, values in seconds.items()}

    return {
        "epoch_s": seconds,
        "median_epoch_s": medians,
        "after_over_before": medians["after"] / medians["before"],
        "run_wall_s": walls,
        "median_run_wall_s": {side: statistics.median(v) for side, v in walls.items()},
        "before_commit": commit(before),
        "after_commit": commit(after),
    }


def markdown(result: dict) -> list[str]:
    header = ["level", "held GB", "set-up s", *(f"{p} ms" for p in PHASES), "step ms", "busy", "epoch s"]
    rows = [
        [
            entry["level"],
            f"{entry['held_gb']:.2f}",
            f"{entry['setup_s']:.1f}",
            *(f"{entry['phase_ms'][p]:.0f}" for p in PHASES),
            f"{entry['step_ms']:.0f}",
            f"{entry['busy']:.0%}",
            f"{entry['epoch_median_s']:.1f}",
        ]
        for entry in result["levels"]
    ]
    lines = [
        f"# bench_gpu: {result['device_name']}",
        "",
        f"{result['shapes']['train']} training + {result['shapes']['val']} validation shapes of "
        f"{result['vertices']} vertices ({result['data']}), torch {result['torch']}, {result['threads']} CPU "
        "threads.",
        "",
        *markdown_table(header, rows),
    ]
    ab = result.get("before_after")
    if ab:
        lines += [
            "",
            f"CPU epoch, same configuration, `zernet train` alternating over rounds (before = "
            f"{ab['before_commit']}, after = {ab.get('after_commit')}): before {ab['median_epoch_s']['before']:.1f} s, after "
            f"{ab['median_epoch_s']['after']:.1f} s, after/before = {ab['after_over_before']:.2f} "
            f"(epochs: before {[round(s, 1) for s in ab['epoch_s']['before']]}, after "
            f"{[round(s, 1) for s in ab['epoch_s']['after']]}); whole `zernet train` command (start-up, "
            f"holding the shapes, final evaluation): before {ab['median_run_wall_s']['before']:.1f} s, "
            f"after {ab['median_run_wall_s']['after']:.1f} s.",
        ]
    return lines


def main() -> None:
    parser = arguments(__doc__)
    add_data(
        parser,
        None,
        "folder written by `zernet bodies` (FAUST-size); without it, bodies of --topology are generated in the run",
    )
    parser.add_argument("--topology", default="coarse-615", help="of the generated bodies without --data")
    parser.add_argument("--train", type=int, default=8)
    parser.add_argument("--val", type=int, default=2)
    parser.add_argument("--levels", nargs="*", default=["stream", "host", "device"])
    parser.add_argument("--rounds", type=int, default=1, help="timed passes per level")
    add_device(parser)
    add_threads(parser, default=2)
    parser.add_argument("--cache-dir", type=Path, default=CACHE)
    parser.add_argument("--before", type=Path, default=None, help="a checkout of the code before issue 34")
    parser.add_argument("--after", type=Path, default=REPO, help="the checkout to compare it with (default: this one)")
    parser.add_argument("--ab-epochs", type=int, default=1)
    parser.add_argument("--ab-rounds", type=int, default=2)
    parser.add_argument(
        "--ab-work",
        type=Path,
        default=None,
        help="folder for the two sides' caches and runs (kept: a second call reuses the caches)",
    )
    add_out(parser, SPEED_RESULTS / "bench_gpu")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    device = torch.device(args.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    raw = run_config(args.data, args.topology, args.train, args.val, 1, args.cache_dir, str(device), args.threads)
    config = parse_config(raw)
    preprocess.IN_MEMORY_VERTEX_LIMIT = 0  # streamed, as the recipe's 80 FAUST-size shapes are
    dataset = build_dataset(config, progress=False, workers=None)
    spec = model_spec(config.model, dataset.in_channels, dataset.num_classes, dataset.patch_configs)
    result = {
        "device": str(device),
        "device_name": device_name(device),
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "data": str(args.data or f"generated {args.topology} bodies"),
        "vertices": dataset[0].n_vertices,
        "shapes": {"train": len(dataset.splits["train"]), "val": len(dataset.splits["val"])},
        "levels": [],
    }
    for level in args.levels:
        entry = bench_level(level, config, dataset, spec, device, args.rounds)
        print(
            f"{level:7s} step {entry['step_ms']:.0f} ms ("
            + ", ".join(f"{p} {entry['phase_ms'][p]:.0f}" for p in PHASES)
            + f"), busy {entry['busy']:.0%}, epoch {entry['epoch_median_s']:.1f} s, set-up {entry['setup_s']:.1f} s"
        )
        result["levels"].append(entry)
    if args.before is not None:
        ab_config = dict(raw, train=dict(raw["train"], device="cpu"))
        with tempfile.TemporaryDirectory(prefix="bench_gpu_") as temporary:
            work = args.ab_work or Path(temporary)
            result["before_after"] = before_after(
                args.before.resolve(),
                args.after.resolve(),
                ab_config,
                work,
                args.ab_epochs,
                args.ab_rounds,
                args.threads,
            )
        ab = result["before_after"]
        print(
            f"CPU epoch before {ab['median_epoch_s']['before']:.1f} s, after {ab['median_epoch_s']['after']:.1f} s: "
            f"after/before {ab['after_over_before']:.2f}"
        )
    write_json(result_file(args.out, ".json"), result)
    write_markdown(result_file(args.out, ".md"), markdown(result))


if __name__ == "__main__":
    main()
