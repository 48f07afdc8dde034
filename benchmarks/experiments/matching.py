"""Matching held-out generated bodies, each in a form of its own: the shipped template model and the shipped
descriptor model against ZoomOut alone (from a rigid nearest-neighbour initial map), per setting.

Settings (pairs of test bodies i -> i + 1, never seen in training; each body remeshed or sampled on its own):

- ``remeshed``: source and target each remeshed independently (MeshLab, 0.55-1.0 times the body's vertex
  count, shuffled vertex order);
- ``rotated``: the same pairs, the target turned by a random rotation (the error must not change);
- ``cloud``: the source a noisy point cloud (half the vertex count, density varying 3x, 2 mm noise), the
  target remeshed;
- ``partial``: the source a one-sided scan (the faces a camera sees), the target remeshed whole; both
  scaled by one factor (``zernet match --same-scale``), so the source is matched as a part of the target.

Error (the field's convention): the geodesic distance on the target between the predicted vertex and the
true one (the target vertex nearest to the true image, :func:`zernet.matching.bodies.ground_truth_map`),
divided by the square root of the target's area, x100; the curve is the fraction of source vertices
within 0-10 % of the target's geodesic diameter. Time per pair: both shapes prepared from scratch (no
cache: operators, features, eigenbases) plus the match, at ``--threads`` CPU threads (default 2).

    .venv/bin/python -m benchmarks.experiments.matching [--topology faust] [--pairs 8] [--model FILE] [--template FILE]
        [--split test|validation] [--methods template,descriptors,zoomout] [--fine-tuned FILE]
        [--classifier RUN] [--out benchmarks/experiments/results/matching]

``--fine-tuned FILE`` adds a column for a template model fine-tuned from the shipped one on a small labelled
set (``python -m zernet.matching.train_template BODIES RUN --out FILE --init-from
zernet/pretrained/bodies-match-template.pt``).

``--classifier RUN`` adds, for reference, a 6,890-way correspondence run (``configs/bodies_correspondence.yaml``)
on the same pairs as generated, where source and target share the template's topology.

``--split validation`` pairs bodies 400, 401, ... of the train stream instead (never trained on by either
shipped model): the pairs a model is chosen on, so the test pairs stay unseen by every choice.

``--real DIR`` also scores **real people**, written apart (``STEM_real.json``, ``STEM_real.md``): the FAUST
training registrations in ``DIR`` (``tr_reg_000.ply`` ... ``tr_reg_079.ply``: people 0-7 only, scan =
10 x person + pose; people 8 and 9 are never read), ``--real-pairs`` pairs of two different people (of
``--real-people`` only, e.g. ``6,7`` for a template model fine-tuned on people 0-5), each scan
made into forms by the project's own tools (:mod:`zernet.data.bodies.forms`; cached under
``--cache-dir``/matching/real-forms, nothing of the data in the repository):

- ``remeshed``: both scans remeshed isotropically on their own (about 5,000 vertices);
- ``anisotropic``: both remeshed after stretching the scan 3x across the shoulders (x), then shrunk back:
  triangles three times longer up-down and front-back than across, about 5,000 vertices;
- ``decimated``: both halved by quadric decimation, left as the simplifier returns them;
- ``cloud``: the source a noisy half-density point cloud, the target remeshed;
- ``partial``: the source a one-sided scan, the target remeshed whole (``--same-scale``).

The ground truth of a form's vertex is the point of its registration it came from (closest point); the
registrations share one vertex order, so that point on the target's registration, and its nearest target
vertex, is the true image. Each pair is matched by ``zernet match``'s default (the template model and the
repair of :mod:`zernet.matching.consistency`) and with ``repair=False``, so the repair's part is measured.
Use ``--pairs 0`` for the real pairs alone.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from benchmarks.harness import (
    CACHE,
    EXPERIMENT_RESULTS,
    add_out,
    add_threads,
    arguments,
    markdown_table,
    result_file,
    write_json,
    write_markdown,
)
from zernet.data.bodies.forms import (
    closest_points,
    decimated_form,
    noisy_cloud_form,
    partial_form,
    remeshed_form,
)
from zernet.geometry import Surface, read_surface
from zernet.matching.bodies import LocatedForm, body_forms, ground_truth_map
from zernet.matching.fmap import zoomout
from zernet.matching.match import match_shapes, match_surfaces, nearest_vertex_map, shared_scale
from zernet.matching.model import load_matching_model
from zernet.matching.shapes import prepare_shape
from zernet.matching.template import load_template_model
from zernet.metrics import error_curve, geodesic_diameter, geodesic_errors
from zernet.training.augment import random_rotation
from zernet.viz import plot_error_curve, render_side_by_side

#: --split: (stream of zernet.matching.bodies.body_forms, first body index).
SPLITS = {"test": ("test", 0), "validation": ("train", 400)}
#: --methods: the columns each name adds.
METHODS = {
    "template": ("template model",),
    "fine-tuned": ("template model, fine-tuned",),
    "descriptors": ("descriptor model", "descriptor model, no ZoomOut"),
    "zoomout": ("ZoomOut alone (rigid start)",),
}
#: ZoomOut alone starts from this many eigenpairs (the rigid map is only trusted at low frequency).
ZOOMOUT_ALONE_START = 10

#: --real: the FAUST training scans that may be read (people 0-7, scan = 10 x person + pose); people 8 and 9
#: (scans 80-99) are held out for an independent measurement and never read here.
REAL_SCANS = range(80)
#: --real: (source form, target form) of each setting of real pairs.
REAL_SETTINGS = {
    "remeshed": ("remeshed", "remeshed"),
    "anisotropic": ("anisotropic", "anisotropic"),
    "decimated": ("decimated", "decimated"),
    "cloud": ("cloud-noisy", "remeshed"),
    "partial": ("partial", "remeshed"),
}
#: The forms of real scans, in the order their random streams are numbered.
REAL_FORM_NAMES = ("remeshed", "anisotropic", "decimated", "cloud-noisy", "partial")
#: Remeshed forms of a 6,890-vertex registration land near 5,000 vertices with these target ratios.
REAL_REMESH_RATIO = (0.62, 0.75)
#: The anisotropic form: stretch across the shoulders (x) before the isotropic remesh, and target ratio.
ANISOTROPIC_STRETCH = np.array([3.0, 1.0, 1.0])
ANISOTROPIC_REMESH_RATIO = (0.45, 0.55)
#: Bumped when a change alters the cached real forms.
REAL_FORMS_VERSION = 1
#: --real: the columns (the default of zernet match, and without its repair).
REAL_METHODS = ("template model", "template model, no repair")


def errors_on_target(
    target: Surface, predicted: np.ndarray, truth: np.ndarray, diameter: float
) -> tuple[np.ndarray, np.ndarray]:
    """(errors x100 / sqrt(area), errors / geodesic diameter) per source vertex.

    The exact geodesics need an oriented manifold mesh: on a target whose simplifier left a few faces that
    share a directed edge with another (a decimated scan), the distances are measured without those faces
    (the area is the whole target's)."""
    root_area = np.sqrt(target.area)
    vertices, faces = target.vertices, target.faces
    if faces is not None and len(faces):
        faces = faces[measurable_faces(faces)]
        kept = np.unique(faces)
        if len(kept) < len(vertices):  # vertices left without a face answer through the nearest kept one
            renumber = cKDTree(vertices[kept]).query(vertices)[1]
            vertices, faces = vertices[kept], np.searchsorted(kept, faces)
            predicted, truth = renumber[np.asarray(predicted)], renumber[np.asarray(truth)]
    relative = geodesic_errors(vertices, predicted, truth, faces=faces, diameter=root_area)
    return 100 * relative, relative * root_area / diameter


def measurable_faces(faces: np.ndarray) -> np.ndarray:
    """(F,) bool: the faces none of whose directed edges another face also has, and none of whose edges more
    than two faces share (what the exact geodesic solver accepts)."""
    faces = np.asarray(faces, dtype=np.int64)
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    owner = np.tile(np.arange(len(faces)), 3)
    bad = np.zeros(len(faces), dtype=bool)
    for edges, most in ((directed, 1), (np.sort(directed, axis=1), 2)):
        _, inverse, counts = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
        bad[owner[counts[np.asarray(inverse).reshape(-1)] > most]] = True
    return ~bad


def descriptor_and_zoomout_maps(
    model, source_form, target_surface: Surface, setting: str, seconds: list, pair: int
) -> dict[str, np.ndarray]:
    """The descriptor model's maps (with and without ZoomOut) and ZoomOut alone from a rigid start; the time
    of the remeshed pairs appended to ``seconds`` (both shapes prepared from scratch, then the match)."""
    spec = model.spec
    start = time.perf_counter()
    # A partial scan is matched in the units it shares with the whole body (zernet match --same-scale).
    area = spec.area
    if setting == "partial":
        area = shared_scale(spec.area, [source_form.surface, target_surface])
    source, target = (
        prepare_shape(
            surface,
            spec.patch_config_objects(),
            area,
            spec.feature_kind,
            spec.n_eigen,
            cache_dir=None,
            name=name,
            descriptor_vertices=spec.descriptor_vertices,
        )
        for surface, name in ((source_form.surface, source_form.name), (target_surface, target_surface.name))
    )
    result = match_shapes(model, source, target)
    if setting == "remeshed":
        seconds.append(
            {
                "pair": pair,
                "source_vertices": source.n_vertices,
                "target_vertices": target.n_vertices,
                "seconds": time.perf_counter() - start,
                **{f"{k}_seconds": v for k, v in result.seconds.items()},
            }
        )
    layer_only = match_shapes(model, source, target, zoomout_end=0).vertex_map
    rigid, _ = zoomout(
        nearest_vertex_map(source, target),
        target.basis,
        source.basis,
        ZOOMOUT_ALONE_START,
        spec.zoomout_end,
        spec.zoomout_step,
    )
    return {
        "descriptor model": result.vertex_map,
        "descriptor model, no ZoomOut": layer_only,
        "ZoomOut alone (rigid start)": rigid,
    }


def classifier_reference(run: str, bodies: dict, faces: np.ndarray, indices) -> dict:
    """The 6,890-way correspondence classifier of a run (``configs/bodies_correspondence.yaml``) on the same
    pairs, where shapes share the template's topology: each source body as generated is labelled with a
    template vertex per vertex, which is the target vertex of that index (as ``zernet predict`` applies the
    run, its refinement included); the error is measured on the target as generated."""
    from zernet.inference.predict import predict

    errors, pair_means = [], []
    for source_index, target_index in zip(indices[:-1], indices[1:]):
        target = Surface(bodies[target_index], faces)
        labels = predict(run, Surface(bodies[source_index], faces))
        truth = np.arange(len(labels))  # a registered source vertex i is target vertex i
        area_errors, _ = errors_on_target(target, labels, truth, geodesic_diameter(target))
        errors.append(area_errors)
        pair_means.append(float(area_errors.mean()))
    every = np.concatenate(errors)
    return {
        "run": run,
        "mean_error_x100": float(every.mean()),
        "median_error_x100": float(np.median(every)),
        "pair_means": pair_means,
    }


def real_pairs(n: int, seed: int = 0, people: tuple[int, ...] | None = None) -> list[tuple[int, int]]:
    """``n`` (source scan, target scan) pairs of two different people among :data:`REAL_SCANS`, drawn once;
    ``people``: only the scans of these people (scan // 10), e.g. those a fine-tune did not train on."""
    scans = [scan for scan in REAL_SCANS if people is None or scan // 10 in people]
    if people is not None and len({scan // 10 for scan in scans}) < 2:
        raise ValueError(f"pairs of two different people need two of people 0-7, got {sorted(people)}")
    rng = np.random.default_rng(seed)
    pairs = []
    while len(pairs) < n:
        source, target = (int(scan) for scan in rng.choice(scans, 2))
        if source // 10 != target // 10:
            pairs.append((source, target))
    return pairs


def registration(directory: Path, scan: int) -> Surface:
    """FAUST training registration ``scan`` (one of :data:`REAL_SCANS` only)."""
    if scan not in REAL_SCANS:
        raise ValueError(f"scan {scan} is a held-out person's (people 8-9); only scans 0-79 are read")
    return read_surface(directory / f"tr_reg_{scan:03d}.ply")


def real_form(directory: Path, scan: int, form: str, cache_dir: Path) -> LocatedForm:
    """Registration ``scan`` in ``form`` (:data:`REAL_SETTINGS`), located on its registration; cached."""
    name = f"real_{scan:03d}_{form}"
    path = cache_dir / "matching" / "real-forms" / f"{name}-v{REAL_FORMS_VERSION}.npz"
    if not path.is_file():
        body = registration(directory, scan)
        vertices, faces = np.asarray(body.vertices, np.float64), np.asarray(body.faces, np.int64)
        labels = np.zeros(len(vertices), dtype=np.int64)  # no parts: only the ground truth is used
        rng = np.random.default_rng([scan, REAL_FORM_NAMES.index(form)])  # each scan and form its own stream
        if form == "remeshed":
            made = remeshed_form(vertices, faces, labels, rng, vertex_ratio=REAL_REMESH_RATIO)
            new_vertices, new_faces = made.vertices, made.faces
        elif form == "anisotropic":
            stretched = remeshed_form(vertices * ANISOTROPIC_STRETCH, faces, labels, rng, ANISOTROPIC_REMESH_RATIO)
            new_vertices, new_faces = stretched.vertices / ANISOTROPIC_STRETCH, stretched.faces
        else:
            maker = {"decimated": decimated_form, "cloud-noisy": noisy_cloud_form, "partial": partial_form}[form]
            made = maker(vertices, faces, labels, rng)
            new_vertices, new_faces = made.vertices, made.faces
        face_index, barycentric, on_body, _ = closest_points(vertices, faces, new_vertices)
        path.parent.mkdir(parents=True, exist_ok=True)
        empty = np.zeros((0, 3), np.int64)
        np.savez(
            path,
            vertices=new_vertices,
            faces=empty if new_faces is None else new_faces,
            face_index=face_index,
            barycentric=barycentric,
            on_body=on_body,
        )
    with np.load(path) as stored:
        faces = stored["faces"] if stored["faces"].size else None
        surface = Surface(stored["vertices"], faces, name=name)
        return LocatedForm(name, form, scan, surface, stored["face_index"], stored["barycentric"], stored["on_body"])


def score_real(
    directory: Path, n_pairs: int, setting: str, template_model, cache_dir: Path, people: tuple[int, ...] | None = None
) -> dict:
    """One setting's pairs of real people: per pair, the mean error of ``zernet match``'s default and of the
    template map without the repair, the median, the share of points more than 10 away, and the times."""
    source_form_name, target_form_name = REAL_SETTINGS[setting]
    rows = []
    for source_scan, target_scan in real_pairs(n_pairs, people=people):
        source = real_form(directory, source_scan, source_form_name, cache_dir)
        target = real_form(directory, target_scan, target_form_name, cache_dir)
        target_registration = registration(directory, target_scan)
        truth = ground_truth_map(source, target, target_registration.vertices, target_registration.faces)
        row = {"pair": [source_scan, target_scan], "vertices": [source.surface.n_vertices, target.surface.n_vertices]}
        for name, repair in zip(REAL_METHODS, (True, False)):
            start = time.perf_counter()
            result, _, _ = match_surfaces(
                source.surface, target.surface, template_model, same_scale=setting == "partial", repair=repair
            )
            seconds = time.perf_counter() - start
            errors, _ = errors_on_target(target.surface, result.vertex_map, truth, 1.0)
            row[name] = {
                "mean_error_x100": float(errors.mean()),
                "median_error_x100": float(np.median(errors)),
                "share_above_10": float(np.mean(errors > 10)),
                "seconds": seconds,
                "stage_seconds": result.seconds,
            }
        rows.append(row)
        print(
            f"real {setting} {source_scan}->{target_scan}: "
            + ", ".join(f"{name} {row[name]['mean_error_x100']:.2f}" for name in REAL_METHODS),
            flush=True,
        )
    return {
        "pairs": rows,
        **{
            name: {
                "mean_error_x100": float(np.mean([row[name]["mean_error_x100"] for row in rows])),
                "worst_pair_x100": float(np.max([row[name]["mean_error_x100"] for row in rows])),
                "mean_seconds": float(np.mean([row[name]["seconds"] for row in rows])),
            }
            for name in REAL_METHODS
        },
    }


def real_markdown(
    results: dict, n_pairs: int, threads: int, template: str, people: tuple[int, ...] | None = None
) -> list[str]:
    whom = "people 0-7" if people is None else "people " + ", ".join(str(p) for p in sorted(people))
    lines = [
        f"# Matching real people: FAUST training scans, {whom} ({n_pairs} pairs of two different people)",
        "",
        "Real scans (not generated bodies; generated pairs: `matching.md`). Mean geodesic error x100 / sqrt(target "
        "area) over the pairs (worst pair in brackets); `zernet match`'s default (the template model and its "
        "repair, `zernet.matching.consistency`) and the template map without the repair (`--no-repair`). "
        f"{threads} CPU thread(s); time per pair of the default, both shapes read from scratch. Template model: "
        f"{template}.",
        "",
    ]
    rows = [
        [
            setting,
            *(f"{entry[name]['mean_error_x100']:.2f} ({entry[name]['worst_pair_x100']:.2f})" for name in REAL_METHODS),
            f"{entry[REAL_METHODS[0]]['mean_seconds']:.1f} s",
        ]
        for setting, entry in results.items()
    ]
    lines += markdown_table(["real setting", *REAL_METHODS, "time per pair"], rows)
    lines += ["", "Per pair (source scan -> target scan: default / no repair; scan = 10 x person + pose):", ""]
    for setting, entry in results.items():
        pairs = "; ".join(
            f"{row['pair'][0]}->{row['pair'][1]}: {row[REAL_METHODS[0]]['mean_error_x100']:.2f} / "
            f"{row[REAL_METHODS[1]]['mean_error_x100']:.2f}"
            for row in entry["pairs"]
        )
        lines.append(f"- {setting}: {pairs}")
    return lines


def main(argv=None) -> int:
    parser = arguments(__doc__)
    parser.add_argument("--topology", default="faust")
    parser.add_argument("--pairs", type=int, default=8)
    parser.add_argument("--settings", default="remeshed,rotated,cloud,partial")
    parser.add_argument("--model", default=None, help="descriptor model file or run folder (default: the shipped one)")
    parser.add_argument("--template", default=None, help="template model file (default: the shipped one)")
    parser.add_argument(
        "--fine-tuned",
        default=None,
        help="a template model fine-tuned from the shipped one on a small labelled set (train_template "
        "--init-from): adds its column",
    )
    add_out(parser, EXPERIMENT_RESULTS / "matching")
    add_threads(parser, default=2)
    parser.add_argument("--cache-dir", type=Path, default=CACHE)
    parser.add_argument("--split", choices=sorted(SPLITS), default="test", help="test pairs, or validation pairs")
    parser.add_argument(
        "--classifier",
        default=None,
        help="a 6,890-way correspondence run (configs/bodies_correspondence.yaml, faust topology): adds its "
        "error on the same pairs as generated (shared topology), for reference",
    )
    parser.add_argument(
        "--methods", default="template,descriptors,zoomout", help="comma-separated subset of " + ",".join(METHODS)
    )
    parser.add_argument(
        "--real",
        type=Path,
        default=None,
        metavar="DIR",
        help="FAUST training registrations (tr_reg_000.ply ...): also score pairs of real people 0-7",
    )
    parser.add_argument("--real-pairs", type=int, default=10, help="pairs of real people per setting")
    parser.add_argument("--real-settings", default=",".join(REAL_SETTINGS), help="subset of " + ",".join(REAL_SETTINGS))
    parser.add_argument(
        "--real-people",
        default=None,
        help="comma-separated people (0-7) whose scans make the real pairs (default: all eight), e.g. 6,7 for a "
        "template model fine-tuned on people 0-5",
    )
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    model, provenance = load_matching_model(args.model)
    template_model = load_template_model(args.template)
    template_name = Path(args.template).name if args.template else "shipped"
    template_name += f" (commit {str(template_model.provenance.get('commit'))[:10]})"
    if args.real is not None:
        real_settings = args.real_settings.split(",")
        real_people = None if args.real_people is None else tuple(int(p) for p in args.real_people.split(","))
        if real_people is not None and not set(real_people) <= set(range(8)):
            parser.error(f"--real-people: people 0-7 only (8 and 9 are held out), got {args.real_people}")
        unknown = set(real_settings) - set(REAL_SETTINGS)
        if unknown:
            parser.error(f"--real-settings: unknown {sorted(unknown)}; choose from {sorted(REAL_SETTINGS)}")
        real = {}
        for setting in real_settings:  # the files are written after each setting: a long run keeps what it has
            real[setting] = score_real(
                args.real, args.real_pairs, setting, template_model, Path(args.cache_dir), real_people
            )
            write_json(
                result_file(args.out, "_real.json"),
                {
                    "pairs": args.real_pairs,
                    "people": list(real_people or range(8)),
                    "threads": args.threads,
                    "template": template_name,
                    "settings": real,
                },
            )
            lines = real_markdown(real, args.real_pairs, args.threads, template_name, real_people)
            write_markdown(result_file(args.out, "_real.md"), lines)
        print("\n".join(lines))
    if args.pairs == 0:
        return 0
    settings = args.settings.split(",")
    stream, first = SPLITS[args.split]
    indices = range(first, first + args.pairs + 1)
    targets, target_bodies, faces = body_forms(
        indices, stream, {"remeshed": 1.0}, 0, args.topology, "varied", 0, args.cache_dir
    )
    sources = {"remeshed": targets, "rotated": targets}
    for setting, form in (("cloud", "cloud-noisy"), ("partial", "partial")):
        if setting in settings:
            sources[setting] = body_forms(indices, stream, {form: 1.0}, 0, args.topology, "varied", 0, args.cache_dir)[
                0
            ]
    rng = np.random.default_rng(0)
    chosen = args.methods.split(",") + (["fine-tuned"] if args.fine_tuned else [])
    if "fine-tuned" in chosen and not args.fine_tuned:
        parser.error("--methods fine-tuned needs --fine-tuned FILE")
    fine_tuned_model = load_template_model(args.fine_tuned) if args.fine_tuned else None
    unknown = set(chosen) - set(METHODS)
    if unknown:
        parser.error(f"--methods: unknown {sorted(unknown)}; choose from {sorted(METHODS)}")
    methods = [name for key in METHODS if key in chosen for name in METHODS[key]]
    results = {
        setting: {name: {"errors": [], "diameter_errors": [], "pair_means": []} for name in methods}
        for setting in settings
    }
    seconds, template_seconds, example = [], [], None
    for i in range(args.pairs):
        target_form = targets[i + 1]
        truth_body = target_bodies[target_form.body]
        for setting in settings:
            source_form = sources[setting][i]
            truth = ground_truth_map(source_form, target_form, truth_body, faces)
            target_surface = target_form.surface
            if setting == "rotated":
                rotation = random_rotation(rng, "any")
                target_surface = Surface(target_surface.vertices @ rotation.T, target_surface.faces, name="rotated")
            predictions = {}
            if "descriptors" in chosen or "zoomout" in chosen:
                timed = seconds if "descriptors" in chosen else []  # the descriptor model's time, when it is measured
                predictions.update(descriptor_and_zoomout_maps(model, source_form, target_surface, setting, timed, i))
            if "template" in chosen:
                # The template model from the surfaces as a user has them (match_surfaces: repair, scaling, all).
                start = time.perf_counter()
                template_result, _, _ = match_surfaces(
                    source_form.surface, target_surface, template_model, same_scale=setting == "partial"
                )
                if setting == "remeshed":
                    template_seconds.append(
                        {"pair": i, "seconds": time.perf_counter() - start, **template_result.seconds}
                    )
                    if example is None:
                        example = (source_form.surface, target_surface, template_result)
                predictions["template model"] = template_result.vertex_map
            if fine_tuned_model is not None:
                tuned, _, _ = match_surfaces(
                    source_form.surface, target_surface, fine_tuned_model, same_scale=setting == "partial"
                )
                predictions["template model, fine-tuned"] = tuned.vertex_map
            # Errors are measured on the target in its own units (rotation does not change them).
            diameter = geodesic_diameter(target_surface)
            for name in methods:
                area_errors, diameter_errors = errors_on_target(target_surface, predictions[name], truth, diameter)
                entry = results[setting][name]
                entry["errors"].append(area_errors)
                entry["diameter_errors"].append(diameter_errors)
                entry["pair_means"].append(float(area_errors.mean()))
            print(
                f"pair {i} {setting}: "
                + ", ".join(f"{name} {results[setting][name]['pair_means'][-1]:.2f}" for name in methods),
                flush=True,
            )
    summary = {
        "topology": args.topology,
        "pairs": args.pairs,
        "split": args.split,
        "model": str(args.model or "shipped"),
        "model_provenance": {k: provenance.get(k) for k in ("commit", "command", "step", "val_error")},
        "template": str(args.template or "shipped"),
        "template_provenance": {k: template_model.provenance.get(k) for k in ("commit", "command")},
        "fine_tuned": args.fine_tuned,
        "fine_tuned_provenance": {k: fine_tuned_model.provenance.get(k) for k in ("commit", "command")}
        if fine_tuned_model is not None
        else None,
        "template_time_per_pair": template_seconds,
        "template_mean_seconds_per_pair": float(np.mean([s["seconds"] for s in template_seconds]))
        if template_seconds
        else None,
        "threads": args.threads,
        "time_per_pair": seconds,
        "mean_seconds_per_pair": float(np.mean([s["seconds"] for s in seconds])) if seconds else None,
        "settings": {},
    }
    if args.classifier:
        summary["classifier_reference"] = classifier_reference(args.classifier, target_bodies, faces, list(indices))
    curves = {}
    for setting in settings:
        summary["settings"][setting] = {}
        for name, entry in results[setting].items():
            errors = np.concatenate(entry["errors"])
            radii, fractions = error_curve(np.concatenate(entry["diameter_errors"]))
            summary["settings"][setting][name] = {
                "mean_error_x100": float(errors.mean()),
                "median_error_x100": float(np.median(errors)),
                "pair_means": entry["pair_means"],
                "curve_radii": radii.tolist(),
                "curve_fractions": fractions.tolist(),
            }
            curves[f"{setting}: {name}"] = (radii, fractions)
    if "rotated" in settings and "remeshed" in settings:
        summary["rotation_change"] = {
            name: float(
                np.max(
                    np.abs(np.subtract(results["rotated"][name]["pair_means"], results["remeshed"][name]["pair_means"]))
                )
            )
            for name in ("template model", "template model, fine-tuned", "descriptor model")
            if name in methods
        }
    write_json(result_file(args.out, ".json"), summary)
    plot_error_curve(
        curves,
        result_file(args.out, "_curves.png"),
        title=f"Matching held-out generated bodies ({args.topology}, each remeshed on its own)",
    )
    if example is not None:
        from zernet.cli.match import source_colour_field, transfer_field

        source, target, result = example
        field = source_colour_field(source.vertices)
        render_side_by_side(
            [source, target],
            [field, transfer_field(field, result.reverse_map)],
            result_file(args.out, "_example.png"),
            ["source", "target"],
            title="colour on the source, carried to the target by the template model's map",
        )
    lines = markdown(summary)
    write_markdown(result_file(args.out, ".md"), lines)
    print("\n".join(lines))
    return 0


def markdown(summary: dict) -> list[str]:
    lines = [
        f"# Matching held-out generated bodies ({summary['topology']} topology, {summary['pairs']} "
        f"{summary['split']} pairs)",
        "",
        f"{summary['threads']} CPU thread(s). Template model: {summary['template']} "
        f"(commit {str(summary['template_provenance'].get('commit'))[:10]}); descriptor model: {summary['model']} "
        f"(commit {str(summary['model_provenance'].get('commit'))[:10]}).",
        "",
        "Mean geodesic error x100 / sqrt(target area) (median in brackets); every body in a form of its own.",
        "",
    ]
    methods = list(next(iter(summary["settings"].values())))
    rows = [
        [setting, *(f"{m['mean_error_x100']:.2f} ({m['median_error_x100']:.2f})" for m in by_method.values())]
        for setting, by_method in summary["settings"].items()
    ]
    lines += markdown_table(["setting", *methods], rows)
    if "rotation_change" in summary:
        lines += [
            "",
            "Largest change of a pair's mean error when the target is rotated: "
            + ", ".join(f"{name} {value:.3f}" for name, value in summary["rotation_change"].items())
            + ".",
        ]
    if summary["time_per_pair"]:
        sizes = [(s["source_vertices"], s["target_vertices"]) for s in summary["time_per_pair"]]
        lines += [
            "",
            f"Time per pair with the descriptor model (remeshed, {min(min(s) for s in sizes)}-"
            f"{max(max(s) for s in sizes)} vertices, both shapes prepared from scratch, {summary['threads']} thread(s)): mean "
            f"{summary['mean_seconds_per_pair']:.1f} s, max {max(s['seconds'] for s in summary['time_per_pair']):.1f} s.",
        ]
    if summary["template_time_per_pair"]:
        lines += [
            "",
            "Time per pair with the template model (remeshed, from the surfaces as a user has them: "
            f"`match_surfaces`, the functional map included, {summary['threads']} thread(s)): mean "
            f"{summary['template_mean_seconds_per_pair']:.1f} s, "
            f"max {max(s['seconds'] for s in summary['template_time_per_pair']):.1f} s.",
        ]
    if summary.get("classifier_reference"):
        reference = summary["classifier_reference"]
        lines += [
            "",
            f"For reference, where shapes share the template's topology (each body as generated, not remeshed): "
            f"the 6,890-way correspondence classifier `{reference['run']}`, as `zernet predict` applies it, "
            f"{reference['mean_error_x100']:.2f} ({reference['median_error_x100']:.2f}).",
        ]
    if summary.get("fine_tuned"):
        lines += [
            "",
            f"Fine-tuned template model: `{summary['fine_tuned']}`, made from the shipped one by "
            f"`{summary['fine_tuned_provenance'].get('command')}`.",
        ]
    return lines


if __name__ == "__main__":
    raise SystemExit(main())
