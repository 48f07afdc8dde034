"""Benchmark of the patch operator: build time and accuracy of each polar backend against exact geodesics,
and the operator's apply time.

Prints a table and writes ``benchmarks/speed/results/bench_operator.json`` (``--out``).

Surfaces:
* a posed human body generated with ``anny`` (``zernet.data.bodies``, the FAUST-sized topology, 6,890
  vertices, fingers, armpits and crotch) at area 15000, r0 = 5.5, 12,000 samples;
* the aneurysm meshes of ``--aneurysms DIR`` (default ``data/aneurysm``, your copy) when that folder
  exists (area 100, r0 = 0.6 as in the paper's regression experiment, 12,000 samples).

Accuracy is measured against exact polyhedral geodesics (MMP, :mod:`zernet.geometry.polar.exact`, the samples
inserted as vertices) on ``--centres`` random vertices, with the columns of ``bench_geodesics``: kept
pairs from beyond 1.1 r0, true pairs dropped, radius error median / p95 (% of r0), angle error p95 (rad,
r > 0.1 r0, after each centre's constant offset). The build time is the whole
:func:`~zernet.operators.build_patch_operator` (sampling, polar coordinates, fit, assembly), best of
``repeats``. The apply time is measured on the default operator of the body.

Cache formats (``--formats`` runs only these rows, at ``--threads`` threads, 2 by default): the body with the
shipped FAUST patch settings (``configs/faust_single_scale.yaml``) stored as cache format 4 (the float32 CSR
matrix and its transpose, rebuilt here from the expanded matrix) and as format 6 (the patches' sample
geometry on disk, fitted again into vertex pairs, :mod:`zernet.operators.pairs`, when read) in each
precision: bytes on disk and held for a step, build time, read time, one convolution layer's
forward+backward (64 -> 128 channels) and its output's difference from format 4's.

The procedural :func:`mannequin` (capsules, no limb-torso junctions; it cannot show the far-side failure
of folds) is kept as the stand-in operator of ``bench_layers --real``.

Usage::

    .venv/bin/python -m benchmarks.speed.bench_operator                 # fast and front
    .venv/bin/python -m benchmarks.speed.bench_operator --backends fast front accurate --centres 50
    .venv/bin/python -m benchmarks.speed.bench_operator --quick         # fewer centres and repeats
    .venv/bin/python -m benchmarks.speed.bench_operator --formats       # only the cache formats
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import yaml

from benchmarks.harness import (
    BODY_AREA,
    REPO,
    SPEED_RESULTS,
    add_out,
    add_threads,
    arguments,
    body_surface,
    result_file,
    write_json,
)
from benchmarks.speed.bench_geodesics import exact_reference, score
from zernet.geometry import Surface, compute_polar, load_surface, normalize_area, sample_surface, tangent_frames
from zernet.operators import PatchConfig, PatchOperator, build_patch_operator

ANEURYSMS = Path("data/aneurysm")  # your copy of the aneurysm data set
FAUST_RECIPE = REPO / "configs" / "faust_single_scale.yaml"


# ====================================================================== the procedural body
def _capsule(radius: float, length: float, edge: float) -> tuple[np.ndarray, np.ndarray]:
    """Closed capsule along z centred at the origin: staggered rings ~``edge`` apart, one vertex per pole."""
    around = max(6, int(round(2 * np.pi * radius / edge)))
    cap = np.pi * radius / 2
    total = 2 * cap + length
    n_rings = max(3, int(round(total / (edge * 0.866))))
    s = np.linspace(0, total, n_rings + 2)[1:-1]  # arclength along the profile, poles excluded
    lower, upper = s < cap, s > cap + length
    z = np.where(
        lower,
        -length / 2 - radius * np.cos(s / radius),
        np.where(upper, length / 2 + radius * np.cos((total - s) / radius), s - cap - length / 2),
    )
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


def bench_surface(
    surface: Surface, config: PatchConfig, backends, n_centres: int, n_jobs: int, repeats: int, seed: int
) -> dict:
    """Build time and accuracy against exact geodesics of each backend on one surface."""
    samples = sample_surface(surface, config.n_samples, seed=config.seed)
    frames = tangent_frames(surface)
    centres = np.sort(
        np.random.default_rng(seed).choice(surface.n_vertices, min(n_centres, surface.n_vertices), replace=False)
    )
    started = time.perf_counter()
    exact = exact_reference(surface, samples, frames, centres, config.r0)
    row = {
        "name": surface.name,
        "vertices": surface.n_vertices,
        "area": surface.area,
        "r0": config.r0,
        "samples": config.n_samples,
        "centres": int(len(centres)),
        "reference_s": time.perf_counter() - started,
    }
    for backend in backends:
        backend_config = PatchConfig(**{**config.to_dict(), "backend": backend})
        build, _ = _best_time(
            lambda config=backend_config: build_patch_operator(surface, config, n_jobs=n_jobs),
            1 if backend == "accurate" else repeats,
        )
        polar = compute_polar(surface, samples, config.r0, backend=backend, n_jobs=n_jobs)
        row[backend] = {"operator_build_s": build, "polar_s": polar.seconds, **score(polar, exact, centres, config.r0)}
    return row


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


# ====================================================================== cache formats (issue 50)
def faust_patch_config(precision: str) -> PatchConfig:
    """The shipped FAUST recipe's patch settings (``configs/faust_single_scale.yaml``) with ``precision``."""
    scale = yaml.safe_load(FAUST_RECIPE.read_text())["patch"]["scales"][0]
    return PatchConfig(**{**scale, "precision": precision})


def _layer_time(conv, operator, x, repeats: int) -> float:
    """Best forward+backward time of one convolution layer (gradients to its input too)."""

    def step():
        conv.zero_grad()
        x.grad = None
        conv(x, operator).square().mean().backward()

    step()  # compiles the kernels, builds what is built once
    return _best_time(step, repeats)[0]


def bench_formats(surface: Surface, precisions, width: int, repeats: int) -> dict:
    """Format 4 (the float32 CSR matrix and its stored transpose, multiplied by torch) against format 6 (the
    sample geometry in the file, vertex pairs in memory, :mod:`zernet.operators.pairs`) in each precision, on
    one surface with the shipped FAUST settings: bytes per shape on disk and held in memory, build time, the
    time to read a cached file (median of three), one convolution layer's forward+backward
    (``width`` -> ``2 width`` channels) and its largest output difference from format 4's, relative to the
    largest output. Format 4 is rebuilt from the expanded matrix: the file it wrote (its arrays packed as
    it packed them) and the tensors its layers held (:class:`zernet.nn.reference.MatrixOperator`, the same
    torch CSR products with a stored transpose)."""
    from zernet.nn import ZernikeConv
    from zernet.nn.reference import MatrixOperator
    from zernet.operators.cache import pack_arrays, sparse_to_arrays

    torch.manual_seed(0)
    conv = ZernikeConv(width, 2 * width)
    order = conv.operator_basis_order()
    x = torch.randn(surface.n_vertices, width, requires_grad=True)
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        started = time.perf_counter()
        fitted = build_patch_operator(surface, faust_patch_config("float32"))  # the fit, no cache
        fit_s = time.perf_counter() - started
        matrix = fitted.matrix.astype(np.float32)  # (not timed: format 4's fit wrote this matrix directly)
        started = time.perf_counter()
        transpose = matrix.T.tocsr()
        transpose.sort_indices()
        arrays = {
            "frames": fitted.frames,
            "patch_sample_index": fitted.patch_sample_index,
            "patch_radius": fitted.patch_radius,
            "patch_angle": fitted.patch_angle,
            **sparse_to_arrays("matrix", matrix),
            **sparse_to_arrays("transpose", transpose),
            **sparse_to_arrays("interpolation", fitted.interpolation),
        }
        old_file = Path(folder) / "format4.zop"
        old_file.write_bytes(pack_arrays(arrays, "format 4"))
        old_build_s = fit_s + time.perf_counter() - started
        old = MatrixOperator(matrix, fitted.k).to("cpu", [order] if order else [])
        held = old._tensors(torch.float32, torch.device("cpu"), order)
        old_bytes = sum(
            t.numel() * t.element_size() for m in held for t in (m.crow_indices(), m.col_indices(), m.values())
        )
        with torch.no_grad():
            reference = conv(x, old)
        rows.append(
            {
                "format": "4: float32 CSR + transpose",
                "disk_mb": old_file.stat().st_size / 1e6,
                "memory_mb": old_bytes / 1e6,
                "build_s": old_build_s,
                "read_s": None,
                "layer_ms": 1e3 * _layer_time(conv, old, x, repeats),
                "layer_relative_difference": 0.0,
            }
        )
        del old, held
        for precision in precisions:
            started = time.perf_counter()
            operator = build_patch_operator(surface, faust_patch_config(precision), cache_dir=folder)
            build_s = time.perf_counter() - started
            read_s = []
            for _ in range(3):
                started = time.perf_counter()
                PatchOperator.load(operator.cache_file)
                read_s.append(time.perf_counter() - started)
            operator.to("cpu", [order] if order else [])
            with torch.no_grad():
                out = conv(x, operator)
            rows.append(
                {
                    "format": f"6: geometry, {precision} pairs",
                    "disk_mb": operator.cache_file.stat().st_size / 1e6,
                    "memory_mb": operator.prepared_nbytes / 1e6,
                    "build_s": build_s,
                    "read_s": float(np.median(read_s)),
                    "layer_ms": 1e3 * _layer_time(conv, operator, x, repeats),
                    "layer_relative_difference": float((out - reference).abs().max() / reference.abs().max()),
                }
            )
    return {
        "vertices": surface.n_vertices,
        "pairs": int(operator.pairs.n_pairs),
        "nnz_format_4": int(matrix.nnz),
        "width": width,
        "threads": torch.get_num_threads(),
        "rows": rows,
    }


def print_formats(result: dict) -> None:
    print(
        f"cache formats, N={result['vertices']}, {result['pairs']} pairs ({result['nnz_format_4']} non-zeros), "
        f"conv {result['width']} -> {2 * result['width']}, {result['threads']} threads"
    )
    header = (
        f"{'format':<28}{'disk MB':>9}{'memory MB':>10}{'build s':>9}{'read s':>8}{'layer ms':>10}{'rel. diff':>11}"
    )
    print(header)
    print("-" * len(header))
    for row in result["rows"]:
        print(
            f"{row['format']:<28}{row['disk_mb']:>9.1f}{row['memory_mb']:>10.1f}{row['build_s']:>9.2f}"
            f"{'-' if row['read_s'] is None else format(row['read_s'], '.2f'):>8}{row['layer_ms']:>10.0f}{row['layer_relative_difference']:>11.1e}"
        )


# ====================================================================== main
def print_table(rows, backends) -> None:
    header = (
        f"{'surface':<26}{'N':>6}{'r0':>5}  {'backend':<9}{'build s':>8}{'polar s':>8}{'>1.1r0 %':>9}"
        f"{'drop %':>7}{'r med %':>8}{'r p95 %':>8}{'θ p95':>7}"
    )
    print(header)
    print("-" * len(header))
    for row in rows:
        for i, backend in enumerate(backends):
            b = row[backend]
            label = f"{row['name'][:25]:<26}{row['vertices']:>6}{row['r0']:>5}" if i == 0 else " " * 37
            angle = "-" if b["angle_p95_rad"] is None else f"{b['angle_p95_rad']:.3f}"
            print(
                f"{label}  {backend:<9}{b['operator_build_s']:>8.2f}{b['polar_s']:>8.2f}{b['kept_beyond_1.1r0_percent']:>9.2f}"
                f"{b['true_dropped_percent']:>7.2f}{b['radius_median_percent_r0']:>8.3f}{b['radius_p95_percent_r0']:>8.2f}{angle:>7}"
            )


def main(argv: list[str] | None = None) -> dict:
    parser = arguments(__doc__)
    parser.add_argument("--quick", action="store_true", help="fewer centres and repeats, one aneurysm")
    parser.add_argument("--backends", nargs="+", default=["fast", "front"], help="fast, front, accurate")
    parser.add_argument("--centres", type=int, default=100, help="centre vertices scored against exact geodesics")
    parser.add_argument("--jobs", type=int, default=2, help="processes for the accurate backend")
    parser.add_argument("--aneurysms", type=Path, default=ANEURYSMS, help="folder of the aneurysm .mat files")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--formats", action="store_true", help="only the cache formats: format 4 against the vertex pairs"
    )
    add_threads(parser, 2)
    add_out(parser, SPEED_RESULTS / "bench_operator")
    args = parser.parse_args(argv)

    repeats = 1 if args.quick else 3
    centres = min(args.centres, 30) if args.quick else args.centres
    body, _ = body_surface(args.seed, BODY_AREA)
    torch.set_num_threads(args.threads)
    formats = bench_formats(body, ("float32", "float16", "bfloat16"), 64, repeats)
    print_formats(formats)
    if args.formats:
        result = {"quick": args.quick, "formats": formats}
        write_json(result_file(args.out.with_name(args.out.name + "_formats"), ".json"), result)
        return result
    body_config = PatchConfig(r0=5.5, n_samples=12000)
    rows = [bench_surface(body, body_config, args.backends, centres, args.jobs, repeats, args.seed)]
    if args.aneurysms.is_dir():
        files = sorted(args.aneurysms.glob("*.mat"), key=lambda p: p.stat().st_size)
        chosen = files[:1] if args.quick else [files[0], files[len(files) // 2], files[-1]]
        for path in chosen:
            surface, _ = normalize_area(load_surface(path), 100.0)
            rows.append(
                bench_surface(
                    surface, PatchConfig(r0=0.6, n_samples=12000), args.backends, centres, args.jobs, repeats, args.seed
                )
            )
    apply = bench_apply(body, body_config, 128, 5 if args.quick else 10)
    print_table(rows, args.backends)
    print()
    print(
        f"apply N={apply['vertices']} k={apply['k']} d={apply['d']} float32, nnz={apply['nnz']} ({apply['nnz_per_row']:.1f}/row): "
        f"forward {apply['forward_ms']:.1f} ms, forward+backward {apply['forward_backward_ms']:.1f} ms "
        f"(torch.sparse.mm COO: {apply['torch_sparse_mm_coo_forward_backward_ms']:.1f} ms)"
    )
    result = {"quick": args.quick, "surfaces": rows, "apply": apply, "formats": formats}
    write_json(result_file(args.out, ".json"), result)
    return result


if __name__ == "__main__":
    main()
