"""Matching two human bodies through a template: a classifier names where on the body each point lies.

A template model is a zernet classifier trained to name, for every vertex or point of a body in any form
(a mesh of any triangulation, a noisy point cloud, a one-sided scan), the vertex of a template body it lies
at (generated bodies in every form, :func:`zernet.data.bodies.forms.make_forms`, labelled with the template
vertex through their barycentric ground truth). Each vertex of a surface is then given a **template
position**: the mean of the template vertices' rest positions weighted by its class probabilities (a
vertex torn between two neighbouring classes lands between them), and two surfaces are matched by pairing
nearest template positions. Nothing assumes the two are isometric, unlike a functional map and ZoomOut
(:mod:`zernet.matching.match`), and a part of a body (a one-sided scan) reads its own positions, unlike a
spectral method, whose eigenbasis changes with the missing side.

Pose. The classifier reads positions, in the frame its training bodies were generated in (y up, facing
+z), so every surface is turned into it: the candidates are the rotations that carry its principal axes
onto those of the training frame (:func:`candidate_rotations`), and the one under which the classifier is
most confident (its mean top probability) is kept, then refined by rigid fits onto the template positions
it was read at and finished by a search on the confidence itself. Every step starts from the principal
axes, never from the frame the file was written in, so the match does not depend on how either surface was
turned. (Reading a surface as given when that was more confident gained 0.03 on validation pairs already
in the training frame and cost 0.26 on the same pairs turned.)

Resolution. Like the descriptor model, the classifier reads a surface of more than 1.5 times
``coarse_vertices`` through a coarse copy (:func:`zernet.geometry.coarsen_surface`); every vertex takes the
template position interpolated from its nearest copy vertices (inverse distance, 4 of them).

Smoothing. The classifier answers each vertex on its own; the template positions are then smoothed along the
surface by a short heat diffusion (:func:`zernet.operators.spectral.heat_smoothed`,
:data:`SMOOTHING_TIME`), which averages out its independent errors (a third off the mean matching error between remeshed bodies).

A template model file is a model file of kind ``template`` (:mod:`zernet.inference.model_file`):
``{"model_spec", "model" (state dict), "patch_configs", "feature_kind", "feature_stats", "area",
"coarse_vertices", "template_positions" (C, 3), "provenance"}`` beside the format fields; made from a
training run by :func:`save_template_model`. The model shipped with zernet is
:data:`PRETRAINED_TEMPLATE_MODEL`.
"""

from __future__ import annotations

import functools
import hashlib
import io
import os
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from zernet.data import prepare_record
from zernet.data.features import register_input_part
from zernet.geometry import FixedScale, Surface, SurfaceWarning, coarsen_surface
from zernet.inference.batch import Batch, model_basis_orders, model_directional_order
from zernet.inference.model_file import model_file, pretrained_path, read_model_file
from zernet.inference.spec import build_model_from_spec
from zernet.inference.targets import standardise_features
from zernet.io_utils import atomic_save_torch, atomic_write_bytes, plain
from zernet.matching.fmap import cycle_confidence
from zernet.matching.shapes import rotating_columns
from zernet.operators import PatchConfig
from zernet.operators.cache import CacheWarning
from zernet.operators.spectral import heat_smoothed

__all__ = [
    "PRETRAINED_TEMPLATE_MODEL",
    "TEMPLATE_PART_MODEL",
    "TemplateModel",
    "TemplateShape",
    "save_template_model",
    "load_template_model",
    "candidate_rotations",
    "template_shape",
    "match_template_shapes",
    "body_template_positions",
]

#: The template model shipped in the package, the one ``zernet match`` uses (trained on generated bodies
#: only; provenance beside it).
PRETRAINED_TEMPLATE_MODEL = pretrained_path("bodies-match-template")

#: The template model the ``template`` input part reads (:func:`body_template_positions`): the first template
#: model, kept when ``zernet match`` moved to a better one, because models trained on that part (the shipped
#: ``bodies-faust-template``, users' runs) learnt its positions, and a part must mean what it meant.
TEMPLATE_PART_MODEL = pretrained_path("bodies-template-part")

#: Rigid refinements of the chosen alignment (each one more pass of the classifier).
ALIGNMENT_STEPS = 3

#: Angles (degrees) of the confidence search that finishes the turn, coarse to fine (one parabolic step per
#: axis at each: 7 passes of the classifier; 1.31 -> 0.94 mean error on the validation pairs).
CONFIDENCE_SEARCH_DEGREES = (8.0, 4.0, 2.0)

#: Copy vertices a template position is interpolated from.
INTERPOLATION_NEIGHBOURS = 4

#: Heat diffusion time the template positions are smoothed for along the surface, as a fraction of the
#: model's area (10 at 15,000, in the units a whole body is read at: a few edge lengths at 5,000 vertices).
#: The classifier's neighbouring answers are independent guesses; averaging them took validation pairs from
#: 1.66 to 1.06 remeshed, 2.52 to 1.95 as noisy clouds and 2.62 to 2.40 as one-sided scans (times 5-20
#: within 0.1 on meshes and clouds; longer blurs the rim of a one-sided scan).
SMOOTHING_TIME = 10.0 / 15000.0

#: The training frame's principal axes, largest spread first (rows): up (y), across the shoulders (x), and
#: front to back (z) to make a right-handed frame.
TRAINING_AXES = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


@dataclass
class TemplateModel:
    """A loaded template model (module docstring)."""

    network: torch.nn.Module
    patch_configs: list[PatchConfig]
    feature_kind: str
    feature_stats: dict | None
    area: float
    coarse_vertices: int | None
    template_positions: np.ndarray  # (C, 3) rest positions of the template vertices (the classes)
    provenance: dict

    @property
    def n_classes(self) -> int:
        return len(self.template_positions)


@dataclass
class TemplateShape:
    """A surface read by a template model.

    Attributes:
        surface: the surface scaled as the model reads it (to its area, or by a fixed factor).
        positions: (N, 3) template position of each vertex.
        confidence: (N,) the classifier's top probability (on the copy's vertex nearest each vertex).
        rotation: (3, 3) the turn applied to its pose-dependent inputs (into the training frame).
    """

    surface: Surface
    positions: np.ndarray
    confidence: np.ndarray
    rotation: np.ndarray

    @property
    def n_vertices(self) -> int:
        return self.surface.n_vertices


def save_template_model(run_checkpoint: dict, template_positions: np.ndarray, path, provenance: dict) -> Path:
    """Write a template model file from a training run's checkpoint (a classifier whose classes are the
    template's vertices) and the template's rest positions (C, 3); weights in float16."""
    preprocess = run_checkpoint["preprocess"]
    if run_checkpoint["task"] != "classification" or run_checkpoint["num_classes"] != len(template_positions):
        raise ValueError(
            f"a template model needs a classifier with one class per template vertex "
            f"({len(template_positions)}), got a {run_checkpoint['task']} model with "
            f"{run_checkpoint.get('num_classes')} classes"
        )
    unit_scale = preprocess.get("unit_scale")
    area = preprocess["area"]
    if area is None:  # trained at a fixed scale: surfaces are brought to the training bodies' median area
        area = provenance["training_area"]
    contents = {
        "model_spec": plain(run_checkpoint["model_spec"]),
        "model": {key: value.half() for key, value in run_checkpoint["model"].items()},
        "patch_configs": plain(preprocess["patch_configs"]),
        "feature_kind": preprocess["feature_kind"],
        "feature_stats": plain(run_checkpoint.get("feature_stats")),
        "area": float(area),
        "coarse_vertices": provenance.get("coarse_vertices"),
        "template_positions": torch.as_tensor(np.asarray(template_positions, dtype=np.float32)),
        "provenance": plain({**provenance, "unit_scale": unit_scale}),
    }
    path = Path(path)
    atomic_save_torch(model_file("template", contents), path)
    return path


def load_template_model(path: str | os.PathLike | None = None, device: str | torch.device = "cpu") -> TemplateModel:
    """A template model from its file (None: the shipped one)."""
    path = PRETRAINED_TEMPLATE_MODEL if path is None else Path(path)
    payload = read_model_file(path, ("template",), "zernet template model")
    network = build_model_from_spec(payload["model_spec"])
    network.load_state_dict({key: value.float() for key, value in payload["model"].items()})
    network.to(device).eval()
    return TemplateModel(
        network,
        [PatchConfig(**config) for config in payload["patch_configs"]],
        payload["feature_kind"],
        payload["feature_stats"],
        float(payload["area"]),
        payload["coarse_vertices"],
        payload["template_positions"].double().numpy(),
        payload["provenance"],
    )


def principal_frame(vertices: np.ndarray) -> np.ndarray:
    """(3, 3) rows: the principal axes of a point set, largest spread first, right-handed."""
    centred = vertices - vertices.mean(axis=0)
    _, vectors = np.linalg.eigh(centred.T @ centred)
    axes = vectors[:, ::-1].T.copy()
    axes[2] = np.cross(axes[0], axes[1])
    return axes


def candidate_rotations(vertices: np.ndarray) -> list[np.ndarray]:
    """Rotations (3, 3) to try on a surface: the 8 that carry its principal axes onto :data:`TRAINING_AXES`:
    4 proper choices of the axes' signs, with the second and third axes in either order (a posed body can be
    deeper than it is wide)."""
    axes = principal_frame(vertices)
    swapped = np.array([axes[0], axes[2], -axes[1]])  # still right-handed
    signs = [np.diag(s) for s in ((1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1))]
    return [TRAINING_AXES.T @ sign @ frame for frame in (axes, swapped) for sign in signs]


@torch.no_grad()
def template_shape(
    model: TemplateModel,
    surface: Surface,
    area: float | FixedScale | None = None,
    cache_dir: str | os.PathLike | None = None,
    smoothing: float | None = None,
) -> TemplateShape:
    """Read ``surface`` with the template model: the template position of every vertex (module docstring).

    ``area``: the area the surface is scaled to (None: the model's), or a
    :class:`~zernet.geometry.FixedScale` (a surface matched as a part of another in the same units).
    ``smoothing``: the heat diffusion time of the positions, in the scaled surface's units (None:
    :data:`SMOOTHING_TIME` times the model's area; 0: none).
    """
    area = model.area if area is None else area
    factor = area.factor if isinstance(area, FixedScale) else float(np.sqrt(area / surface.area))
    surface = Surface(surface.vertices * factor, surface.faces, name=surface.name)
    coarse = None
    with warnings.catch_warnings():
        # The copy is the matcher's own: what a simplifier leaves in it (non-manifold edges) is not the user's.
        warnings.simplefilter("ignore", SurfaceWarning)
        if model.coarse_vertices and surface.n_vertices > 1.5 * model.coarse_vertices:
            coarse = coarsen_surface(surface, model.coarse_vertices)
        read = surface if coarse is None else coarse.surface
        record = prepare_record(
            read, model.patch_configs, cache_dir=cache_dir, target_area=FixedScale(1.0), feature_kind=model.feature_kind
        )
    device = next(model.network.parameters()).device
    batch = Batch(
        [record], device, None, None, model_directional_order(model.network), model_basis_orders(model.network)
    )
    n_max = model.patch_configs[0].n_max
    template = torch.as_tensor(model.template_positions, device=device)

    def read_turned(rotation: np.ndarray):
        """(mean top probability, template positions (n, 3), top probabilities (n,), rotation)."""
        features = np.array(record.features, dtype=np.float32)
        for columns in rotating_columns(model.feature_kind, n_max):
            features[:, columns] = features[:, columns] @ rotation.T.astype(np.float32)
        inputs = torch.from_numpy(features).to(device)
        if model.feature_stats is not None:
            inputs = standardise_features(inputs, model.feature_stats)
        probabilities = torch.softmax(model.network(inputs, batch.geometry).float(), dim=1)
        top = probabilities.max(dim=1).values
        positions = (probabilities.double() @ template).cpu().numpy()
        return float(top.mean()), positions, top.cpu().numpy(), rotation

    best = max((read_turned(rotation) for rotation in candidate_rotations(record.surface.vertices)), key=lambda r: r[0])
    # A principal frame is only roughly the training frame: the turn that best carries the surface onto the
    # template positions it was read at (weighted by confidence) is tried next, while it helps.
    for _ in range(ALIGNMENT_STEPS):
        turned = read_turned(_fitted_rotation(record.surface.vertices, best[1], best[2]))
        if turned[0] <= best[0]:
            break
        best = turned
    # The rigid fit is onto rest-pose positions, which a posed body only roughly follows: the turn is finished
    # on the confidence itself, one parabolic step per axis of the training frame, halving the angle.
    for degrees in CONFIDENCE_SEARCH_DEGREES:
        angle = np.radians(degrees)
        tried, step = [], np.zeros(3)
        for axis in range(3):
            plus, minus = (read_turned(_turn(sign * angle * np.eye(3)[axis]) @ best[3]) for sign in (1, -1))
            tried += [plus, minus]
            slope, curvature = (plus[0] - minus[0]) / 2, plus[0] + minus[0] - 2 * best[0]
            step[axis] = angle * (np.clip(-slope / curvature, -1, 1) if curvature < 0 else np.sign(slope))
        tried.append(read_turned(_turn(step) @ best[3]))
        best = max([best, *tried], key=lambda read: read[0])
    _, positions, confidence, rotation = best
    if coarse is not None:
        positions, confidence = _interpolated(read.vertices, surface.vertices, positions, confidence)
    positions = heat_smoothed(surface, positions, SMOOTHING_TIME * model.area if smoothing is None else smoothing)
    return TemplateShape(surface, positions, confidence, rotation)


def _turn(rotation_vector: np.ndarray) -> np.ndarray:
    """(3, 3) the rotation about ``rotation_vector`` by its length (radians)."""
    return Rotation.from_rotvec(rotation_vector).as_matrix()


def _fitted_rotation(vertices: np.ndarray, positions: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(3, 3) the rotation R minimising the weighted squared distances between R (centred ``vertices``) and the
    centred template ``positions`` (Kabsch)."""
    weights = weights / weights.sum()
    x = vertices - weights @ vertices
    y = positions - weights @ positions
    u, _, vt = np.linalg.svd((y * weights[:, None]).T @ x)
    return u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt


def _interpolated(copy_vertices, vertices, positions, confidence) -> tuple[np.ndarray, np.ndarray]:
    """Template positions (inverse-distance weighted) and confidences (nearest) of a coarse copy carried to
    the surface's own vertices."""
    distances, nearest = cKDTree(copy_vertices).query(vertices, k=INTERPOLATION_NEIGHBOURS)
    weights = 1.0 / np.maximum(distances, 1e-12 * max(float(np.ptp(copy_vertices)), 1e-300))
    weights /= weights.sum(axis=1, keepdims=True)
    return np.einsum("nk,nkd->nd", weights, positions[nearest]), confidence[nearest[:, 0]]


def match_template_shapes(source: TemplateShape, target: TemplateShape, confidence_scale: float):
    """(vertex_map source -> target, reverse_map, confidence): nearest template positions both ways; the
    confidence is the round trip's agreement (:func:`zernet.matching.fmap.cycle_confidence`, distances over
    ``confidence_scale``, in the source's units)."""
    start = time.perf_counter()
    _, vertex_map = cKDTree(target.positions).query(source.positions)
    _, reverse_map = cKDTree(source.positions).query(target.positions)
    vertex_map, reverse_map = np.asarray(vertex_map, np.int64), np.asarray(reverse_map, np.int64)
    confidence = cycle_confidence(vertex_map, reverse_map, source.surface.vertices, confidence_scale)
    return vertex_map, reverse_map, confidence, time.perf_counter() - start


@functools.cache
def _template_part_model() -> tuple[TemplateModel, str]:
    """The template part's model (:data:`TEMPLATE_PART_MODEL`), loaded once per process, and the sha256 of its
    file (a cache key)."""
    digest = hashlib.sha256(TEMPLATE_PART_MODEL.read_bytes()).hexdigest()
    return load_template_model(TEMPLATE_PART_MODEL), digest


def body_template_positions(surface: Surface, cache_dir: str | os.PathLike | None = None) -> np.ndarray:
    """(N, 3) float32 template position of every vertex of a human body (mesh or cloud, any pose, any
    scale) read by the template part's model (:data:`TEMPLATE_PART_MODEL`, :func:`template_shape`), in the
    surface's units (the template body scaled as the surface is); read from / written to ``cache_dir``/template
    when given (keyed by the geometry and the model file).

    Why: the positions are in the template's rest pose, so they are nearly the same for one place on any
    person in any pose (spread 0.7 % of the height across 100 generated bodies): a person-invariant input
    for models trained on a few people (the "template" feature part, :mod:`zernet.data.features`).
    """
    model, model_digest = _template_part_model()
    path = None
    if cache_dir is not None:
        key = hashlib.sha256(f"{surface.geometry_hash()}:{model_digest}".encode()).hexdigest()
        path = Path(cache_dir) / "template" / f"{key}.npz"
        if path.exists():
            try:
                with np.load(path, allow_pickle=False) as stored:
                    if str(stored["key"]) == key and stored["positions"].shape == (surface.n_vertices, 3):
                        return stored["positions"]
                raise ValueError("stored for another surface")
            except (ValueError, OSError, KeyError, EOFError) as error:
                warnings.warn(f"rebuilding cached template positions {path}: {error}", CacheWarning, stacklevel=2)
    # In the surface's units, as if the template body were scaled like the surface (the model reads bodies
    # scaled by unit_scale from the template's metres, to its area), so the part sits beside xyz.
    scale = (model.provenance.get("unit_scale") or 1.0) * np.sqrt(surface.area / model.area)
    positions = (template_shape(model, surface, cache_dir=cache_dir).positions * scale).astype(np.float32)
    if path is not None:
        buffer = io.BytesIO()
        np.savez(buffer, positions=positions, key=np.asarray(key))
        atomic_write_bytes(path, buffer.getvalue())
    return positions


def _template_part(surface: Surface, operators, cache_dir) -> np.ndarray:
    """The "template" input part (:mod:`zernet.data.features`): :func:`body_template_positions`."""
    return body_template_positions(surface, cache_dir)


# Registered here, not in zernet.data: the part runs a trained model, a layer above the data sets.
register_input_part("template", 3, _template_part)
