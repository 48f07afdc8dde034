"""How close the generated bodies come to real people: each real FAUST training scan against its nearest
generated body, for the older pose mode (``varied``) and the wider one (``wide``), the same number of each.

A generated body and a FAUST registration do not share a vertex order (the ``faust`` topology has FAUST's
vertex count, not its vertices), so shapes are compared as surfaces:

1. every shape is centred (area-weighted) and scaled to unit area, then sampled by ``--points`` points
   uniform on its surface (seeded); both are upright and face the same way (y up, facing +z);
2. for each scan, every body is scored by the symmetric mean closest-point distance of their samples
   (a Chamfer distance) as they stand; the ``--candidates`` closest are then moved by a rigid fit (ICP,
   rotation and translation, ``--icp-steps`` steps) and scored again; the best is the scan's nearest body;
3. the distance is in hundredths of the square root of the surface's area (x100 / sqrt(area), as the
   matching errors are), per scan, and per body part: each scan point's distance goes to the part of the
   nearest body's point closest to it (the generated body's own labels: no FAUST label is read).

Reported per mode: the median, mean and worst scan, each FAUST pose (scan ``XXX`` is person ``XXX // 10``
in pose ``XXX % 10``) at its median over people, each part's median, and the share of the bodies whose
surface runs into itself (generalised winding number above 1 at some vertex: a vertex inside the body
elsewhere), on the first ``--intersection-bodies`` bodies of each mode. Only scans 000-079 (people 0-7)
are read, never FAUST's test people; only figures are written, to
``benchmarks/experiments/results/body_coverage.{json,md}``.

    .venv/bin/python -m benchmarks.experiments.body_coverage --data ~/data/MPI-FAUST --bodies 200 --threads 1
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from benchmarks.harness import (
    CACHE,
    EXPERIMENT_RESULTS,
    add_data,
    add_out,
    add_threads,
    arguments,
    markdown_table,
    result_file,
    write_json,
    write_markdown,
)
from zernet.data.segmentation import HUMAN_PART_NAMES

MODES = ("varied", "wide")
TRAINING_SCANS = range(80)  # people 0-7; 080-099 are FAUST's test people and are never read


def read_scans(root: Path) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Scan number -> (vertices, faces) of FAUST's training registrations 000-079 under ``root``."""
    import trimesh

    folder = root / "training" / "registrations"
    scans = {}
    for number in TRAINING_SCANS:
        path = folder / f"tr_reg_{number:03d}.ply"
        if not path.is_file():
            raise SystemExit(f"{path} is missing: --data is the folder holding training/registrations")
        mesh = trimesh.load(path, process=False)
        scans[number] = (np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64))
    return scans


def surface_samples(
    vertices: np.ndarray, faces: np.ndarray, count: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """(``count`` points uniform on the surface, centred and scaled to unit area; the face of each)."""
    corners = vertices[faces]
    areas = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    centroid = (areas[:, None] * corners.mean(1)).sum(0) / areas.sum()
    chosen = rng.choice(len(faces), size=count, p=areas / areas.sum())
    u, v = rng.uniform(size=(2, count))
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    triangle = corners[chosen]
    points = (
        triangle[:, 0] + u[:, None] * (triangle[:, 1] - triangle[:, 0]) + v[:, None] * (triangle[:, 2] - triangle[:, 0])
    )
    return (points - centroid) / np.sqrt(areas.sum()), chosen


def chamfer(scan: np.ndarray, scan_tree: cKDTree, body: np.ndarray, body_tree: cKDTree) -> float:
    """Symmetric mean closest-point distance between two sample sets."""
    return 0.5 * (body_tree.query(scan)[0].mean() + scan_tree.query(body)[0].mean())


def rigid_fit(scan: np.ndarray, scan_tree: cKDTree, body: np.ndarray, steps: int) -> np.ndarray:
    """``body`` moved onto ``scan`` by ICP (rotation and translation; both ways' closest points each step)."""
    moved = body
    for _ in range(steps):
        body_tree = cKDTree(moved)
        source = np.concatenate([moved, moved[body_tree.query(scan)[1]]])
        target = np.concatenate([scan[scan_tree.query(moved)[1]], scan])
        source_mean, target_mean = source.mean(0), target.mean(0)
        u, _, vt = np.linalg.svd((source - source_mean).T @ (target - target_mean))
        rotation = (u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt).T
        moved = (moved - source_mean) @ rotation.T + target_mean
    return moved


def inside_vertices(vertices: np.ndarray, faces: np.ndarray, chunk: int = 256) -> int:
    """Vertices of a closed surface that lie inside it elsewhere: generalised winding number above 1 (a
    vertex on the surface has 1/2 from its own sheet; one more whole turn means another part encloses it)."""
    corners = vertices[faces]
    count = 0
    for start in range(0, len(vertices), chunk):
        a, b, c = (corners[None, :, k] - vertices[start : start + chunk, None] for k in range(3))
        la, lb, lc = (np.linalg.norm(x, axis=2) for x in (a, b, c))
        numerator = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
        denominator = (
            la * lb * lc
            + np.einsum("pfi,pfi->pf", a, b) * lc
            + np.einsum("pfi,pfi->pf", b, c) * la
            + np.einsum("pfi,pfi->pf", c, a) * lb
        )
        winding = np.abs(2.0 * np.arctan2(numerator, denominator).sum(1) / (4.0 * np.pi))
        count += int((winding > 1.0).sum())
    return count


def nearest_bodies(scan_points, bodies, candidates: int, icp_steps: int) -> dict:
    """The nearest body to one scan among ``bodies`` (each (points, tree, parts)), and its distances."""
    scan, scan_tree = scan_points
    rough = np.array([chamfer(scan, scan_tree, points, tree) for points, tree, _ in bodies])
    best = None
    for index in np.argsort(rough)[:candidates]:
        points, _, parts = bodies[index]
        moved = rigid_fit(scan, scan_tree, points, icp_steps)
        moved_tree = cKDTree(moved)
        distance = chamfer(scan, scan_tree, moved, moved_tree)
        if best is None or distance < best["distance"]:
            scan_to_body, nearest = moved_tree.query(scan)
            best = {
                "body": int(index),
                "distance": float(distance),
                "scan_to_body": scan_to_body,
                "parts": parts[nearest],
            }
    per_part = {
        HUMAN_PART_NAMES[part]: float(best["scan_to_body"][best["parts"] == part].mean())
        for part in np.unique(best["parts"])
    }
    return {
        "body": best["body"],
        "distance": 100.0 * best["distance"],
        "parts": {k: 100.0 * v for k, v in per_part.items()},
    }


def main() -> None:
    parser = arguments(__doc__)
    add_data(parser, None, "FAUST's folder (holding training/registrations/tr_reg_000.ply ...); scans 000-079 only")
    add_out(parser, EXPERIMENT_RESULTS / "body_coverage")
    add_threads(parser, 1)
    parser.add_argument("--bodies", type=int, default=200, help="generated bodies per pose mode (default 200)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the generated bodies (default 0)")
    parser.add_argument("--points", type=int, default=1000, help="surface samples per shape (default 1000)")
    parser.add_argument("--candidates", type=int, default=5, help="bodies fitted by ICP per scan (default 5)")
    parser.add_argument("--icp-steps", type=int, default=8, help="ICP steps per fit (default 8)")
    parser.add_argument(
        "--intersection-bodies", type=int, default=10, help="bodies per mode checked for self-intersection"
    )
    parser.add_argument("--cache-dir", type=Path, default=CACHE, help="zernet cache of generated bodies")
    args = parser.parse_args()
    if args.data is None:
        parser.error("--data is required")
    import torch

    from zernet.data.bodies import BodyGenerator

    torch.set_num_threads(args.threads)
    started = time.perf_counter()
    rng = np.random.default_rng(0)
    scans = read_scans(args.data.expanduser())
    scan_points = {}
    for number, (vertices, faces) in scans.items():
        points, _ = surface_samples(vertices, faces, args.points, rng)
        scan_points[number] = (points, cKDTree(points))
    modes = {}
    for mode in MODES:
        generator = BodyGenerator("faust", mode, args.seed, args.cache_dir)
        bodies, inside = [], []
        for index in range(args.bodies):
            body = generator.body(index)
            points, chosen = surface_samples(body.vertices, body.faces, args.points, rng)
            bodies.append((points, cKDTree(points), body.parts[body.faces[chosen, 0]]))
            if index < args.intersection_bodies:
                inside.append(inside_vertices(body.vertices, body.faces))
        nearest = {
            number: nearest_bodies(scan_points[number], bodies, args.candidates, args.icp_steps) for number in scans
        }
        distances = np.array([entry["distance"] for entry in nearest.values()])
        worst = sorted(nearest, key=lambda number: -nearest[number]["distance"])[:5]
        modes[mode] = {
            "median": float(np.median(distances)),
            "mean": float(distances.mean()),
            "worst": float(distances.max()),
            "worst_scans": {f"{number:03d}": nearest[number]["distance"] for number in worst},
            "per_pose_median": {str(pose): float(np.median(distances[pose::10])) for pose in range(10)},
            "per_part_median": {
                name: float(np.median([entry["parts"][name] for entry in nearest.values() if name in entry["parts"]]))
                for name in HUMAN_PART_NAMES
            },
            "distinct_nearest_bodies": len({entry["body"] for entry in nearest.values()}),
            "self_intersecting_bodies": int(np.count_nonzero(inside)),
            "intersection_bodies": len(inside),
            "median_inside_vertices": float(np.median(inside)) if inside else None,
            "per_scan": {f"{number:03d}": round(entry["distance"], 3) for number, entry in nearest.items()},
        }
        print(f"{mode}: median {modes[mode]['median']:.2f}, worst {modes[mode]['worst']:.2f}")
    result = {
        "what": "each real FAUST training scan (000-079) to its nearest generated body: symmetric mean closest-"
        "point distance x100 / sqrt(area) after a rigid fit, both at unit area",
        "bodies_per_mode": args.bodies,
        "seed": args.seed,
        "points": args.points,
        "candidates": args.candidates,
        "icp_steps": args.icp_steps,
        "modes": modes,
        "seconds": round(time.perf_counter() - started, 1),
    }
    write_json(result_file(args.out, ".json"), result)
    write_markdown(result_file(args.out, ".md"), report(result))


def report(result: dict) -> list[str]:
    modes = result["modes"]
    lines = [
        "# Coverage of real poses by generated bodies",
        "",
        f"Each of FAUST's 80 training scans (people 0-7) against its nearest of {result['bodies_per_mode']} "
        "generated bodies per pose mode (`faust` topology, seed "
        f"{result['seed']}): symmetric mean closest-point distance of {result['points']} surface samples each, "
        f"x100 / sqrt(area), after a rigid fit (ICP on the {result['candidates']} closest as they stand). "
        "Lower is closer; 0 would be the same surface.",
        "",
    ]
    lines += markdown_table(
        [
            "pose mode",
            "median scan",
            "mean",
            "worst scan",
            "worst scans",
            "distinct nearest bodies",
            "self-intersecting bodies",
        ],
        [
            [
                mode,
                f"{entry['median']:.2f}",
                f"{entry['mean']:.2f}",
                f"{entry['worst']:.2f}",
                ", ".join(f"{name} ({value:.2f})" for name, value in list(entry["worst_scans"].items())[:3]),
                entry["distinct_nearest_bodies"],
                f"{entry['self_intersecting_bodies']} of {entry['intersection_bodies']}",
            ]
            for mode, entry in modes.items()
        ],
    )
    lines += ["", "Per FAUST pose (scan number mod 10), median over the 8 people:", ""]
    lines += markdown_table(
        ["pose mode", *(str(pose) for pose in range(10))],
        [
            [mode, *(f"{entry['per_pose_median'][str(pose)]:.2f}" for pose in range(10))]
            for mode, entry in modes.items()
        ],
    )
    lines += [
        "",
        "Per body part (each scan point's distance, by the part of the nearest body's closest point), median over scans:",
        "",
    ]
    lines += markdown_table(
        ["pose mode", *HUMAN_PART_NAMES],
        [
            [mode, *(f"{entry['per_part_median'][name]:.2f}" for name in HUMAN_PART_NAMES)]
            for mode, entry in modes.items()
        ],
    )
    lines += ["", f"{result['seconds']:.0f} s in all."]
    return lines


if __name__ == "__main__":
    main()
