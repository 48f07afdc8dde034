"""How close the generated bodies come to real people: each real FAUST training scan against its nearest
generated body, for the older pose mode (``varied``) and the wider one (``wide``), the same number of each.

A generated body and a FAUST registration do not share a vertex order (the ``faust`` topology has FAUST's
vertex count, not its vertices: vertex to vertex after a Procrustes fit, a rest body and scan 000 are 41
apart in the unit below, surface to surface 8), so shapes are compared as surfaces:

1. every shape is centred (area-weighted) and scaled to unit area; ``--points`` points uniform on its
   surface are measured from, ``--dense`` others measured to (so that a distance reads the surface, not
   the spacing of a few samples); both stand upright facing the same way (y up, facing +z);
2. for each scan, every body is scored by the symmetric mean closest-point distance (a Chamfer distance)
   as they stand; the ``--candidates`` closest are then moved by a rigid fit (ICP, rotation and
   translation, ``--icp-steps`` steps) and scored again; the best is the scan's nearest body;
3. distances are in hundredths of the square root of the surface's area (x100 / sqrt(area), as the
   matching errors are), per scan, and per body part: each scan point's distance goes to the part of the
   nearest body's point closest to it (the generated body's own labels: no FAUST label is read).

For scale, the same distance from each scan to the nearest of the other 7 people in the same pose (what a
perfect pose with another person's shape gives), and to a second sampling of itself (the floor the sampling
leaves). Reported per mode: the median, mean and worst scan, each FAUST pose (scan ``XXX`` is person
``XXX // 10`` in pose ``XXX % 10``) at its median over people, each part's median, and the share of bodies
whose surface runs into itself (generalised winding number above 1 at some vertex: a vertex inside the body
elsewhere), on the first ``--intersection-bodies`` bodies of each mode. Only scans 000-079 (people 0-7) are
read, never FAUST's test people; only figures are written, to
``benchmarks/experiments/results/body_coverage.{json,md}``.

    .venv/bin/python -m benchmarks.experiments.body_coverage --data ~/data/MPI-FAUST --bodies 200 --threads 1
"""

from __future__ import annotations

import time
from dataclasses import dataclass
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


@dataclass(frozen=True)
class SampledSurface:
    """A shape at unit area, centred: ``queries`` measured from, ``dense`` points (and their ``tree``) measured
    to, so a distance reads the surface, not the spacing of a few samples; ``parts`` of the dense points."""

    queries: np.ndarray
    dense: np.ndarray
    tree: cKDTree
    parts: np.ndarray | None = None


def sample_surface(
    vertices: np.ndarray, faces: np.ndarray, queries: int, dense: int, rng, labels: np.ndarray | None = None
) -> SampledSurface:
    """Points uniform on the surface (area-weighted), the shape centred and scaled to unit area; with
    per-vertex ``labels``, the label of each dense point's triangle (its first corner)."""
    corners = vertices[faces]
    areas = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    centroid = (areas[:, None] * corners.mean(1)).sum(0) / areas.sum()
    unit = (corners - centroid) / np.sqrt(areas.sum())

    def draw(count):
        chosen = rng.choice(len(faces), size=count, p=areas / areas.sum())
        u, v = rng.uniform(size=(2, count))
        flip = u + v > 1.0
        u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
        triangle = unit[chosen]
        return triangle[:, 0] + u[:, None] * (triangle[:, 1] - triangle[:, 0]) + v[:, None] * (
            triangle[:, 2] - triangle[:, 0]
        ), chosen

    query_points, _ = draw(queries)
    dense_points, chosen = draw(dense)
    parts = None if labels is None else labels[faces[chosen, 0]]
    return SampledSurface(query_points, dense_points, cKDTree(dense_points), parts)


def distances(scan: SampledSurface, body: SampledSurface, rotation: np.ndarray, shift: np.ndarray) -> tuple:
    """(scan points to the moved body, the nearest body point of each, the moved body's points to the scan)
    with the body moved by ``x -> rotation x + shift``: the scan's points are moved back instead."""
    to_body, nearest = body.tree.query((scan.queries - shift) @ rotation)
    to_scan, _ = scan.tree.query(body.queries @ rotation.T + shift)
    return to_body, nearest, to_scan


def chamfer(scan: SampledSurface, body: SampledSurface) -> float:
    """Symmetric mean closest-point distance of the two as they stand."""
    to_body, _, to_scan = distances(scan, body, np.eye(3), np.zeros(3))
    return 0.5 * (to_body.mean() + to_scan.mean())


def rigid_fit(scan: SampledSurface, body: SampledSurface, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """(rotation, shift) moving ``body`` onto ``scan``: ICP on both ways' closest points, from as they stand."""
    rotation, shift = np.eye(3), np.zeros(3)
    for _ in range(steps):
        _, nearest_on_body = body.tree.query((scan.queries - shift) @ rotation)
        _, nearest_on_scan = scan.tree.query(body.queries @ rotation.T + shift)
        source = np.concatenate([body.dense[nearest_on_body], body.queries])
        target = np.concatenate([scan.queries, scan.dense[nearest_on_scan]])
        source_mean, target_mean = source.mean(0), target.mean(0)
        u, _, vt = np.linalg.svd((source - source_mean).T @ (target - target_mean))
        rotation = vt.T @ np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))]) @ u.T
        shift = target_mean - rotation @ source_mean
    return rotation, shift


def inside_vertices(vertices: np.ndarray, faces: np.ndarray, chunk: int = 128) -> int:
    """Vertices of a closed surface that lie inside it elsewhere: generalised winding number above 1 (a
    vertex on the surface has 1/2 from its own sheet; one more whole turn means another part encloses it)."""
    corners = vertices[faces].astype(np.float32)
    count = 0
    for start in range(0, len(vertices), chunk):
        a, b, c = (corners[None, :, k] - vertices[start : start + chunk, None].astype(np.float32) for k in range(3))
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


def nearest(scan: SampledSurface, candidates_of: list[SampledSurface], candidates: int, icp_steps: int) -> dict:
    """The nearest of ``candidates_of`` to one scan after a rigid fit (the ``candidates`` closest as they
    stand are fitted), its distance x100 and, with part labels, the scan points' distance per part."""
    rough = np.array([chamfer(scan, other) for other in candidates_of])
    best = None
    for index in np.argsort(rough)[:candidates]:
        other = candidates_of[index]
        rotation, shift = rigid_fit(scan, other, icp_steps)
        to_other, nearest_point, to_scan = distances(scan, other, rotation, shift)
        distance = 0.5 * (to_other.mean() + to_scan.mean())
        if best is None or distance < best["distance"]:
            best = {"index": int(index), "distance": float(distance), "to_other": to_other, "nearest": nearest_point}
    result = {"index": best["index"], "distance": 100.0 * best["distance"]}
    parts = candidates_of[best["index"]].parts
    if parts is not None:
        scan_parts = parts[best["nearest"]]
        result["parts"] = {
            HUMAN_PART_NAMES[part]: 100.0 * float(best["to_other"][scan_parts == part].mean())
            for part in np.unique(scan_parts)
        }
    return result


def summary(per_scan: dict[int, dict]) -> dict:
    """Median, mean, worst and the worst scans of per-scan nearest distances, and each FAUST pose's median."""
    values = np.array([per_scan[number]["distance"] for number in sorted(per_scan)])
    numbers = sorted(per_scan)
    worst = sorted(numbers, key=lambda number: -per_scan[number]["distance"])[:5]
    return {
        "median": float(np.median(values)),
        "mean": float(values.mean()),
        "worst": float(values.max()),
        "worst_scans": {f"{number:03d}": per_scan[number]["distance"] for number in worst},
        "per_pose_median": {
            str(pose): float(np.median([per_scan[n]["distance"] for n in numbers if n % 10 == pose]))
            for pose in range(10)
        },
        "per_scan": {f"{number:03d}": round(per_scan[number]["distance"], 3) for number in numbers},
    }


def main() -> None:
    parser = arguments(__doc__)
    add_data(parser, None, "FAUST's folder (holding training/registrations/tr_reg_000.ply ...); scans 000-079 only")
    add_out(parser, EXPERIMENT_RESULTS / "body_coverage")
    add_threads(parser, 1)
    parser.add_argument("--bodies", type=int, default=200, help="generated bodies per pose mode (default 200)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the generated bodies (default 0)")
    parser.add_argument("--points", type=int, default=1000, help="points measured from, per shape (default 1000)")
    parser.add_argument("--dense", type=int, default=12000, help="points measured to, per shape (default 12000)")
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
    meshes = read_scans(args.data.expanduser())
    scans = {number: sample_surface(*mesh, args.points, args.dense, rng) for number, mesh in meshes.items()}
    # What "close" means: each scan against the other people in the same pose, and against a second sampling
    # of itself (the distance the sampling alone leaves).
    same_pose = {}
    for number, scan in scans.items():
        others = [other for other in scans if other % 10 == number % 10 and other != number]
        same_pose[number] = nearest(scan, [scans[other] for other in others], len(others), args.icp_steps)
    resampled = [
        100.0 * chamfer(scans[number], sample_surface(*meshes[number], args.points, args.dense, rng))
        for number in list(meshes)[::10]
    ]
    modes = {}
    for mode in MODES:
        generator = BodyGenerator("faust", mode, args.seed, args.cache_dir)
        bodies, inside = [], []
        for index in range(args.bodies):
            body = generator.body(index)
            bodies.append(sample_surface(body.vertices, body.faces, args.points, args.dense, rng, body.parts))
            if index < args.intersection_bodies:
                inside.append(inside_vertices(body.vertices, body.faces))
        per_scan = {number: nearest(scan, bodies, args.candidates, args.icp_steps) for number, scan in scans.items()}
        modes[mode] = {
            **summary(per_scan),
            "per_part_median": {
                name: float(np.median([entry["parts"][name] for entry in per_scan.values() if name in entry["parts"]]))
                for name in HUMAN_PART_NAMES
            },
            "distinct_nearest_bodies": len({entry["index"] for entry in per_scan.values()}),
            "self_intersecting_bodies": int(np.count_nonzero(inside)),
            "intersection_bodies": len(inside),
            "median_inside_vertices": float(np.median(inside)) if inside else None,
        }
        print(f"{mode}: median {modes[mode]['median']:.2f}, worst {modes[mode]['worst']:.2f}", flush=True)
    result = {
        "what": "each real FAUST training scan (000-079) to its nearest generated body: symmetric mean closest-"
        "point distance x100 / sqrt(area) after a rigid fit, both at unit area",
        "bodies_per_mode": args.bodies,
        "seed": args.seed,
        "points": args.points,
        "dense": args.dense,
        "candidates": args.candidates,
        "icp_steps": args.icp_steps,
        "same_pose_other_people": summary(same_pose),
        "resampled_self_median": float(np.median(resampled)),
        "modes": modes,
        "seconds": round(time.perf_counter() - started, 1),
    }
    write_json(result_file(args.out, ".json"), result)
    write_markdown(result_file(args.out, ".md"), report(result))


def report(result: dict) -> list[str]:
    modes = result["modes"]
    rows = {"real people, same pose (nearest of the 7 others)": result["same_pose_other_people"]}
    rows.update({f"generated, {mode} ({result['bodies_per_mode']} bodies)": entry for mode, entry in modes.items()})
    lines = [
        "# Coverage of real poses by generated bodies",
        "",
        f"Each of FAUST's 80 training scans (people 0-7) against its nearest of {result['bodies_per_mode']} "
        f"generated bodies per pose mode (`faust` topology, seed {result['seed']}): symmetric mean closest-point "
        f"distance from {result['points']} points of each surface to {result['dense']} of the other, x100 / "
        f"sqrt(area), after a rigid fit (ICP on the {result['candidates']} closest as they stand). For scale, the "
        "same for the other real people in the same pose, and a second sampling of the same scan "
        f"({result['resampled_self_median']:.2f}: the floor the sampling leaves).",
        "",
    ]
    lines += markdown_table(
        [
            "nearest to each scan",
            "median scan",
            "mean",
            "worst scan",
            "worst scans",
            "distinct nearest",
            "self-intersecting bodies",
        ],
        [
            [
                name,
                f"{entry['median']:.2f}",
                f"{entry['mean']:.2f}",
                f"{entry['worst']:.2f}",
                ", ".join(f"{scan} ({value:.2f})" for scan, value in list(entry["worst_scans"].items())[:3]),
                entry.get("distinct_nearest_bodies", "-"),
                f"{entry['self_intersecting_bodies']} of {entry['intersection_bodies']} "
                f"(median {entry['median_inside_vertices']:.0f} vertices inside)"
                if "intersection_bodies" in entry
                else "-",
            ]
            for name, entry in rows.items()
        ],
        "lrrrlrl",
    )
    lines += ["", "Per FAUST pose (scan number mod 10), median over the 8 people:", ""]
    lines += markdown_table(
        ["nearest to each scan", *(str(pose) for pose in range(10))],
        [[name, *(f"{entry['per_pose_median'][str(pose)]:.2f}" for pose in range(10))] for name, entry in rows.items()],
    )
    lines += [
        "",
        "Per body part of the nearest generated body (each scan point's distance, by the part of the body's "
        "point closest to it), median over scans:",
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
