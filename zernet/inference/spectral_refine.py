"""Refining a predicted correspondence globally: the prediction kept within reach of a spectral map.

The rings (:mod:`zernet.inference.refine`) repair a vertex its neighbourhood disagrees with; a whole region
mapped to the wrong place (a knee on the other knee, a hand on the belly) is its own neighbourhood and stays.
This step reads the map as a whole, through functional maps (Ovsjanikov et al. 2012) between the shape's and
the template's Laplace-Beltrami eigenbases, upsampled as ZoomOut does (Melzi et al. 2019), with the pure
pieces of :mod:`zernet.operators.spectral`:

1. ``T``: the predicted map shape -> template (the argmax of the ring-refined scores ``Q``), and each
   vertex's confidence (its largest score);
2. for ``k`` from :data:`K_START` to :data:`K_END` by :data:`K_STEP`: the k × k functional map ``C`` that
   best explains ``T`` (a least squares; in the first round each vertex weighted by its confidence,
   :func:`~zernet.operators.spectral.fmap_from_pointmap`), its point map ``S`` (nearest neighbours in the
   spectral embedding), and the new ``T``: for each vertex the argmax of ``Q`` among the template vertices
   within ``radius`` (a fraction of the template's geodesic diameter, along its mesh edges) of ``S(i)``.

At 10 eigenpairs a flipped region of a few percent of the vertices barely moves ``C``, which the rest of the
body decides (the body's left-right symmetry, which the eigenfunctions alone cannot tell apart, is settled by
the network's map), so ``S`` sends the region to the right side, and ``T`` takes the most probable vertex
there; each later round adds frequencies, so ``S`` comes closer and the radius catches fewer wrong vertices.
Unlike plain ZoomOut, whose point map after the first round no longer reads the network, every round keeps
the network's answer where it lies near the spectral one: on the validation bodies of a coarse run, ZoomOut's
own map (20 to 80 eigenpairs) left 0.42 % of the vertices beyond 10 % of the diameter; with these rounds none
was left there (``docs/RECIPES.md``). On an ellipsoid with a mirrored cap of 9.5 % of its vertices, a single
projection of the map still sends part of the cap across; the rounds repair caps of 5-16 %
(``tests/training/test_spectral_refine.py``). A vertex whose scores near ``S(i)`` are all below 1e-6 takes
``S(i)`` itself.

The radius is chosen on validation shapes (``eval.refine_spectral``; 0 turns the step off) after the ring
count. It needs the template's geometry: a run stores the vertices of its first training shape beside the
template's faces (``template_vertices`` in the checkpoint); older checkpoints hold only the faces, and the
step is then unavailable (:func:`template_of`).

Cost: two eigenbases (the template's once per run, the shape's with ``eigsh`` once per shape, on the host,
scipy), then per round a k × k solve on the host and, on the scores' device (the run's device), one
nearest-neighbour search in the spectral embedding (float32) and one masked argmax of the (N, M) scores. The
template's neighbourhoods (one Dijkstra per template vertex, bounded by the radius) are built once per
(template, radius, device) and kept.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict

import numpy as np
import torch

from zernet.geometry import Surface
from zernet.inference.template_graph import edge_graph, edge_neighbourhoods, padded_neighbourhoods
from zernet.metrics import geodesic_diameter
from zernet.operators.spectral import SpectralBasis, fmap_from_pointmap, laplacian_eigenbasis, pointmap_from_fmap

__all__ = [
    "K_START",
    "K_END",
    "K_STEP",
    "SpectralRefiner",
    "spectral_refiner",
    "template_of",
    "check_radii",
]

#: Eigenpairs of the first round's functional map (the one read from the network's map) and of the last.
K_START = 10
K_END = 80
#: Eigenpairs added per round.
K_STEP = 5
#: A vertex whose scores within the radius are all below this takes the spectral map's own answer.
_FALLBACK = 1e-6


def check_radii(radii) -> list[float]:
    """The candidate radii as floats; ValueError unless each is a number in [0, 1]."""
    values = [radii] if isinstance(radii, (int, float)) and not isinstance(radii, bool) else list(radii)
    if not values or any(isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 <= v <= 1 for v in values):
        raise ValueError(f"refine_spectral radii must be one or more numbers in [0, 1], got {radii!r}")
    return [float(v) for v in values]


def template_of(checkpoint: dict) -> tuple[np.ndarray, np.ndarray] | None:
    """(vertices, faces) of the template a correspondence checkpoint stores, or None when it stores no geometry
    (checkpoints written before the global refinement: only ``template_faces``)."""
    vertices, faces = checkpoint.get("template_vertices"), checkpoint.get("template_faces")
    if vertices is None or faces is None:
        return None
    return np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64)


class SpectralRefiner:
    """The global refinement against one template (module docstring). Build it with :func:`spectral_refiner`,
    which keeps one per template."""

    def __init__(
        self, vertices: np.ndarray, faces: np.ndarray, k_start: int = K_START, k_end: int = K_END, step: int = K_STEP
    ):
        self.template = Surface(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64))
        self.k_start, self.k_end, self.step = int(k_start), int(k_end), int(step)
        self.basis = laplacian_eigenbasis(self.template, self.k_end)
        self.diameter = geodesic_diameter(self.template.vertices, self.template.faces)
        self._graph = edge_graph(self.template.vertices, self.template.faces)
        self._neighbourhoods: OrderedDict[tuple, torch.Tensor] = OrderedDict()
        self._shape_bases: OrderedDict[str, SpectralBasis] = OrderedDict()

    @property
    def n_vertices(self) -> int:
        return self.template.n_vertices

    def neighbourhood(self, radius: float, device) -> torch.Tensor:
        """(M, K) int64 on ``device``: row ``i`` lists the template vertices within ``radius`` × the diameter
        of vertex ``i`` along the mesh edges (a Dijkstra per vertex, bounded), padded with ``i`` itself to the
        longest list; kept per radius and device."""
        key = (float(radius), str(torch.device(device)))
        if key not in self._neighbourhoods:
            table, _ = padded_neighbourhoods(edge_neighbourhoods(self._graph, float(radius) * self.diameter))
            self._neighbourhoods[key] = torch.from_numpy(table).to(device)
            while len(self._neighbourhoods) > 4:
                self._neighbourhoods.popitem(last=False)
        return self._neighbourhoods[key]

    def shape_basis(self, surface: Surface) -> SpectralBasis:
        """The shape's eigenbasis (``k_end`` eigenpairs), kept for the last few shapes (a validation shape is
        refined once per candidate radius)."""
        key = surface.geometry_hash()
        if key not in self._shape_bases:
            self._shape_bases[key] = laplacian_eigenbasis(surface, self.k_end)
            while len(self._shape_bases) > 4:
                self._shape_bases.popitem(last=False)
        self._shape_bases.move_to_end(key)
        return self._shape_bases[key]

    def restrict(self, scores: torch.Tensor, spectral_map: np.ndarray, radius: float) -> torch.Tensor:
        """(N,) int64 on the scores' device: the argmax of each row among the template vertices within
        ``radius`` (× the diameter) of its spectral image; the image itself where every score there is below
        1e-6."""
        images = torch.as_tensor(spectral_map, device=scores.device)
        candidates = self.neighbourhood(radius, scores.device)[images]  # (N, K)
        values, best = scores.gather(1, candidates).max(dim=1)
        chosen = candidates.gather(1, best[:, None]).squeeze(1)
        return torch.where(values >= _FALLBACK, chosen, images)

    def refine(self, scores: torch.Tensor, surface: Surface, radius: float) -> np.ndarray:
        """(N,) int64 the globally refined map (module docstring) of the (ring-refined) ``scores`` (N, M) of
        ``surface``, computed where the scores are; radius 0: their argmax."""
        if radius <= 0:
            return scores.argmax(dim=1).cpu().numpy()
        if surface.faces is None:
            raise ValueError(f"{surface.name}: the global refinement needs a triangle mesh, not a point cloud")
        if tuple(scores.shape) != (surface.n_vertices, self.n_vertices):
            raise ValueError(
                f"scores have shape {tuple(scores.shape)}, expected ({surface.n_vertices}, {self.n_vertices})"
            )
        basis = self.shape_basis(surface)
        confidence, predicted = scores.max(dim=1)
        pointmap, weights = predicted.cpu().numpy(), confidence.double().cpu().numpy()
        k_end = min(self.k_end, basis.k, self.basis.k)
        for k in range(min(self.k_start, k_end), k_end + 1, self.step):
            fmap = fmap_from_pointmap(pointmap, self.basis, basis, k, k, weights=weights)
            weights = None  # later rounds read maps the radius has already cleaned
            spectral_map = pointmap_from_fmap(fmap, self.basis, basis, device=scores.device)
            pointmap = self.restrict(scores, spectral_map, radius).cpu().numpy()
        return pointmap


_REFINERS: OrderedDict[str, SpectralRefiner] = OrderedDict()


def spectral_refiner(vertices: np.ndarray, faces: np.ndarray) -> SpectralRefiner:
    """The :class:`SpectralRefiner` of a template, built once per template (vertices and faces) and kept."""
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    key = hashlib.sha1(vertices.tobytes() + faces.tobytes() + str((vertices.shape, faces.shape)).encode()).hexdigest()
    if key not in _REFINERS:
        _REFINERS[key] = SpectralRefiner(vertices, faces)
        while len(_REFINERS) > 2:
            _REFINERS.popitem(last=False)
    return _REFINERS[key]
