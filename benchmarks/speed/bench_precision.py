"""Does ``train.precision: bfloat16`` cost accuracy? float32 against bfloat16 linear layers, same everything else.

A many-class stand-in for shape correspondence that needs no download: creatures of
:func:`zernet.data.synthetic.make_creature` share one mesh topology (a Fibonacci sphere of ``--vertices``
vertices, not rotated), so vertex ``i`` is "the same point" on every creature and the class of a vertex is its
index, as in FAUST. The single-scale correspondence model (Conv64-Conv128-Conv256-Lin512-Lin<N>, s = 4,
input xyz + normals) is trained twice from the same initial weights and shape order: once in float32, once
with the linear layers in bfloat16 under ``torch.autocast`` (convolutions stay float32), for each of
``--seeds`` initialisations, so the precision effect can be read against the seed spread. Printed: test
accuracy (predicted vertex = true vertex), mean distance of the predicted vertex to the true one (in units of
the patch radius), and the median training step time of each.

Usage::

    .venv/bin/python -m benchmarks.speed.bench_precision              # 24 creatures of 1,000 vertices, 15 epochs
    .venv/bin/python -m benchmarks.speed.bench_precision --epochs 5   # quicker
"""

from __future__ import annotations

import copy
import dataclasses
import statistics
import sys
import time

import numpy as np
import torch

from benchmarks.harness import SPEED_RESULTS, add_out, arguments, result_file, write_json
from zernet.data.features import compute_features
from zernet.data.synthetic import make_creature
from zernet.inference import keep_freed_memory, precision_autocast
from zernet.nn import Geometry, build_model
from zernet.operators import PatchConfig, build_patch_operator

PATCH = PatchConfig(r0=2.5, n_samples=4000, patch_size=50, n_max=5)


def creatures(count: int, n_vertices: int) -> list[dict]:
    """Surfaces, their patch operator and standardised xyz + normals features."""
    shapes = []
    for seed in range(count):
        surface, _, _ = make_creature(1000 + seed, n_vertices=n_vertices, rotate=False)
        operator = build_patch_operator(surface, PATCH)
        shapes.append(
            {
                "surface": surface,
                "geometry": Geometry([operator]),
                "x": torch.from_numpy(compute_features(surface, "xyz+normals")),
            }
        )
    features = torch.cat([s["x"] for s in shapes])
    mean, std = features.mean(0), features.std(0)
    for s in shapes:
        s["x"] = (s["x"] - mean) / std
    return shapes


def train_and_test(model, train, test, epochs: int, lr: float, precision: str, seed: int) -> dict:
    target = torch.arange(train[0]["x"].shape[0])
    optimizer = torch.optim.Adam(model.parameters(), lr=lr)
    generator = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)  # dropout masks
    step_times, losses = [], []
    for _ in range(epochs):
        model.train()
        for i in torch.randperm(len(train), generator=generator).tolist():
            started = time.perf_counter()
            optimizer.zero_grad(set_to_none=True)
            with precision_autocast(precision, "cpu"):
                output = model(train[i]["x"], train[i]["geometry"])
            loss = torch.nn.functional.cross_entropy(output.float(), target)
            loss.backward()
            optimizer.step()
            step_times.append(time.perf_counter() - started)
            losses.append(loss.item())
    model.eval()
    hits, distances = [], []
    with torch.no_grad():
        for shape in test:
            predicted = model(shape["x"], shape["geometry"]).argmax(dim=1).numpy()
            vertices = shape["surface"].vertices
            hits.append(float((predicted == np.arange(len(predicted))).mean()))
            distances.append(float(np.linalg.norm(vertices[predicted] - vertices, axis=1).mean() / PATCH.r0))
    return {
        "accuracy": float(np.mean(hits)),
        "mean_error_r0": float(np.mean(distances)),
        "final_train_loss": float(np.mean(losses[-len(train) :])),
        "step_s_median": statistics.median(step_times),
    }


def main(argv=None) -> int:
    parser = arguments(__doc__)
    parser.add_argument("--shapes", type=int, default=24, help="creatures; the last 4 are the test shapes")
    parser.add_argument("--vertices", type=int, default=1000, help="vertices (= classes) per creature")
    parser.add_argument("--epochs", type=int, default=15)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--seeds", type=int, default=2, help="initial weights and shape orders tried")
    add_out(parser, SPEED_RESULTS / "bench_precision")
    args = parser.parse_args(argv)
    keep_freed_memory()
    shapes = creatures(args.shapes, args.vertices)
    train, test = shapes[:-4], shapes[-4:]
    rows = {"float32": [], "bfloat16": []}
    for seed in range(args.seeds):
        torch.manual_seed(seed)
        initial = build_model("zernet", 6, args.vertices, widths=(64, 128, 256, 512), angular_resolution=4)
        for name in ("float32", "bfloat16"):
            row = train_and_test(copy.deepcopy(initial), train, test, args.epochs, args.lr, name, seed)
            rows[name].append(row)
            print(
                f"seed {seed} {name:8s}: test accuracy {row['accuracy']:.3f}, mean error "
                f"{row['mean_error_r0']:.3f} r0, final train loss {row['final_train_loss']:.3f}, "
                f"step {row['step_s_median'] * 1e3:.0f} ms",
                flush=True,
            )
    for name, runs in rows.items():
        print(
            f"{name:8s}: accuracy over seeds "
            + " ".join(f"{r['accuracy']:.3f}" for r in runs)
            + f", mean {np.mean([r['accuracy'] for r in runs]):.3f}"
        )
    payload = {
        "shapes": args.shapes,
        "test_shapes": 4,
        "vertices": args.vertices,
        "epochs": args.epochs,
        "lr": args.lr,
        "seeds": args.seeds,
        "patch": dataclasses.asdict(PATCH),
        "rows": rows,
    }
    write_json(result_file(args.out, ".json"), payload)
    return 0


if __name__ == "__main__":
    sys.exit(main())
