"""Generated bodies for matching: each body in a form of its own (remeshed, or a noisy point cloud), with
the ground truth that relates any two of them.

Every generated body shares one topology, so a point given in barycentric coordinates of a template
triangle is the same anatomical point on every body. Each vertex of a form is located on its own body by
its closest point (:func:`zernet.data.bodies.forms.closest_points`: a triangle and barycentric weights), so
the true image of a source vertex on another body is that triangle and those weights evaluated on the
target body's vertices; its true target vertex is the target-form vertex nearest to that point
(:func:`ground_truth_map`). This is finer than the nearest template vertex, whose spacing on coarse
topologies would put an error floor of about half an edge under every measurement.

Forms come from :func:`zernet.data.bodies.forms.make_forms` (remeshing by MeshLab, noisy clouds), one per
body, drawn from a per-body stream, and are cached under ``<cache_dir>/matching/forms/``.
"""

from __future__ import annotations

import hashlib
import io
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from zernet.data.bodies.forms import closest_points, make_forms
from zernet.data.bodies.generator import SPLIT_CODES, BodyGenerator
from zernet.geometry import Surface
from zernet.io_utils import atomic_write_bytes

__all__ = ["FORMS_VERSION", "LocatedForm", "body_forms", "ground_truth_map", "true_points"]

#: Bumped when a change alters the cached forms.
FORMS_VERSION = 1


@dataclass(frozen=True)
class LocatedForm:
    """One body in one form, located on its body.

    Attributes:
        name: ``<split>_<index>_<form>``.
        form: the form's name (``remeshed``, ``cloud-noisy``, ...).
        body: the body's index within its split.
        surface: the form (metres; faces None for a cloud), vertices in their own (shuffled) order.
        face_index: (N,) int64 the template triangle each vertex lies on (closest point).
        barycentric: (N, 3) float64 its weights in that triangle.
        on_body: (N, 3) float64 that closest point on the body (the vertex itself for a mesh form; the
            noise-free position for a noisy cloud).
    """

    name: str
    form: str
    body: int
    surface: Surface
    face_index: np.ndarray
    barycentric: np.ndarray
    on_body: np.ndarray


def true_points(form: LocatedForm, body_vertices: np.ndarray, template_faces: np.ndarray) -> np.ndarray:
    """(N, 3) where the vertices of ``form`` lie on another body (its vertices ``body_vertices`` (V, 3))."""
    corners = body_vertices[template_faces[form.face_index]]  # (N, 3 corners, 3)
    return np.einsum("nc,ncd->nd", form.barycentric, corners)


def ground_truth_map(
    source: LocatedForm, target: LocatedForm, target_body_vertices: np.ndarray, template_faces: np.ndarray
) -> np.ndarray:
    """(N_source,) int64: the target vertex nearest to the true image of each source vertex (module
    docstring); ``target_body_vertices`` are the vertices of the body ``target`` was made from."""
    points = true_points(source, target_body_vertices, template_faces)
    _, nearest = cKDTree(target.on_body).query(points)
    return np.asarray(nearest, dtype=np.int64)


def _form_key(generator: BodyGenerator, index: int, split: str, form: str, seed: int) -> str:
    text = f"{generator.body_key(index, split)}-{form}-seed{seed}-forms{FORMS_VERSION}"
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def _make_form(
    generator: BodyGenerator, index: int, split: str, form: str, seed: int, cache: Path | None
) -> LocatedForm:
    """Body ``index`` of ``split`` in form ``form`` (cached)."""
    name = f"{split}_{index:03d}_{form}"
    path = None if cache is None else cache / f"{_form_key(generator, index, split, form, seed)}.npz"
    if path is not None and path.is_file():
        with np.load(path) as stored:
            faces = stored["faces"] if stored["faces"].size else None
            surface = Surface(stored["vertices"], faces, name=name)
            return LocatedForm(
                name, form, index, surface, stored["face_index"], stored["barycentric"], stored["on_body"]
            )
    body = generator.body(index, split)
    rng = np.random.default_rng(np.random.SeedSequence([seed, SPLIT_CODES[split], index]))
    made = make_forms(body, [form], rng)[form]
    face_index, barycentric, on_body, _ = closest_points(body.vertices, body.faces, made.vertices)
    surface = Surface(made.vertices, made.faces, name=name)
    if path is not None:
        buffer = io.BytesIO()
        np.savez(
            buffer,
            vertices=surface.vertices,
            faces=np.zeros((0, 3), np.int64) if made.faces is None else made.faces,
            face_index=face_index,
            barycentric=barycentric,
            on_body=on_body,
        )
        atomic_write_bytes(path, buffer.getvalue())
    return LocatedForm(name, form, index, surface, face_index, barycentric, on_body)


def body_forms(
    indices,
    split: str = "train",
    forms: dict[str, float] | None = None,
    seed: int = 0,
    topology: str = "coarse-1229",
    poses: str = "varied",
    body_seed: int = 0,
    cache_dir: str | os.PathLike | None = ".zernet-cache",
) -> tuple[list[LocatedForm], dict[int, np.ndarray], np.ndarray]:
    """One form of each body ``indices`` of ``split``.

    Args:
        indices: body indices within the split.
        forms: {form name: weight}: each body's form is drawn with these probabilities from the body's own
            stream (default: all remeshed).
        seed: seeds the form draws (and the remeshing); ``body_seed`` seeds the bodies themselves.
        topology, poses: of the generated bodies (:class:`zernet.data.bodies.BodyGenerator`).

    Returns:
        (forms, {body index: its vertices (V, 3)}, the template faces (F, 3)).
    """
    forms = forms or {"remeshed": 1.0}
    names = sorted(forms)
    weights = np.asarray([forms[name] for name in names], dtype=np.float64)
    generator = BodyGenerator(topology, poses, body_seed, cache_dir)
    cache = None if cache_dir is None else Path(os.path.expanduser(os.fspath(cache_dir))) / "matching" / "forms"
    made, body_vertices = [], {}
    for index in indices:
        draw = np.random.default_rng(np.random.SeedSequence([seed, SPLIT_CODES[split], int(index), 1]))
        form = names[int(draw.choice(len(names), p=weights / weights.sum()))]
        made.append(_make_form(generator, int(index), split, form, seed, cache))
        body_vertices[int(index)] = generator.body(int(index), split).vertices
    return made, body_vertices, generator.topology().faces
