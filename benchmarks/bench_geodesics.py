"""Geodesic polar coordinates of each backend against exact polyhedral geodesics, on realistic surfaces.

The reference is MMP (``zernet.geometry.exact``: the samples inserted into the mesh as vertices, initial
directions from the exact paths), on random centre vertices. Surfaces: a posed generated human body
(``zernet.data.bodies``, fingers, armpits and crotch), scaled to area 15000 with r0 = 5.5 and 12,000
samples as in the paper's FAUST settings, plus any mesh passed with ``--mesh PATH`` (scaled to
``--area``; an aneurysm ``.mat`` case works at area 100, r0 0.6, 8000 samples).

    .venv/bin/python benchmarks/bench_geodesics.py --centres 100
    .venv/bin/python benchmarks/bench_geodesics.py --mesh case.mat --area 100 --r0 0.6 --samples 8000

Per backend: kept pairs whose exact distance exceeds 1.1 r0 (a fold crossed), true pairs (exact < 0.95 r0)
dropped, radius error median / p95 in % of r0, angle error p95 (rad, r > 0.1 r0, after removing each
centre's median offset), and the time for all vertices. Prints a table, writes
``benchmarks/results/bench_geodesics.json``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from zernet.data.bodies import generate_bodies
from zernet.geometry import Surface, compute_polar, load_surface, normalize_area, sample_surface, tangent_frames
from zernet.geometry.exact import ExactGeodesics
from zernet.io_utils import atomic_write_bytes

RESULTS = Path(__file__).resolve().parent / "results" / "bench_geodesics.json"


def body_surface(seed: int) -> Surface:
    """One posed generated body at the FAUST-sized topology."""
    body = generate_bodies(count=2, seed=seed, topology="faust", poses="varied", n_test=1, progress=False)[0]
    return Surface(body.vertices, body.faces, name=f"generated body (seed {seed})")


def exact_reference(surface, samples, frames, centres, r0):
    """{(centre, sample): (distance, angle)} from MMP."""
    c, s, d, a = ExactGeodesics(surface, samples, frames).polar(centres, r0, limit=1.5 * r0)
    return {(int(i), int(j)): (dist, ang) for i, j, dist, ang in zip(c, s, d, a)}


def score(polar, exact, centres, r0) -> dict:
    """The accuracy columns of one backend against the exact pairs of ``centres``."""
    chosen = set(int(c) for c in centres)
    pick = np.isin(polar.center, centres)
    kept = {(int(i), int(j)): (r, t) for i, j, r, t in
            zip(polar.center[pick], polar.sample[pick], polar.radius[pick], polar.angle[pick])}
    far = sum(1 for key in kept if exact.get(key, (np.inf,))[0] > 1.1 * r0)
    true = [key for key, (d, _) in exact.items() if d < 0.95 * r0 and key[0] in chosen]
    dropped = sum(1 for key in true if key not in kept)
    both = [key for key in true if key in kept]
    radius_error = np.array([abs(kept[k][0] - exact[k][0]) for k in both]) / r0
    angle_error = []
    for centre in chosen:
        keys = [k for k in both if k[0] == centre and exact[k][0] > 0.1 * r0 and np.isfinite(exact[k][1])]
        if keys:
            diff = np.angle(np.exp(1j * np.array([kept[k][1] - exact[k][1] for k in keys])))
            offset = np.angle(np.mean(np.exp(1j * diff)))
            angle_error.extend(np.abs(np.angle(np.exp(1j * (diff - offset)))))
    return {"kept_beyond_1.1r0_percent": 100.0 * far / max(1, len(kept)),
            "true_dropped_percent": 100.0 * dropped / max(1, len(true)),
            "radius_median_percent_r0": 100.0 * float(np.median(radius_error)),
            "radius_p95_percent_r0": 100.0 * float(np.percentile(radius_error, 95)),
            "angle_p95_rad": float(np.percentile(angle_error, 95)) if angle_error else None}


def measure(surface, r0, n_samples, n_centres, backends, seed) -> dict:
    samples = sample_surface(surface, n_samples, seed=seed)
    frames = tangent_frames(surface)
    centres = np.sort(np.random.default_rng(seed).choice(surface.n_vertices, n_centres, replace=False))
    started = time.perf_counter()
    exact = exact_reference(surface, samples, frames, centres, r0)
    rows = {"surface": surface.name, "vertices": surface.n_vertices, "r0": r0, "samples": n_samples,
            "centres": n_centres, "reference_seconds": time.perf_counter() - started, "backends": {}}
    for backend in backends:
        polar = compute_polar(surface, samples, r0, backend=backend)
        rows["backends"][backend] = {"seconds_all_vertices": polar.seconds, **score(polar, exact, centres, r0)}
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--mesh", type=Path, action="append", default=[], help="also measure this mesh")
    parser.add_argument("--area", type=float, default=15000.0)
    parser.add_argument("--r0", type=float, default=5.5)
    parser.add_argument("--samples", type=int, default=12000)
    parser.add_argument("--centres", type=int, default=100)
    parser.add_argument("--backends", nargs="+", default=["fast", "front"])
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    surfaces = [body_surface(args.seed)] + [load_surface(path) for path in args.mesh]
    results = []
    for surface in surfaces:
        surface, _ = normalize_area(surface, args.area)
        results.append(measure(surface, args.r0, args.samples, args.centres, args.backends, args.seed))
        row = results[-1]
        print(f"\n{row['surface']}: {row['vertices']} vertices, r0 {row['r0']}, {row['samples']} samples, "
              f"{row['centres']} centres (exact reference {row['reference_seconds']:.0f} s)")
        print(f"{'backend':8} {'>1.1r0 %':>9} {'dropped %':>10} {'r med %':>8} {'r p95 %':>8} {'θ p95':>7} {'time s':>7}")
        for name, b in row["backends"].items():
            angle = "-" if b["angle_p95_rad"] is None else f"{b['angle_p95_rad']:.3f}"
            print(f"{name:8} {b['kept_beyond_1.1r0_percent']:9.2f} {b['true_dropped_percent']:10.2f} "
                  f"{b['radius_median_percent_r0']:8.3f} {b['radius_p95_percent_r0']:8.2f} {angle:>7} "
                  f"{b['seconds_all_vertices']:7.2f}")
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(RESULTS, json.dumps(results, indent=2).encode())


if __name__ == "__main__":
    main()
