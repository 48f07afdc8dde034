"""Benchmark of the patch operator: polar-coordinate backends (time, accuracy) and operator apply time.

Prints a table and writes ``benchmarks/results/bench_operator.json``.

Surfaces:
* a procedural "mannequin" with human proportions at area 15000 (FAUST cannot be shipped): torso, head,
  arms, legs and four thin fingers as capsules, 10 closed components a few units apart, ~6,900 vertices,
  well-shaped triangles. It has thin parts (fingers, circumference ≈ r0) and sheets of other parts
  within r0 (legs 3.5 units apart, fingers 0.4 apart), but no limb-torso junctions.
* the aneurysm meshes of ``--aneurysms DIR`` (default ``data/aneurysm``) when that folder exists (area 100, r0 = 0.6 as in
  the paper's regression experiment, 12,000 samples).

Accuracy of a backend is measured against the accurate backend (potpourri3d log map, AffineLocal) on the
(vertex, sample) pairs both keep: radius error in % of r0 (median, p95), and angle error p95 after
removing each vertex's constant frame offset (the circular mean of its angle differences), over pairs
with radius > 0.1 r0 (the angle of a sample almost at the vertex is ill-defined).

Usage::

    .venv/bin/python benchmarks/bench_operator.py            # full run (accurate backend on everything)
    .venv/bin/python benchmarks/bench_operator.py --quick    # smaller meshes, one aneurysm
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

from zernet.operators import PatchConfig, assemble_operator, build_patch_operator
from zernet.geometry import compute_polar
from zernet.geometry import Surface, load_surface, sample_surface

RESULTS = Path(__file__).resolve().parent / "results" / "bench_operator.json"
ANEURYSMS = Path("data/aneurysm")  # your copy of the aneurysm data set


# ====================================================================== the procedural body
def _capsule(radius: float, length: float, edge: float) -> tuple[np.ndarray, np.ndarray]:
    """Closed capsule along z centred at the origin: staggered rings ~``edge`` apart, one vertex per pole."""
    around = max(6, int(round(2 * np.pi * radius / edge)))
    cap = np.pi * radius / 2
    total = 2 * cap + length
    n_rings = max(3, int(round(total / (edge * 0.866))))
    s = np.linspace(0, total, n_rings + 2)[1:-1]  # arclength along the profile, poles excluded
    lower, upper = s < cap, s > cap + length
    z = np.where(lower, -length / 2 - radius * np.cos(s / radius), np.where(upper, length / 2 + radius * np.cos((total - s) / radius), s - cap - length / 2))
    rho = np.where(lower, radius * np.sin(s / radius), np.where(upper, radius * np.sin((total - s) / radius), radius))
    phi = 2 * np.pi * (np.arange(around)[None, :] + 0.5 * (np.arange(n_rings)[:, None] % 2)) / around
    ring = np.stack([rho[:, None] * np.cos(phi), rho[:, None] * np.sin(phi), np.repeat(z[:, None], around, 1)], -1)
    vertices = np.concatenate([[[0, 0, -length / 2 - radius]], ring.reshape(-1, 3), [[0, 0, length / 2 + radius]]])
    index = 1 + np.arange(n_rings * around).reshape(n_rings, around)
    a = np.arange(around)
    b = (a + 1) % around
    faces = [np.stack([np.zeros(around, int), index[0, b], index[0, a]], 1)]
    for r in range(n_rings - 1):
        lo, hi = index[r], index[r + 1]
        if r % 2 == 0:  # the upper ring is shifted by half a step
            faces += [np.stack([lo[a], lo[b], hi[a]], 1), np.stack([lo[b], hi[b], hi[a]], 1)]
        else:
            faces += [np.stack([lo[a], hi[b], hi[a]], 1), np.stack([lo[a], lo[b], hi[b]], 1)]
    top = len(vertices) - 1
    faces.append(np.stack([np.full(around, top), index[-1, a], index[-1, b]], 1))
    return vertices, np.concatenate(faces)


def mannequin(area: float = 15000.0, edge: float = 1.79) -> Surface:
    """Human-proportioned capsule figure scaled to ``area`` (edge 1.79 gives ~6,900 vertices)."""
    parts: list[tuple[np.ndarray, np.ndarray]] = []

    def add(radius, length, offset, horizontal=False):
        vertices, faces = _capsule(radius, length, edge)
        if horizontal:  # rotate z -> x
            vertices = vertices[:, [2, 1, 0]] * [1, 1, -1]
        parts.append((vertices + offset, faces))

    add(13.0, 45.0, (0, 0, 0))  # torso
    add(9.0, 4.0, (0, 0, 52))  # head
    for side in (-1, 1):
        add(4.0, 50.0, (side * 48, 0, 18), horizontal=True)  # arms
        add(6.0, 70.0, (side * 8, 0, -80))  # legs, 3.5 units apart at the thighs
    for finger in range(4):
        add(0.8, 7.0, (83, 0, 14.5 + 2.0 * finger), horizontal=True)  # fingers, 0.4 apart
    offsets = np.cumsum([0] + [len(v) for v, _ in parts])
    vertices = np.concatenate([v for v, _ in parts])
    faces = np.concatenate([f + o for (_, f), o in zip(parts, offsets)])
    surface = Surface(vertices, faces, name="mannequin")
    return Surface(vertices * np.sqrt(area / surface.area), faces, name="mannequin")


# ====================================================================== measurements
def _best_time(function, repeats: int) -> tuple[float, object]:
    best, result = np.inf, None
    for _ in range(repeats):
        start = time.perf_counter()
        result = function()
        best = min(best, time.perf_counter() - start)
    return best, result


def compare(reference, candidate, r0: float) -> dict:
    """Radius and angle errors of ``candidate`` against ``reference`` on their common pairs."""
    n_samples = int(max(reference.sample.max(), candidate.sample.max())) + 1
    key_ref = reference.center * n_samples + reference.sample
    key_new = candidate.center * n_samples + candidate.sample
    common, i_ref, i_new = np.intersect1d(key_ref, key_new, assume_unique=True, return_indices=True)
    radius_error = np.abs(candidate.radius[i_new] - reference.radius[i_ref]) / r0 * 100
    centers = reference.center[i_ref]
    usable = reference.radius[i_ref] > 0.1 * r0
    difference = np.angle(np.exp(1j * (candidate.angle[i_new] - reference.angle[i_ref])))[usable]
    centers = centers[usable]
    # Per-vertex constant frame offset: circular mean of the differences.
    mean_vector = np.zeros(reference.frames.shape[0], dtype=complex)
    np.add.at(mean_vector, centers, np.exp(1j * difference))
    residual = np.abs(np.angle(np.exp(1j * (difference - np.angle(mean_vector[centers])))))
    return {
        "pairs_reference": int(len(key_ref)),
        "pairs_common_pct": 100.0 * len(common) / max(len(key_ref), 1),
        "pairs_extra_pct": 100.0 * (len(key_new) - len(common)) / max(len(key_ref), 1),
        "radius_error_median_pct_r0": float(np.median(radius_error)),
        "radius_error_p95_pct_r0": float(np.percentile(radius_error, 95)),
        "angle_error_p95_rad": float(np.percentile(residual, 95)),
    }


def bench_surface(surface: Surface, config: PatchConfig, n_jobs: int, repeats: int) -> dict:
    """Build times of both backends and the fast backend's accuracy on one surface."""
    samples = sample_surface(surface, config.n_samples, seed=config.seed)
    fast_build, _ = _best_time(lambda: build_patch_operator(surface, config), repeats)
    fast_polar_time, fast = _best_time(lambda: compute_polar(surface, samples, config.r0, "fast"), repeats)
    start = time.perf_counter()
    accurate = compute_polar(surface, samples, config.r0, "accurate", n_jobs=n_jobs)
    accurate_time = time.perf_counter() - start
    start = time.perf_counter()
    assemble_operator(accurate.center, accurate.sample, accurate.radius, accurate.angle, accurate.frames, samples.interpolation, config)
    accurate_build = accurate_time + (time.perf_counter() - start)
    return {
        "name": surface.name,
        "vertices": surface.n_vertices,
        "area": surface.area,
        "r0": config.r0,
        "samples": config.n_samples,
        "fast": {"operator_build_s": fast_build, "polar_s": fast_polar_time, **compare(accurate, fast, config.r0)},
        "accurate": {"operator_build_s": accurate_build, "polar_s": accurate_time, "processes": n_jobs},
    }


def bench_apply(surface: Surface, config: PatchConfig, d: int, repeats: int) -> dict:
    """Forward and forward+backward time of the operator at width ``d`` (float32), and torch.sparse.mm."""
    op = build_patch_operator(surface, config)
    x = torch.randn(op.n_vertices, d, requires_grad=True)
    grad = torch.randn(op.n_vertices, op.k, d)
    op.apply(x)  # builds the cached tensors

    def forward():
        with torch.no_grad():
            return op.apply(x)

    def forward_backward():
        y = op.apply(x)
        y.backward(grad)

    t_forward, _ = _best_time(forward, repeats)
    t_both, _ = _best_time(forward_backward, repeats)
    coo = op.matrix.tocoo()
    builtin = torch.sparse_coo_tensor(np.vstack([coo.row, coo.col]), coo.data.astype(np.float32), coo.shape).coalesce()

    def builtin_forward_backward():
        y = torch.sparse.mm(builtin, x)
        y.backward(grad.reshape(-1, d))

    t_builtin, _ = _best_time(builtin_forward_backward, max(1, repeats // 2))
    return {
        "vertices": op.n_vertices,
        "k": op.k,
        "d": d,
        "nnz": op.nnz,
        "nnz_per_row": op.nnz / (op.n_vertices * op.k),
        "forward_ms": 1e3 * t_forward,
        "forward_backward_ms": 1e3 * t_both,
        "torch_sparse_mm_coo_forward_backward_ms": 1e3 * t_builtin,
        "torch_threads": torch.get_num_threads(),
    }


# ====================================================================== main
def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="smaller body, one aneurysm, fewer repeats")
    parser.add_argument("--jobs", type=int, default=2, help="processes for the accurate backend")
    parser.add_argument("--aneurysms", type=Path, default=ANEURYSMS, help="folder of the aneurysm .mat files")
    parser.add_argument("--output", type=Path, default=RESULTS)
    args = parser.parse_args(argv)

    repeats = 2 if args.quick else 3
    rows = []
    body = mannequin(edge=3.0 if args.quick else 1.79)
    body_config = PatchConfig(r0=5.5, n_samples=12000)
    rows.append(bench_surface(body, body_config, args.jobs, repeats))

    if args.aneurysms.is_dir():
        files = sorted(args.aneurysms.glob("*.mat"), key=lambda p: p.stat().st_size)
        chosen = files[:1] if args.quick else [files[0], files[len(files) // 2], files[-1]]
        for path in chosen:
            surface = load_surface(path)
            surface = Surface(surface.vertices * np.sqrt(100.0 / surface.area), surface.faces, name=path.name)
            rows.append(bench_surface(surface, PatchConfig(r0=0.6, n_samples=12000), args.jobs, repeats))

    apply_body = body if not args.quick else mannequin(edge=1.79)
    apply = bench_apply(apply_body, body_config, 128, 5 if args.quick else 10)

    header = f"{'surface':<18}{'N':>6}{'r0':>5}  {'backend':<9}{'build s':>8}{'polar s':>8}{'r med %':>8}{'r p95 %':>8}{'θ p95 rad':>10}{'common %':>9}"
    print(header)
    print("-" * len(header))
    for row in rows:
        fast, acc = row["fast"], row["accurate"]
        print(
            f"{row['name']:<18}{row['vertices']:>6}{row['r0']:>5}  {'fast':<9}{fast['operator_build_s']:>8.2f}{fast['polar_s']:>8.2f}"
            f"{fast['radius_error_median_pct_r0']:>8.3f}{fast['radius_error_p95_pct_r0']:>8.2f}{fast['angle_error_p95_rad']:>10.4f}{fast['pairs_common_pct']:>9.1f}"
        )
        print(f"{'':<18}{'':>6}{'':>5}  {'accurate':<9}{acc['operator_build_s']:>8.2f}{acc['polar_s']:>8.2f}{'(reference, ' + str(acc['processes']) + ' processes)':>35}")
    print()
    print(
        f"apply N={apply['vertices']} k={apply['k']} d={apply['d']} float32, nnz={apply['nnz']} ({apply['nnz_per_row']:.1f}/row): "
        f"forward {apply['forward_ms']:.1f} ms, forward+backward {apply['forward_backward_ms']:.1f} ms "
        f"(torch.sparse.mm COO: {apply['torch_sparse_mm_coo_forward_backward_ms']:.1f} ms)"
    )
    result = {
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "quick": args.quick,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "torch": torch.__version__, "load_average": os.getloadavg()},
        "surfaces": rows,
        "apply": apply,
    }
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(result, indent=2))
    print(f"wrote {args.output}")
    return result


if __name__ == "__main__":
    main()
