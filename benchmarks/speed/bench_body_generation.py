"""Generated human bodies: time of the body model build, of one body, and of preprocessing one body.

For each topology: the anny model build (in this process; anny reuses a model it built earlier in the same
process, and the first build on a machine with an empty ``~/.cache/anny`` is much slower, see
docs/BODIES.md), the topology build, the seconds per posed body (no body cache), and one body's preprocessing (area normalisation and patch operator, no operator cache) with
the settings the shipped configurations use: the demo's (area 1000, r0 4, 1600 samples, 50 per patch) on
the coarse topologies, the paper's FAUST settings (area 15000, r0 5.5, 12000 samples, r0/4 left out,
centre subtracted) with the ``fast`` and ``front`` geodesic backends on the 6,890-vertex one.

    .venv/bin/python -m benchmarks.speed.bench_body_generation         # every topology, 5 bodies each
    .venv/bin/python -m benchmarks.speed.bench_body_generation --bodies 2 --topologies coarse-615

Prints a table and writes ``benchmarks/speed/results/bench_body_generation.json`` (``--out``).
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

import torch

from benchmarks.harness import SPEED_RESULTS, add_out, add_threads, arguments, markdown_table, result_file, write_json
from zernet.data.bodies import BodyGenerator
from zernet.geometry import normalize_area
from zernet.operators import PatchConfig, build_patch_operator

DEMO_PATCH = {"area": 1000.0, "config": dict(r0=4.0, n_samples=1600, patch_size=50, n_max=5)}
FAUST_PATCH = {
    "area": 15000.0,
    "config": dict(r0=5.5, n_samples=12000, patch_size=50, n_max=5, inner_radius=1.375, subtract_center=True),
}
TOPOLOGIES = ("coarse-369", "coarse-615", "coarse-1229", "faust")


def _settings(topology: str) -> list[tuple[str, float, PatchConfig]]:
    """(label, area, patch config) of the preprocessing runs of one topology."""
    if topology == "faust":
        return [
            (f"FAUST settings, {backend}", FAUST_PATCH["area"], PatchConfig(**FAUST_PATCH["config"], backend=backend))
            for backend in ("fast", "front")
        ]
    return [("demo settings, fast", DEMO_PATCH["area"], PatchConfig(**DEMO_PATCH["config"]))]


def measure(topology: str, n_bodies: int, workdir: Path) -> dict:
    """Model build, topology build, seconds per body, preprocessing seconds per body (median)."""
    generator = BodyGenerator(topology, "varied", seed=0, cache_dir=workdir / topology)
    started = time.perf_counter()
    generator.model  # noqa: B018  (builds the anny model)
    model_seconds = time.perf_counter() - started
    started = time.perf_counter()
    topology_data = generator.topology()
    topology_seconds = time.perf_counter() - started
    per_body, bodies = [], []
    for index in range(n_bodies):
        started = time.perf_counter()
        bodies.append(generator.body(index))
        per_body.append(time.perf_counter() - started)
    preprocessing = {}
    for label, area, config in _settings(topology):
        seconds = []
        for body in bodies:
            started = time.perf_counter()
            surface, _ = normalize_area(body.surface(), area)
            build_patch_operator(surface, config, cache_dir=None)
            seconds.append(time.perf_counter() - started)
        preprocessing[label] = statistics.median(seconds)
    return {
        "n_vertices": topology_data.n_vertices,
        "model_build_seconds": model_seconds,
        "topology_seconds": topology_seconds,
        "body_seconds": statistics.median(per_body),
        "preprocess_seconds": preprocessing,
        "bodies": n_bodies,
    }


def main(argv=None) -> int:
    parser = arguments(__doc__)
    parser.add_argument("--bodies", type=int, default=5, help="bodies per topology (default 5)")
    parser.add_argument("--topologies", default=",".join(TOPOLOGIES), help="comma-separated topologies")
    add_threads(parser, default=1)
    add_out(parser, SPEED_RESULTS / "bench_body_generation")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    results = {}
    with tempfile.TemporaryDirectory(prefix="zernet-bodies-") as workdir:
        for topology in args.topologies.split(","):
            results[topology] = measure(topology, args.bodies, Path(workdir))
            r = results[topology]
            print(
                f"{topology}: {r['n_vertices']} vertices, model {r['model_build_seconds']:.1f} s, topology "
                f"{r['topology_seconds']:.2f} s, per body {r['body_seconds']:.3f} s, preprocessing per body "
                + ", ".join(f"{k} {v:.2f} s" for k, v in r["preprocess_seconds"].items()),
                flush=True,
            )
    header = [
        "topology",
        "vertices",
        "anny model build, this process (s)",
        "per body (s)",
        "preprocessing per body (s)",
    ]
    rows = [
        [
            topology,
            f"{r['n_vertices']:,}",
            f"{r['model_build_seconds']:.1f}",
            f"{r['body_seconds']:.3f}",
            "; ".join(f"{k}: {v:.2f}" for k, v in r["preprocess_seconds"].items()),
        ]
        for topology, r in results.items()
    ]
    print("\n" + "\n".join(markdown_table(header, rows, align="lrrrl")))
    write_json(result_file(args.out, ".json"), {"threads": args.threads, "results": results})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
