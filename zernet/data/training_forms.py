"""Form augmentation of the training shapes (``data.forms``): each training shape also trained on in the forms
users bring, remeshed, decimated, sampled as a point cloud (clean or noisy) or scanned from one side.

``forms`` maps a form name (:data:`FORM_NAMES`, made by :mod:`zernet.data.bodies.forms`, which works on any
triangle mesh) to a rate: the number of copies of that form per training shape. ``1`` gives every
training shape one copy, ``0.25`` a quarter of them (drawn once, seeded), ``2`` every shape two copies
with different draws. The training shapes themselves always stay in training. Only the shapes of the
training split get forms, after the validation shapes are carved from it: validation and test shapes are
scored as given.

Targets follow the vertices: each vertex or point of a form is a position on the original surface, and it
takes the target of the original vertex nearest that position within its triangle
(:func:`~zernet.data.bodies.forms.ground_truth`): the vertex a point was sampled next to (clouds, before
the noise), the vertex itself (one-sided scans), the nearest corner of the closest triangle (remeshed,
decimated). Part labels (per-face labels are per-vertex by then, see :mod:`zernet.data.segmentation`),
regression values and correspondence classes (the template vertex index) are carried the same way; a
regression value is therefore piecewise constant over a form, within one original edge of exact.

A form is an ordinary shape to the preprocessing: validated (repaired: the decimated form keeps the
simplifier's degenerate faces on purpose), area-normalised like every shape (so a one-sided scan is
enlarged to a whole shape's area, exactly as a one-sided scan given to ``predict`` is; ``patch.scale``
keeps one factor for all) and cached under a key made of its source's key, the form, the copy and the
seed (``data.seed``): a second run reads the forms back instead of making them again.
"""

from __future__ import annotations

import hashlib
import importlib.util
import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import replace
from functools import partial

import numpy as np

from zernet.data.bodies.forms import (
    cloud_form,
    decimated_form,
    noisy_cloud_form,
    partial_form,
    remeshed_form,
)
from zernet.data.dataset import DatasetError
from zernet.data.source import ShapeSource
from zernet.geometry import Surface, SurfaceWarning, validate_surface

__all__ = ["FORM_NAMES", "FORMS_VERSION", "check_form_rates", "form_sources", "load_form"]

#: The forms a training shape can be trained in, as :mod:`zernet.data.bodies.forms` names them.
FORM_NAMES = ("remeshed", "decimated", "cloud", "cloud-noisy", "partial")
#: Bump when a form's making changes, so cached forms are made again.
FORMS_VERSION = 2
#: Noise of the noisy cloud per unit of sqrt(area): 2 mm on a human body of 1.8 m² (the generated
#: bodies' and FAUST's size), the same relative noise on a shape of any size or unit.
NOISE_PER_SIZE = 0.0015

_MAKERS = {
    "remeshed": remeshed_form,
    "decimated": decimated_form,
    "cloud": cloud_form,
    "cloud-noisy": noisy_cloud_form,
    "partial": partial_form,
}
# The package each form needs beyond the core dependencies, and how to get it.
_EXTRAS = {"remeshed": ("pymeshlab", "pip install 'zernet[bodies]' (or pip install pymeshlab)")}
# Why "original" is not a form to ask for.
_ORIGINAL = "the training shapes themselves always stay in training; data.forms names the forms added to them"


def check_form_rates(forms: Mapping[str, float] | None) -> dict[str, float]:
    """``forms`` checked: {form name: rate >= 0} with the forms of rate 0 left out, in :data:`FORM_NAMES`
    order. :class:`~zernet.data.dataset.DatasetError` for anything else: not a mapping, an unknown form
    name, a rate that is not a finite number >= 0, or a form whose package is not installed."""
    if forms is None:
        return {}
    if not isinstance(forms, Mapping):
        raise DatasetError(
            f"forms must map form names to rates (copies per training shape), e.g. {{cloud: 0.25}}, got {forms!r}"
        )
    for name, rate in forms.items():
        if name == "original":
            raise DatasetError(f"forms: 'original' is not a form to add: {_ORIGINAL}")
        if name not in FORM_NAMES:
            raise DatasetError(f"forms: unknown form {name!r}; choose from {', '.join(FORM_NAMES)}")
        if isinstance(rate, bool) or not isinstance(rate, (int, float)) or not math.isfinite(rate) or rate < 0:
            raise DatasetError(
                f"forms.{name} must be a number >= 0 (copies per training shape: 1 each, 0.25 a quarter "
                f"of them), got {rate!r}"
            )
    for name, (package, advice) in _EXTRAS.items():
        if forms.get(name, 0) > 0 and importlib.util.find_spec(package) is None:
            raise DatasetError(f"forms: the {name!r} form needs {package}: {advice}")
    return {name: float(forms[name]) for name in FORM_NAMES if forms.get(name, 0) > 0}


def form_sources(
    training: Sequence[ShapeSource], forms: Mapping[str, float], seed: int
) -> dict[str, list[ShapeSource]]:
    """The sources of the forms of the ``training`` shapes, {form: sources}: per form of rate r,
    ``floor(r)`` copies of every shape and one more of ``round(frac(r) * len(training))`` shapes drawn by
    ``seed``, shape by shape (in ``training`` order), copy by copy. Each form's draws depend on ``seed``, its
    shape, form and copy only, so asking for another form or rate does not change the forms already made."""
    sources: dict[str, list[ShapeSource]] = {}
    for form, rate in check_form_rates(forms).items():
        whole, fraction = int(rate), rate - int(rate)
        extra = round(fraction * len(training))
        chooser = np.random.default_rng(_digest_seed(f"choose|{form}|{seed}"))
        chosen = set(chooser.permutation(len(training))[:extra].tolist())
        sources[form] = [
            _form_source(source, form, copy, seed)
            for position, source in enumerate(training)
            for copy in range(whole + (position in chosen))
        ]
    return sources


def _form_source(source: ShapeSource, form: str, copy: int, seed: int) -> ShapeSource:
    """The source of copy ``copy`` of ``form`` of ``source``: named ``<name>#<form>`` (``#<form><copy+1>``
    beyond the first copy), cached under the source's key plus the form, copy, seed and forms version."""
    name = f"{source.name}#{form}" + (str(copy + 1) if copy else "")
    form_seed = _digest_seed(f"{source.key or source.name}|{form}|{copy}|{seed}")
    key = None if source.key is None else f"{source.key}|form={form}|copy={copy}|seed={seed}|v{FORMS_VERSION}"
    return replace(source, name=name, load=partial(load_form, source, form, form_seed), key=key)


def load_form(source: ShapeSource, form: str, form_seed: int) -> tuple[Surface, np.ndarray]:
    """ShapeSource loader of one form: the shape ``source`` loads, made into ``form`` with a generator
    seeded by ``form_seed``, its per-vertex target carried to the form's vertices (module docstring)."""
    surface, target = source.load()
    if surface.faces is None:
        raise DatasetError(f"{source.name}: is a point cloud; forms are made from triangle meshes")
    if target is None:
        raise DatasetError(f"{source.name}: has no target; forms carry a per-vertex target to their vertices")
    target = np.asarray(target)
    if target.ndim != 1 or len(target) != surface.n_vertices:
        raise DatasetError(
            f"{source.name}: target has shape {target.shape}, not one value per vertex ({surface.n_vertices}): "
            "forms carry per-vertex targets only"
        )
    vertices = np.asarray(surface.vertices, dtype=np.float64)
    faces = np.asarray(surface.faces, dtype=np.int64)
    original_vertex = np.arange(len(vertices))  # as "labels": each form vertex gets its original vertex
    rng = np.random.default_rng(form_seed)
    if form == "cloud-noisy":
        size = math.sqrt(float(surface.face_areas().sum()))
        made = noisy_cloud_form(vertices, faces, original_vertex, rng, noise=NOISE_PER_SIZE * size)
    else:
        made = _MAKERS[form](vertices, faces, original_vertex, rng)
    # The makers shuffle the vertices; in an order along a space-filling curve instead, neighbours are near
    # in memory and a training step on the form is 1.4-1.5 times faster (a 6,890-vertex body: 3.2 s
    # shuffled, 2.3 s in this order, 2.1 s in the mesh's own).
    order = _spatial_order(made.vertices)
    faces = None if made.faces is None else np.argsort(order)[made.faces]
    carried = target[made.template_vertex[order]]
    shape = Surface(made.vertices[order], faces, name=f"{surface.name} ({form})")
    # The decimated form keeps degenerate and duplicate faces on purpose (the simplifier's output); the
    # repair drops them, the target following the vertices. The warnings about them are expected here.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SurfaceWarning)
        repaired = validate_surface(shape.with_fields({"__target__": carried}), repair=True)
    fields = {k: v for k, v in repaired.fields.items() if k != "__target__"}
    return Surface(repaired.vertices, repaired.faces, None, fields, repaired.name), repaired.fields["__target__"]


def _spatial_order(points: np.ndarray, bits: int = 10) -> np.ndarray:
    """The order of ``points`` (N, 3) along a Z-order (Morton) curve through a grid of ``2**bits`` cells a
    side over their bounding box: points near each other in space come near each other in the order."""
    low = points.min(axis=0)
    span = float((points.max(axis=0) - low).max()) or 1.0
    cells = ((points - low) / span * (2**bits - 1)).astype(np.int64)
    code = np.zeros(len(points), dtype=np.int64)
    for bit in range(bits):
        for axis in range(3):
            code |= ((cells[:, axis] >> bit) & 1) << (3 * bit + axis)
    return np.argsort(code, kind="stable")


def _digest_seed(text: str) -> int:
    """A 64-bit seed from ``text``, the same on every machine and Python run (unlike ``hash``)."""
    return int.from_bytes(hashlib.sha256(text.encode()).digest()[:8], "little")
