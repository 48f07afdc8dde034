"""Geodesic polar coordinates of each backend against exact polyhedral geodesics, on realistic surfaces.

The reference is MMP (``zernet.geometry.polar.exact``: the samples inserted into the mesh as vertices, initial
directions from the exact paths), on random centre vertices. Surfaces: a posed generated human body
(``zernet.data.bodies``, fingers, armpits and crotch), scaled to area 15000 with r0 = 5.5 and 12,000
samples as in the paper's FAUST settings, plus any mesh passed with ``--mesh PATH`` (scaled to
``--area``; an aneurysm ``.mat`` case works at area 100, r0 0.6, 8000 samples).

    .venv/bin/python -m benchmarks.speed.bench_geodesics --centres 100
    .venv/bin/python -m benchmarks.speed.bench_geodesics --mesh case.mat --area 100 --r0 0.6 --samples 8000

Point clouds (backend ``cloud``): the same surface's vertices without faces, triangulated through
themselves (:func:`zernet.geometry.mesh_from_cloud`) and measured by the front on that triangulation, at
the same samples (each moved to the nearest point of the cloud's triangulation), against the same exact
geodesics on the mesh the points came from; its build time is that of the whole point-cloud operator.
Backend ``cloud-normals``: the same cloud with the mesh's normals given (as a scanner that writes ``nx ny
nz`` gives them), which the triangulation then uses instead of estimating and orienting its own: what the
estimated normals cost.

Per backend: kept pairs whose exact distance exceeds 1.1 r0 (a fold crossed), true pairs (exact < 0.95 r0)
dropped, radius error median / p95 in % of r0, angle error p95 (rad, r > 0.1 r0, after removing each
centre's circular-mean offset; on the body also per body part), and the time for all vertices.

Patch fit (the default :class:`~zernet.operators.PatchConfig`: every sample within r0, piston-sparing
ridge, backend front on meshes), on the vertices farther than r0 (Euclidean, so at least r0 along the
surface) from any boundary:

* constant field (``subtract_center`` off): piston error in % of its exact unit-disk value ``√π`` (p95)
  and the largest other coefficient in % of the piston (p95);
* linear field ``f(x) = g·x`` (random unit ``g``): the fit reconstructed at the patch samples, relative
  residual ``‖B a − f‖ / ‖f − f(p)‖`` per patch (median, p95), at ``n_max`` 5 and, to tell the Zernike
  truncation of curved patches from coordinate errors, at ``n_max`` 8 on the same coordinates, and the same
  fit on the exact (MMP) coordinates of the reference centres: what perfect geodesics would give;
* operator build time (sampling, polar coordinates, fit, assembly) in seconds per 1000 vertices: the
  first build in this process (compiled kernels loaded from numba's disk cache) and a second one.

Prints a table, writes ``benchmarks/speed/results/bench_geodesics.json`` (``--out``).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import scipy.sparse
import trimesh
from scipy.spatial import cKDTree

from benchmarks.harness import SPEED_RESULTS, add_out, arguments, body_surface, result_file, write_json
from zernet.geometry import (
    PolarCoordinates,
    Surface,
    SurfaceSamples,
    compute_polar,
    load_surface,
    mesh_from_cloud,
    normalize_area,
    sample_surface,
    tangent_frames,
)
from zernet.geometry.polar.exact import ExactGeodesics
from zernet.operators import PatchConfig, assemble_operator, build_patch_operator


def exact_reference(surface, samples, frames, centres, r0):
    """{(centre, sample): (distance, angle)} from MMP."""
    c, s, d, a = ExactGeodesics(surface, samples, frames).polar(centres, r0, limit=1.5 * r0)
    return {(int(i), int(j)): (dist, ang) for i, j, dist, ang in zip(c, s, d, a)}


def exact_polar(exact, frames, r0) -> PolarCoordinates:
    """The exact pairs within ``r0`` as polar coordinates (only the reference's centres have patches)."""
    pairs = np.array([(i, j, d, a) for (i, j), (d, a) in exact.items() if d <= r0 and np.isfinite(a)]).reshape(-1, 4)
    pairs = pairs[np.lexsort((pairs[:, 2], pairs[:, 0]))]
    return PolarCoordinates(
        pairs[:, 0].astype(np.int64),
        pairs[:, 1].astype(np.int64),
        pairs[:, 2],
        pairs[:, 3],
        frames,
        r0=r0,
        backend="exact",
    )


def score(polar, exact, centres, r0, regions=None) -> dict:
    """The accuracy columns of one backend against the exact pairs of ``centres``; with ``regions`` (the
    region name of every vertex) also the angle p95 of the centres in each region."""
    chosen = set(int(c) for c in centres)
    pick = np.isin(polar.center, centres)
    kept = {
        (int(i), int(j)): (r, t)
        for i, j, r, t in zip(polar.center[pick], polar.sample[pick], polar.radius[pick], polar.angle[pick])
    }
    far = sum(1 for key in kept if exact.get(key, (np.inf,))[0] > 1.1 * r0)
    true = [key for key, (d, _) in exact.items() if d < 0.95 * r0 and key[0] in chosen]
    dropped = sum(1 for key in true if key not in kept)
    both = [key for key in true if key in kept]
    radius_error = np.array([abs(kept[k][0] - exact[k][0]) for k in both]) / r0
    angle_error, region_errors = [], {}
    for centre in chosen:
        keys = [k for k in both if k[0] == centre and exact[k][0] > 0.1 * r0 and np.isfinite(exact[k][1])]
        if keys:
            diff = np.angle(np.exp(1j * np.array([kept[k][1] - exact[k][1] for k in keys])))
            offset = np.angle(np.mean(np.exp(1j * diff)))
            errors = np.abs(np.angle(np.exp(1j * (diff - offset))))
            angle_error.extend(errors)
            if regions is not None:
                region_errors.setdefault(str(regions[centre]), []).extend(errors)
    far_by_region = {}
    if regions is not None:
        for name in sorted(set(str(regions[c]) for c in chosen)):
            in_region = [key for key in kept if str(regions[key[0]]) == name]
            beyond = sum(1 for key in in_region if exact.get(key, (np.inf,))[0] > 1.1 * r0)
            far_by_region[name] = 100.0 * beyond / max(1, len(in_region))
    return {
        "kept_beyond_1.1r0_percent": 100.0 * far / max(1, len(kept)),
        "kept_beyond_1.1r0_percent_by_region": far_by_region,
        "true_dropped_percent": 100.0 * dropped / max(1, len(true)),
        "radius_median_percent_r0": 100.0 * float(np.median(radius_error)),
        "radius_p95_percent_r0": 100.0 * float(np.percentile(radius_error, 95)),
        "angle_p95_rad": float(np.percentile(angle_error, 95)) if angle_error else None,
        "angle_p95_rad_by_region": {name: float(np.percentile(e, 95)) for name, e in sorted(region_errors.items())},
    }


def interior_vertices(surface: Surface, r0: float) -> np.ndarray:
    """Vertices farther than ``r0`` (Euclidean) from every boundary vertex (all of them on a closed mesh)."""
    edges = np.sort(
        np.concatenate([surface.faces[:, [0, 1]], surface.faces[:, [1, 2]], surface.faces[:, [2, 0]]]), axis=1
    )
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    boundary = np.unique(unique[counts == 1])
    if len(boundary) == 0:
        return np.arange(surface.n_vertices)
    distance, _ = cKDTree(surface.vertices[boundary]).query(surface.vertices)
    return np.flatnonzero(distance > r0)


def fit_residuals(operator, field_at_samples, field_at_vertices, vertices) -> np.ndarray:
    """Per vertex ``‖B a − f‖ / ‖f − f(p)‖`` over its patch samples."""
    coefficients = (operator.matrix @ field_at_vertices).reshape(operator.n_vertices, operator.k)[vertices]
    index = operator.patch_sample_index[vertices]
    values = np.where(index >= 0, field_at_samples[np.maximum(index, 0)], 0.0)
    fitted = np.einsum("vnk,vk->vn", operator.patch_basis[vertices], coefficients)
    variation = np.where(index >= 0, values - field_at_vertices[vertices, None], 0.0)
    residual = np.where(index >= 0, fitted - values, 0.0)
    return np.linalg.norm(residual, axis=1) / np.maximum(np.linalg.norm(variation, axis=1), 1e-300)


def patch_fit(surface, polar, samples, config, seed, centres=None) -> dict:
    """The patch-fit columns (module docstring) on the coordinates ``polar``, scored on the interior
    vertices; with ``centres`` also under ``"on_centres"``, scored on the interior ones among them (the same
    operators, so a backend's fit compares with the exact coordinates' fit on the same vertices)."""
    operator = assemble_operator(
        polar.center, polar.sample, polar.radius, polar.angle, polar.frames, samples.interpolation, config
    )
    high = assemble_operator(
        polar.center,
        polar.sample,
        polar.radius,
        polar.angle,
        polar.frames,
        samples.interpolation,
        PatchConfig(**{**config.to_dict(), "n_max": 8}),
    )
    direction = np.random.default_rng(seed).normal(size=3)
    field = surface.vertices @ (direction / np.linalg.norm(direction))
    at_samples = samples.interpolation @ field

    def columns(inside):
        coefficients = (operator.matrix @ np.ones(surface.n_vertices)).reshape(-1, operator.k)[inside]
        piston = np.sqrt(np.pi)  # ∫ Z_0 over the unit disk for f = 1
        piston_error = np.abs(coefficients[:, 0] - piston) / piston
        others = np.abs(coefficients[:, 1:]).max(axis=1) / np.abs(coefficients[:, 0])
        residual = fit_residuals(operator, at_samples, field, inside)
        residual_high = fit_residuals(high, at_samples, field, inside)
        counts = (operator.patch_sample_index[inside] >= 0).sum(axis=1)
        return {
            "vertices_scored": int(len(inside)),
            "samples_per_patch_median": float(np.median(counts)),
            "piston_error_p95_percent": 100.0 * float(np.percentile(piston_error, 95)),
            "other_coefficients_p95_percent_of_piston": 100.0 * float(np.percentile(others, 95)),
            "linear_residual_median_percent": 100.0 * float(np.median(residual)),
            "linear_residual_p95_percent": 100.0 * float(np.percentile(residual, 95)),
            "linear_residual_nmax8_median_percent": 100.0 * float(np.median(residual_high)),
        }

    inside = interior_vertices(surface, config.r0)
    result = columns(inside)
    if centres is not None:
        result["on_centres"] = columns(np.intersect1d(inside, centres))
    return result


def build_seconds(surface, config) -> tuple[float, float]:
    """Seconds of the first and of a second full operator build in this process."""
    times = []
    for _ in range(2):
        started = time.perf_counter()
        build_patch_operator(surface, config)
        times.append(time.perf_counter() - started)
    return times[0], times[1]


def cloud_of(surface, backend) -> Surface:
    """``surface``'s vertices as a point cloud: without normals (``cloud``) or with the mesh's
    (``cloud-normals``)."""
    normals = surface.vertex_normals() if backend == "cloud-normals" else None
    return Surface(surface.vertices, None, normals, name=surface.name)


def cloud_polar(cloud, samples, r0):
    """The ``cloud`` backends (module docstring): polar coordinates of ``samples`` by the front on the
    triangulation of the ``cloud``'s points, and those samples as seen on that triangulation."""
    mesh = mesh_from_cloud(cloud)
    # Nearest point among the triangles of the 8 nearest face centroids (no spatial index package needed).
    triangles = mesh.vertices[mesh.faces]
    _, candidate = cKDTree(triangles.mean(axis=1)).query(samples.points, k=8)
    points = np.repeat(samples.points, 8, axis=0)
    nearest = trimesh.triangles.closest_point(triangles[candidate.ravel()], points).reshape(-1, 8, 3)
    best = np.argmin(np.linalg.norm(nearest - samples.points[:, None], axis=2), axis=1)
    face = candidate[np.arange(len(best)), best]
    closest = nearest[np.arange(len(best)), best]
    corners = mesh.faces[face]
    barycentric = trimesh.triangles.points_to_barycentric(mesh.vertices[corners], closest)
    interpolation = scipy.sparse.csr_matrix(
        (barycentric.ravel(), corners.ravel(), np.arange(0, 3 * len(face) + 1, 3)), shape=(len(face), mesh.n_vertices)
    )
    on_cloud = SurfaceSamples(
        points=closest,
        normals=mesh.face_normals()[face],
        face_index=face.astype(np.int64),
        barycentric=barycentric,
        interpolation=interpolation,
    )
    return compute_polar(mesh, on_cloud, r0, backend="front"), on_cloud


def measure(surface, r0, n_samples, n_centres, backends, seed, regions=None) -> dict:
    config = PatchConfig(r0=r0, n_samples=n_samples, seed=seed)
    first, second = build_seconds(surface, config)  # first: before anything else in this process
    samples = sample_surface(surface, n_samples, seed=seed)
    frames = tangent_frames(surface)
    centres = np.sort(
        np.random.default_rng(seed).choice(surface.n_vertices, min(n_centres, surface.n_vertices), replace=False)
    )
    started = time.perf_counter()
    exact = exact_reference(surface, samples, frames, centres, r0)
    rows = {
        "surface": surface.name,
        "vertices": surface.n_vertices,
        "r0": r0,
        "samples": n_samples,
        "centres": int(len(centres)),
        "reference_seconds": time.perf_counter() - started,
        "backends": {},
        "build_first_seconds_per_1000_vertices": 1000.0 * first / surface.n_vertices,
        "build_second_seconds_per_1000_vertices": 1000.0 * second / surface.n_vertices,
    }
    for backend in backends:
        if backend.startswith("cloud"):
            polar, backend_samples = cloud_polar(cloud_of(surface, backend), samples, r0)
            cloud_first, cloud_second = build_seconds(cloud_of(surface, backend), config)
            timing = {
                "build_first_seconds_per_1000_vertices": 1000.0 * cloud_first / surface.n_vertices,
                "build_second_seconds_per_1000_vertices": 1000.0 * cloud_second / surface.n_vertices,
            }
        else:
            polar, backend_samples, timing = compute_polar(surface, samples, r0, backend=backend), samples, {}
        backend_config = PatchConfig(
            **{**config.to_dict(), "backend": "front" if backend.startswith("cloud") else backend}
        )
        rows["backends"][backend] = {
            "seconds_all_vertices": polar.seconds,
            **timing,
            **score(polar, exact, centres, r0, regions),
            **patch_fit(surface, polar, backend_samples, backend_config, seed, centres),
        }
    # The fit on exact coordinates (only the reference's centres have patches): what the patch-fit targets
    # can reach with perfect geodesics.
    rows["exact_fit_on_centres"] = patch_fit(surface, exact_polar(exact, frames, r0), samples, config, seed, centres)[
        "on_centres"
    ]
    return rows


def print_rows(row) -> None:
    print(
        f"\n{row['surface']}: {row['vertices']} vertices, r0 {row['r0']}, {row['samples']} samples, "
        f"{row['centres']} centres (exact reference {row['reference_seconds']:.0f} s); operator build (default "
        f"config) {row['build_first_seconds_per_1000_vertices']:.2f} s / 1000 vertices first, "
        f"{row['build_second_seconds_per_1000_vertices']:.2f} second"
    )
    print(
        f"{'backend':13} {'>1.1r0 %':>9} {'dropped %':>10} {'r med %':>8} {'r p95 %':>8} {'θ p95':>7} {'time s':>7}"
        f" {'piston p95 %':>13} {'others p95 %':>13} {'lin med %':>10} {'lin p95 %':>10} {'lin n8 %':>9}"
    )
    for name, b in row["backends"].items():
        angle = "-" if b["angle_p95_rad"] is None else f"{b['angle_p95_rad']:.3f}"
        print(
            f"{name:13} {b['kept_beyond_1.1r0_percent']:9.2f} {b['true_dropped_percent']:10.2f} "
            f"{b['radius_median_percent_r0']:8.3f} {b['radius_p95_percent_r0']:8.2f} {angle:>7} "
            f"{b['seconds_all_vertices']:7.2f} {b['piston_error_p95_percent']:13.4f} "
            f"{b['other_coefficients_p95_percent_of_piston']:13.4f} {b['linear_residual_median_percent']:10.2f} "
            f"{b['linear_residual_p95_percent']:10.2f} {b['linear_residual_nmax8_median_percent']:9.2f}"
        )
    for name, b in row["backends"].items():
        if "build_second_seconds_per_1000_vertices" in b:
            print(
                f"operator build ({name}): {b['build_first_seconds_per_1000_vertices']:.2f} s / 1000 vertices first, "
                f"{b['build_second_seconds_per_1000_vertices']:.2f} second"
            )
    for name, b in row["backends"].items():
        if b["kept_beyond_1.1r0_percent_by_region"]:
            print(
                f"kept beyond 1.1 r0 by region, % ({name}): "
                + ", ".join(
                    f"{region} {value:.2f}" for region, value in b["kept_beyond_1.1r0_percent_by_region"].items()
                )
            )
    for name, b in row["backends"].items():
        if b["angle_p95_rad_by_region"]:
            print(
                f"angle p95 by region ({name}): "
                + ", ".join(f"{region} {p95:.3f}" for region, p95 in b["angle_p95_rad_by_region"].items())
            )
    print(f"linear residual median on the {row['centres']} reference centres (interior ones), n_max 5 / 8:")
    fits = {
        **{name: b["on_centres"] for name, b in row["backends"].items()},
        "exact (MMP)": row["exact_fit_on_centres"],
    }
    for name, fit in fits.items():
        print(
            f"  {name:12} {fit['linear_residual_median_percent']:6.2f} % / {fit['linear_residual_nmax8_median_percent']:6.2f} %"
            f"  (piston p95 {fit['piston_error_p95_percent']:.2g} %)"
        )


def main() -> None:
    parser = arguments(__doc__)
    parser.add_argument("--mesh", type=Path, action="append", default=[], help="also measure this mesh")
    parser.add_argument("--area", type=float, default=15000.0)
    parser.add_argument("--r0", type=float, default=5.5)
    parser.add_argument("--samples", type=int, default=12000)
    parser.add_argument("--centres", type=int, default=100)
    parser.add_argument("--backends", nargs="+", default=["fast", "front", "cloud", "cloud-normals"])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-body", action="store_true", help="only the meshes passed with --mesh")
    add_out(parser, SPEED_RESULTS / "bench_geodesics")
    args = parser.parse_args()
    surfaces = ([] if args.no_body else [body_surface(args.seed, area=None)]) + [
        (load_surface(path), None) for path in args.mesh
    ]
    results = []
    for surface, regions in surfaces:
        surface, _ = normalize_area(surface, args.area)
        results.append(measure(surface, args.r0, args.samples, args.centres, args.backends, args.seed, regions))
        print_rows(results[-1])
    write_json(result_file(args.out, ".json"), {"surfaces": results})


if __name__ == "__main__":
    main()
