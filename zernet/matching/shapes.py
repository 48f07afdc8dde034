"""One surface made ready for matching: validated, area-normalised, with its patch operators, input
features, descriptor-model geometry and Laplace-Beltrami eigenbasis (:func:`prepare_shape`).

The same function prepares the training bodies and a user's files, so the model always sees inputs made
the same way. The steps are those of :func:`zernet.data.prepare_record` (validation, a point cloud
triangulated through its own points for the geodesic patches, scaling to the model's area, operators and
features, all cached), plus the eigenbasis: of the mesh, or for a point cloud of the points themselves
(robust-laplacian's point-cloud Laplacian: the triangulation serves the patches, not the spectrum).
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass

import numpy as np
import torch

from zernet.data import prepare_record
from zernet.data.features import HKS_TIMES, feature_parts, feature_slices
from zernet.geometry import FixedScale, Surface, SurfaceWarning, coarsen_surface, validate_surface
from zernet.operators import Geometry, PatchConfig
from zernet.operators.spectral import SpectralBasis, heat_kernel_signature, laplacian_eigenbasis

__all__ = ["MatchShape", "prepare_shape", "input_features", "rotating_columns"]


@dataclass
class MatchShape:
    """A surface ready for matching.

    Attributes:
        name: the surface's name.
        surface: the validated surface scaled to the model's area (a point cloud: triangulated through its
            points, unless the model reads a coarse copy; same vertices, same order as the surface handed to
            :func:`prepare_shape`).
        scale: the linear factor applied to the input's coordinates.
        is_point_cloud: whether the input had no faces.
        features: (N, C) float32 model inputs (:func:`input_features`).
        geometry: the patch operators the descriptor model reads.
        basis: the eigenbasis (k = the model's ``n_eigen``), of the scaled surface.
        descriptor_index: None, or (N,) int64 when the model reads a coarse copy (``descriptor_vertices``):
            ``features`` and ``geometry`` are the copy's, and vertex i takes the descriptor of the copy's
            vertex ``descriptor_index[i]``.
    """

    name: str
    surface: Surface
    scale: float
    is_point_cloud: bool
    features: np.ndarray
    geometry: Geometry
    basis: SpectralBasis
    descriptor_index: np.ndarray | None = None

    @property
    def n_vertices(self) -> int:
        return self.surface.n_vertices

    def basis_tensors(self, k: int, dtype=torch.float32) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(eigenvectors (N, k), mass (N,), eigenvalues (k,)) as tensors, for :func:`functional_map`."""
        basis = self.basis.truncated(k)
        return (
            torch.as_tensor(basis.eigenvectors, dtype=dtype),
            torch.as_tensor(basis.mass, dtype=dtype),
            torch.as_tensor(basis.eigenvalues, dtype=dtype),
        )


#: A surface is read through a coarse copy only when it has more than this many times the vertices asked for.
COARSE_MARGIN = 1.5


def input_features(zernet_features: np.ndarray | None, basis: SpectralBasis, feature_kind: str) -> np.ndarray:
    """The model input of ``feature_kind``: the other parts computed by :func:`prepare_record`, then the heat
    kernel signature when ``hks`` is one of the parts, from the matcher's own eigenbasis (the one its maps
    use, already computed; the data sets' ``hks`` part takes its first 64 eigenpairs instead)."""
    columns = [] if zernet_features is None else [zernet_features]
    if "hks" in feature_kind.split("+"):
        columns.append(heat_kernel_signature(basis, HKS_TIMES))
    return np.concatenate(columns, axis=1).astype(np.float32)


def prepare_shape(
    surface: Surface,
    patch_configs: list[PatchConfig],
    area: float | FixedScale,
    feature_kind: str,
    n_eigen: int,
    cache_dir: str | os.PathLike | None = None,
    name: str | None = None,
    descriptor_vertices: int | None = None,
) -> MatchShape:
    """Prepare ``surface`` for matching (module docstring).

    Args:
        surface: a mesh or a point cloud (validated here; repair a user's file first with
            :func:`zernet.geometry.repair_surface`, which keeps the map back to its vertices).
        patch_configs: the descriptor model's patch settings, one per scale.
        area: the area the model was trained at, or a :class:`~zernet.geometry.FixedScale` (a shape matched
            as a part of another in the same units).
        feature_kind: zernet feature parts joined by "+", optionally with ``hks``.
        n_eigen: eigenpairs to compute (the most any later step uses, ZoomOut included).
        cache_dir: cache of operators and eigenbases (None: nothing cached).
        descriptor_vertices: a surface with more than :data:`COARSE_MARGIN` times this many vertices is read
            by the model through a coarse copy of about this many (:func:`zernet.geometry.coarsen_surface`):
            the resolution it was trained at, for a fraction of the time; the eigenbasis, the maps and the
            answer stay on the surface itself.
    """
    is_cloud = surface.is_point_cloud
    zernet_kind = "+".join(part for part in feature_kind.split("+") if part != "hks")
    coarse = None
    with warnings.catch_warnings():
        # The copy is the matcher's own: what a simplifier leaves in it (non-manifold edges) is not the user's.
        if descriptor_vertices and surface.n_vertices > COARSE_MARGIN * descriptor_vertices:
            warnings.simplefilter("ignore", SurfaceWarning)
            coarse = coarsen_surface(surface, descriptor_vertices)
        record = prepare_record(
            surface if coarse is None else coarse.surface,
            patch_configs,
            cache_dir=cache_dir,
            target_area=area,
            feature_kind=zernet_kind or "ones",
            name=name,
        )
    basis = _eigenbasis(record.surface, is_cloud, n_eigen, cache_dir)
    features = input_features(record.features if zernet_kind else None, basis, feature_kind)
    if coarse is None:
        return MatchShape(record.name, record.surface, record.scale, is_cloud, features, record.geometry, basis)
    # The surface itself, moved as the copy was: v' = s v + t (a scaling about the copy's centroid).
    translation = (record.surface.vertices - record.scale * coarse.surface.vertices).mean(axis=0)
    valid = validate_surface(surface)
    scaled = Surface(record.scale * valid.vertices + translation, valid.faces, valid.normals, valid.fields, valid.name)
    return MatchShape(
        record.name,
        scaled,
        record.scale,
        is_cloud,
        features,
        record.geometry,
        _eigenbasis(scaled, is_cloud, n_eigen, cache_dir),
        coarse.nearest,
    )


def _eigenbasis(surface: Surface, is_cloud: bool, n_eigen: int, cache_dir) -> SpectralBasis:
    """The eigenbasis of a prepared surface: of the mesh, or for a cloud of its points (module docstring)."""
    spectral_surface = Surface(surface.vertices, None, name=surface.name) if is_cloud else surface
    return laplacian_eigenbasis(spectral_surface, n_eigen, cache_dir=cache_dir)


def rotating_columns(feature_kind: str, n_max: int) -> list[slice]:
    """The column slices of the parts that turn with the surface (xyz, normals)."""
    zernet_kind = "+".join(part for part in feature_kind.split("+") if part != "hks")
    if not zernet_kind:
        return []
    slices = feature_slices(zernet_kind, [n_max])
    return [slices[part] for part in ("xyz", "normals") if part in feature_parts(zernet_kind)]
