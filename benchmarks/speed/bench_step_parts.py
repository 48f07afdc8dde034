"""How fast a FAUST training step could be if the patch operators cost nothing: the floor that no storage
format, residency or operator kernel can go below (issue 50).

The shipped FAUST recipe (``configs/faust_single_scale.yaml``: its model, its patch settings, a 6,890-way
output) trains on one generated body of FAUST's size (``benchmarks.harness.body_surface``, 6,890
vertices; the inputs are random features of the recipe's width: a step's cost does not depend on their
values). Each step is timed in four variants, alternating over ``--rounds`` rounds so a slow minute of the
machine hits all of them:

* *operators*: the operator as training holds it (vertex pairs in the cache's precision, prepared in the
  layers' basis order), applied forward and backward by its kernels;
* *free operators*: every convolution's operator replaced by one that returns its coefficients as zeros
  and hands back zero gradients: the same layers, products, pooling, head and optimiser, with the
  operators' reading and applying taken out. Its time over the first variant's is the fraction of the step
  that storage and the operator kernels cannot take away;

each in float32 and in ``train.precision: bfloat16`` (linear layers in bfloat16, convolutions in float32).

    .venv/bin/python -m benchmarks.speed.bench_step_parts --threads 2

Prints the medians (seconds per step) and writes ``benchmarks/speed/results/bench_step_parts.json``.
"""

from __future__ import annotations

import statistics
import time

import numpy as np
import torch
import torch.nn.functional as nnf

from benchmarks.harness import (
    REPO,
    SPEED_RESULTS,
    add_out,
    add_threads,
    arguments,
    body_surface,
    result_file,
    write_json,
)
from benchmarks.speed.bench_operator import FAUST_RECIPE
from zernet.data.features import feature_channels
from zernet.inference import build_model_from_spec, model_spec
from zernet.inference.batch import model_basis_orders
from zernet.inference.runtime import flush_denormals, keep_freed_memory, precision_autocast
from zernet.operators import Geometry, PatchConfig, build_patch_operator
from zernet.training.config import load_config, parse_config


class _ZeroCoefficients(torch.autograd.Function):
    """``x (N, C)`` -> zeros ``(N, k, C)``; the backward hands ``x`` zeros: an operator that costs nothing."""

    @staticmethod
    def forward(ctx, x, k):
        ctx.shape = x.shape
        return x.new_zeros(x.shape[0], k, x.shape[1])

    @staticmethod
    def backward(ctx, grad):
        return grad.new_zeros(ctx.shape), None


class FreeOperator:
    """Stands in for a patch operator with ``k`` bases on ``n_vertices`` vertices at no cost."""

    accepts_basis_order = True

    def __init__(self, n_vertices: int, k: int):
        self.n_vertices, self.k = n_vertices, k

    def apply(self, x: torch.Tensor, basis_order: tuple | None = None) -> torch.Tensor:
        return _ZeroCoefficients.apply(x, self.k)


def step_seconds(model, optimizer, features, geometry, target, precision: str, steps: int) -> list[float]:
    """Wall seconds of each of ``steps`` training steps (forward, loss in float32, backward, Adam)."""
    seconds = []
    for _ in range(steps):
        started = time.perf_counter()
        optimizer.zero_grad(set_to_none=True)
        with precision_autocast(precision, features.device.type):
            output = model(features, geometry)
        loss = nnf.cross_entropy(output.float(), target)
        loss.backward()
        optimizer.step()
        seconds.append(time.perf_counter() - started)
    return seconds


def main() -> None:
    parser = arguments(__doc__)
    add_threads(parser, default=2)
    parser.add_argument("--steps", type=int, default=4, help="timed steps per variant and round")
    parser.add_argument("--rounds", type=int, default=3)
    add_out(parser, SPEED_RESULTS / "bench_step_parts")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    keep_freed_memory()  # as the zernet command does

    config = parse_config(load_config(FAUST_RECIPE))
    patch = PatchConfig(**config.patch.scales[0])
    surface, _ = body_surface()
    n = surface.n_vertices
    operator = build_patch_operator(surface, patch)
    in_channels = feature_channels(config.data.options["features"], patch.n_max)
    spec = model_spec(config.model, in_channels, n, [patch])
    torch.manual_seed(0)
    model = build_model_from_spec(spec)
    weights = {name: value.clone() for name, value in model.state_dict().items()}
    operator.to("cpu", model_basis_orders(model))
    geometries = {"operators": Geometry([operator]), "free operators": Geometry([FreeOperator(n, operator.k)])}
    features = torch.randn(n, in_channels)
    target = torch.randperm(n)  # every vertex its own class, as in FAUST correspondence

    variants = [(precision, name) for precision in ("float32", "bfloat16") for name in geometries]
    times: dict[tuple[str, str], list[float]] = {variant: [] for variant in variants}

    def run(variant, steps):
        precision, name = variant
        model.load_state_dict(weights)  # every variant computes the same steps
        model.train()
        optimizer = torch.optim.Adam(model.parameters(), lr=config.train.lr)
        return step_seconds(model, optimizer, features, geometries[name], target, precision, steps)

    with flush_denormals():  # as training runs its epochs
        for variant in variants:  # warm-up: kernels compiled, allocator grown, products built once
            run(variant, 1)
        for _ in range(args.rounds):
            for variant in variants:
                times[variant] += run(variant, args.steps)

    medians = {variant: statistics.median(values) for variant, values in times.items()}
    reference = medians[("float32", "operators")]
    print(
        f"shipped FAUST recipe, one generated body of {n:,} vertices ({operator.pairs.n_pairs:,} vertex pairs, "
        f"{patch.precision}), {args.threads} thread(s), median of {args.rounds} x {args.steps} steps"
    )
    print(f"{'precision':10} {'operators':15} {'s / step':>9} {'of float32 with operators':>26}")
    rows = []
    for (precision, name), value in medians.items():
        print(f"{precision:10} {name:15} {value:9.2f} {value / reference:26.2f}")
        rows.append(
            {
                "precision": precision,
                "operators": name,
                "seconds_per_step": times[(precision, name)],
                "median_seconds_per_step": value,
                "of_float32_with_operators": value / reference,
            }
        )
    write_json(
        result_file(args.out, ".json"),
        {
            "recipe": str(FAUST_RECIPE.relative_to(REPO)),
            "vertices": n,
            "pairs": int(operator.pairs.n_pairs),
            "operator_precision": patch.precision,
            "threads": args.threads,
            "rounds": args.rounds,
            "steps": args.steps,
            "rows": rows,
            "mean_step_spread": float(np.mean([np.std(v) / np.mean(v) for v in times.values()])),
        },
    )


if __name__ == "__main__":
    main()
