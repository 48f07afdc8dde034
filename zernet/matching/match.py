"""Matching two surfaces: descriptors -> functional map -> point map -> ZoomOut -> confidence, or through a
template model (:mod:`zernet.matching.template`, the default for :func:`match_surfaces`: human bodies),
whose vertices that do not survive the round trip are then mapped again by their geodesic distances to
those that do (:mod:`zernet.matching.consistency`).

A model whose inputs depend on the pose (xyz) and whose spec says ``align_target`` sees the target turned
into the source's frame: the 4 rotations that carry the target's principal axes onto the source's
(:func:`candidate_alignments`) are tried, and the one under whose map the descriptors agree best (the
mean squared distance between a source vertex's descriptor and its image's) is kept. The candidates do not depend on the target's pose, so neither does the match.

:func:`match_shapes` works on two prepared shapes (:func:`zernet.matching.shapes.prepare_shape`);
:func:`match_surfaces` takes two surfaces or files as a user has them, repairs them (merged duplicate
vertices are mapped back) and answers per *input* vertex. Both directions are solved (source -> target and
target -> source, each from its own functional map), because the confidence is the round trip's
agreement (:func:`zernet.matching.fmap.cycle_confidence`) and the picture transfers a colour from the
source onto the target, which needs the target -> source map.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from zernet.geometry import FixedScale, Surface, read_surface, repair_surface
from zernet.inference.model_file import read_model_file
from zernet.matching.consistency import repair_map
from zernet.matching.fmap import cycle_confidence, functional_map, nearest_rows, pointmap_from_fmap, zoomout
from zernet.matching.model import DescriptorModel, load_matching_model
from zernet.matching.shapes import MatchShape, prepare_shape, rotating_columns
from zernet.matching.template import (
    TemplateModel,
    TemplateShape,
    load_template_model,
    match_template_shapes,
    template_shape,
)
from zernet.operators.spectral import fmap_from_pointmap, laplacian_eigenbasis

__all__ = [
    "MatchResult",
    "shape_descriptors",
    "principal_axes",
    "candidate_alignments",
    "descriptor_fmap",
    "match_shapes",
    "match_surfaces",
    "load_matcher",
    "nearest_vertex_map",
    "shared_scale",
    "CONFIDENCE_SCALE",
]

#: Source vertices on which the candidate alignments of the target are compared.
ALIGNMENT_SAMPLE = 1000

#: The round-trip distance, as a fraction of the square root of the source's area, at which the
#: confidence falls to 1/e.
CONFIDENCE_SCALE = 0.05


@dataclass
class MatchResult:
    """A correspondence between a source and a target surface.

    Attributes:
        vertex_map: (N_source,) int64 target vertex of each source vertex.
        reverse_map: (N_target,) int64 source vertex of each target vertex.
        fmap: (k, k) the functional map of ``vertex_map`` after ZoomOut: ``C`` with
            ``Φ_source C ≈ Φ_target[vertex_map]``, i.e. it carries a function on the target (its spectral
            coefficients) to the source.
        confidence: (N_source,) in [0, 1] (:func:`zernet.matching.fmap.cycle_confidence`).
        seconds: time per stage.
    """

    vertex_map: np.ndarray
    reverse_map: np.ndarray
    fmap: np.ndarray
    confidence: np.ndarray
    seconds: dict = field(default_factory=dict)


@torch.no_grad()
def shape_descriptors(model: DescriptorModel, shape: MatchShape, rotation: np.ndarray | None = None) -> torch.Tensor:
    """(N, d) float32 descriptors of a prepared shape; ``rotation`` (3, 3) turns its pose-dependent input
    columns (xyz, normals) first."""
    model.eval()
    features = shape.features
    if rotation is not None:
        features = features.copy()
        n_max = int(model.spec.patch_configs[0].get("n_max", 5))
        for columns in rotating_columns(model.spec.feature_kind, n_max):
            features[:, columns] = features[:, columns] @ rotation.T.astype(np.float32)
    descriptors = model(torch.as_tensor(features, dtype=torch.float32), shape.geometry)
    return descriptors if shape.descriptor_index is None else descriptors[torch.as_tensor(shape.descriptor_index)]


def principal_axes(shape: MatchShape) -> np.ndarray:
    """(3, 3) rows: the area-weighted principal axes of a shape (largest spread first), a right-handed frame."""
    weights = shape.basis.mass / shape.basis.mass.sum()
    centred = shape.surface.vertices - weights @ shape.surface.vertices
    _, vectors = np.linalg.eigh((centred * weights[:, None]).T @ centred)
    axes = vectors[:, ::-1].T
    axes[2] = np.cross(axes[0], axes[1])
    return axes


def candidate_alignments(source: MatchShape, target: MatchShape) -> list[np.ndarray]:
    """The 4 rotations (3, 3) that carry the target's principal frame onto the source's, one per proper
    choice of the axes' signs (the signs of a principal axis are arbitrary; reflections are left out, as a
    mirror image is not a pose). For a target in any rotation, the same 4 candidates result."""
    source_axes, target_axes = principal_axes(source), principal_axes(target)
    signs = [np.diag(s) for s in ((1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1))]
    return [source_axes.T @ sign @ target_axes for sign in signs]


def descriptor_fmap(
    model: DescriptorModel,
    descriptors_x: torch.Tensor,
    descriptors_y: torch.Tensor,
    shape_x: MatchShape,
    shape_y: MatchShape,
) -> torch.Tensor:
    """``C_xy`` (k, k), k = the spec's ``n_fmap``: the functional-map layer on two shapes' descriptors."""
    k = model.spec.n_fmap
    vectors_x, mass_x, values_x = shape_x.basis_tensors(k, descriptors_x.dtype)
    vectors_y, mass_y, values_y = shape_y.basis_tensors(k, descriptors_y.dtype)
    return functional_map(
        descriptors_x,
        descriptors_y,
        vectors_x,
        vectors_y,
        mass_x,
        mass_y,
        values_x,
        values_y,
        model.spec.regularisation,
        model.spec.gamma,
    )


def match_shapes(
    model: DescriptorModel, source: MatchShape, target: MatchShape, zoomout_end: int | None = None
) -> MatchResult:
    """Match two prepared shapes (module docstring). ``zoomout_end``: ZoomOut's last size (None: the spec's;
    0: no ZoomOut)."""
    spec = model.spec
    zoomout_end = spec.zoomout_end if zoomout_end is None else int(zoomout_end)
    seconds = {}
    start = time.perf_counter()
    descriptors_s = shape_descriptors(model, source)
    rotations = candidate_alignments(source, target) if spec.align_target else [None]
    # The alignments are told apart on a fixed sample of source vertices: the full point map is then
    # searched once, for the one kept.
    sample = np.sort(np.random.default_rng(0).permutation(source.n_vertices)[:ALIGNMENT_SAMPLE])
    best = None
    for rotation in rotations:
        descriptors_t = shape_descriptors(model, target, rotation)
        with torch.no_grad():
            fmap_ts = descriptor_fmap(model, descriptors_t, descriptors_s, target, source).double().numpy()
        # C_ts carries target functions to the source, so it gives the point map source -> target.
        images = nearest_rows(
            source.basis.eigenvectors[sample, : spec.n_fmap] @ fmap_ts, target.basis.eigenvectors[:, : spec.n_fmap]
        )
        # How well the descriptors agree under the map: a flipped or upside-down alignment maps
        # consistently (both directions agree) but pairs unlike descriptors.
        disagreement = float(
            ((descriptors_s[torch.as_tensor(sample)] - descriptors_t[torch.as_tensor(images)]) ** 2).sum(dim=1).mean()
        )
        if best is None or disagreement < best[0]:
            best = (disagreement, fmap_ts, descriptors_t)
    _, fmap_ts, descriptors_t = best
    vertex_map = pointmap_from_fmap(fmap_ts, target.basis, source.basis)
    with torch.no_grad():
        fmap_st = descriptor_fmap(model, descriptors_s, descriptors_t, source, target).double().numpy()
    reverse_map = pointmap_from_fmap(fmap_st, source.basis, target.basis)
    seconds["descriptors+fmap"] = time.perf_counter() - start
    start = time.perf_counter()
    # ZoomOut refines the answer (source -> target); the reverse map serves the confidence and the
    # picture and keeps the layer's resolution (ZoomOut in both directions doubled the time).
    refined_ts = None
    if zoomout_end > spec.n_fmap:
        features = None
        if spec.zoomout_descriptor_weight > 0:
            # Descriptors in units of their typical length on the source, times the weight.
            scale = spec.zoomout_descriptor_weight / float(descriptors_s.square().sum(dim=1).mean().sqrt())
            features = (scale * descriptors_s.double().numpy(), scale * descriptors_t.double().numpy())
        vertex_map, refined_ts = zoomout(
            vertex_map,
            target.basis,
            source.basis,
            spec.n_fmap,
            zoomout_end,
            spec.zoomout_step,
            features=features,
        )
    seconds["zoomout"] = time.perf_counter() - start
    scale = CONFIDENCE_SCALE * np.sqrt(source.surface.area)
    confidence = cycle_confidence(vertex_map, reverse_map, source.surface.vertices, scale)
    return MatchResult(vertex_map, reverse_map, fmap_ts if refined_ts is None else refined_ts, confidence, seconds)


def nearest_vertex_map(source: MatchShape, target: MatchShape) -> np.ndarray:
    """(N_source,) the target vertex nearest in space to each source vertex, both centred on their
    area-weighted centroids at the same area: the rigid initial map of the "ZoomOut alone" baseline (it
    assumes the two shapes are already aligned)."""

    def centred(shape: MatchShape) -> np.ndarray:
        weights = shape.basis.mass
        return shape.surface.vertices - weights @ shape.surface.vertices / weights.sum()

    _, nearest = cKDTree(centred(target)).query(centred(source))
    return np.asarray(nearest, dtype=np.int64)


def _load_input(surface: Surface | str | os.PathLike):
    """A repaired surface and the map from the input's vertices to it."""
    if not hasattr(surface, "vertices"):
        surface = read_surface(surface)
    return repair_surface(surface)


def load_matcher(path: str | os.PathLike | None = None) -> TemplateModel | DescriptorModel:
    """The model in a file or run folder: a template model (:mod:`zernet.matching.template`) or a descriptor
    model (:func:`zernet.matching.model.load_matching_model`); None: the shipped template model."""
    if path is None:
        return load_template_model()
    path = Path(path)
    if path.is_file():
        try:
            kind = read_model_file(path)["kind"]
        except ValueError:  # load_matching_model names what is wrong with the file
            kind = None
        if kind == "template":
            return load_template_model(path)
    return load_matching_model(path)[0]


def match_surfaces(
    source: Surface | str | os.PathLike,
    target: Surface | str | os.PathLike,
    model: TemplateModel | DescriptorModel | str | os.PathLike | None = None,
    cache_dir: str | os.PathLike | None = None,
    zoomout_end: int | None = None,
    same_scale: bool = False,
    repair: bool = True,
) -> tuple[MatchResult, MatchShape | TemplateShape, MatchShape | TemplateShape]:
    """Match two surfaces or files, answering per input vertex.

    Args:
        source, target: :class:`~zernet.geometry.Surface` objects or mesh / point-cloud files (PLY, OBJ,
            OFF, STL, ...), in any pose, placement and scale; repaired where they can be (duplicate vertices
            merged, degenerate faces dropped).
        model: a :class:`~zernet.matching.template.TemplateModel` (human bodies, through the template the
            classifier names), a :class:`DescriptorModel` (descriptors and functional maps), a file or run
            folder holding either (:func:`load_matcher`), or None: the shipped template model.
        cache_dir: cache of patch operators and eigenbases (None: nothing cached).
        zoomout_end: see :func:`match_shapes` (descriptor models only).
        same_scale: the two are in the same units (two scans from one scanner, one of them partial): both
            are scaled by the one factor that brings the larger to the model's area, instead of each to that
            area, so a part keeps its size (scaled up to the model's area, a one-sided scan reads as a body
            half again as large) and is matched into the whole.

    Returns:
        (result, prepared source, prepared target): ``result.vertex_map`` has one entry per *input* source
        vertex, an index into the *input* target's vertices (likewise ``reverse_map`` and ``confidence``);
        the prepared shapes are the repaired surfaces, for pictures.
    """
    if not isinstance(model, (DescriptorModel, TemplateModel)):
        model = load_matcher(model)
    start = time.perf_counter()
    repaired_source, repaired_target = _load_input(source), _load_input(target)
    model_area = model.area if isinstance(model, TemplateModel) else model.spec.area
    surfaces = [repaired_source.surface, repaired_target.surface]
    area = shared_scale(model_area, surfaces) if same_scale else model_area
    if isinstance(model, TemplateModel):
        result, prepared = _match_through_template(model, surfaces, area, cache_dir, repair)
        return _per_input_vertex(result, prepared, repaired_source, repaired_target), *prepared
    spec = model.spec
    prepared = [
        prepare_shape(
            item.surface,
            spec.patch_config_objects(),
            area,
            spec.feature_kind,
            spec.n_eigen,
            cache_dir=cache_dir,
            name=Path(item.surface.name).stem,
            descriptor_vertices=spec.descriptor_vertices,
        )
        for item in (repaired_source, repaired_target)
    ]
    prepare_seconds = time.perf_counter() - start
    result = match_shapes(model, prepared[0], prepared[1], zoomout_end)
    result.seconds = {"prepare": prepare_seconds, **result.seconds}
    return _per_input_vertex(result, prepared, repaired_source, repaired_target), prepared[0], prepared[1]


#: Eigenpairs of the functional map a template match is also given as.
TEMPLATE_FMAP_SIZE = 80

#: With ``same_scale``, a surface of less than this share of the other's area is a part of it (a one-sided
#: scan), and the template map is not repaired: the repair compares distances along the surfaces, which a
#: part does not keep (its paths cannot cross the missing side). Repaired, 2 one-sided scans of generated
#: test bodies went from 1.73 and 3.06 to 2.52 and 8.83.
PART_AREA_RATIO = 0.8


def _match_through_template(
    model: TemplateModel, surfaces: list[Surface], area, cache_dir, repair: bool = True
) -> tuple[MatchResult, list[TemplateShape]]:
    """Match two repaired surfaces through the template model (:mod:`zernet.matching.template`), then, with
    ``repair`` and unless one is a part of the other (:data:`PART_AREA_RATIO`), map again each direction's
    vertices that fail its checks (:func:`repair_map`); the result's functional map is the point map's, on the
    first 80 eigenfunctions of each surface."""
    start = time.perf_counter()
    prepared = [template_shape(model, surface, area, cache_dir) for surface in surfaces]
    seconds = {"template positions": time.perf_counter() - start}
    scale = CONFIDENCE_SCALE * np.sqrt(prepared[0].surface.area)
    vertex_map, reverse_map, confidence, seconds["point maps"] = match_template_shapes(*prepared, scale)
    source, target = prepared[0].surface, prepared[1].surface
    if repair and min(source.area, target.area) >= PART_AREA_RATIO * max(source.area, target.area):
        start = time.perf_counter()
        reverse_confidence = cycle_confidence(reverse_map, vertex_map, target.vertices, scale)
        vertex_map, _ = repair_map(source, target, vertex_map, confidence)
        reverse_map, _ = repair_map(target, source, reverse_map, reverse_confidence)
        confidence = cycle_confidence(vertex_map, reverse_map, source.vertices, scale)
        seconds["repair"] = time.perf_counter() - start
    start = time.perf_counter()
    bases = [
        laplacian_eigenbasis(
            Surface(shape.surface.vertices, shape.surface.faces, name=shape.surface.name),
            TEMPLATE_FMAP_SIZE,
            cache_dir=cache_dir,
        )
        for shape in prepared
    ]
    fmap = fmap_from_pointmap(vertex_map, bases[1], bases[0])
    seconds["functional map"] = time.perf_counter() - start
    return MatchResult(vertex_map, reverse_map, fmap, confidence, seconds), prepared


def _per_input_vertex(result: MatchResult, prepared, repaired_source, repaired_target) -> MatchResult:
    """The result on the input surfaces' vertices (before the repair)."""
    # Back to input vertices: a merged duplicate answers with its kept copy; a repaired vertex is answered
    # with one of the input vertices merged into it.
    first_target = _first_input_vertex(repaired_target.vertex_map, prepared[1].surface.n_vertices)
    first_source = _first_input_vertex(repaired_source.vertex_map, prepared[0].surface.n_vertices)
    result.vertex_map = first_target[result.vertex_map[repaired_source.vertex_map]]
    result.reverse_map = first_source[result.reverse_map[repaired_target.vertex_map]]
    result.confidence = result.confidence[repaired_source.vertex_map]
    return result


def shared_scale(area: float, surfaces: list[Surface]) -> FixedScale:
    """The one factor that brings the largest of ``surfaces`` to ``area`` (``same_scale``: surfaces in the same
    units, one of them a part of another)."""
    return FixedScale(float(np.sqrt(area / max(surface.area for surface in surfaces))))


def _first_input_vertex(vertex_map: np.ndarray, n_repaired: int) -> np.ndarray:
    """(n_repaired,) the first input vertex that went to each repaired vertex."""
    first = np.full(n_repaired, -1, dtype=np.int64)
    inputs = np.arange(len(vertex_map), dtype=np.int64)
    first[vertex_map[::-1]] = inputs[::-1]  # later writes win: reversed, the first input is kept
    return first
