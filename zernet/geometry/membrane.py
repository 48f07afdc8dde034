"""Wall stress of a thin membrane under inner pressure: a physics prior for stress regression.

For an inflated thin wall, Laplace's law ties stress to curvature (``σ = pR/2t`` on a sphere, ``pR/t`` around a
cylinder), but on a real sac the stress also depends on the shape around each point and on where the wall is
held. Solving the membrane's equilibrium on the surface captures both, and costs one sparse solve:

- Every triangle is a linear plane-stress membrane element (constant strain triangle) of unit thickness,
  Young's modulus 1 and Poisson ratio ν, acting in its own plane; the three displacement components of every
  vertex are unknown.
- A unit pressure pushes each triangle along its normal (``A/3 · n`` per corner, so the normals' side is the
  inside being pressurised: outward normals mean inner pressure).
- Boundary vertices (cuts of the vessel) are clamped, and so are vertices no face uses. A closed surface is
  held by nothing: the pressure's net force is zero, and a vanishing shift fixes the free translation.
- A pure membrane has no stiffness against bending: flat and saddle-shaped regions can fold at no cost, and the
  linear system is then (nearly) singular. A uniform *prestress* ``τ`` (in units of the plane-stress modulus
  ``E / (1 - ν²)``) adds the geometric stiffness of a pre-tensioned film, ``τ ∫ ∇u · ∇v`` (the cotangent
  Laplacian on each displacement component), which removes those mechanisms. It also carries part of the
  load: on a sphere the membrane stress becomes ``pR/2 / (1 + τ / (1 + ν))``, around a long cylinder with
  clamped ends ``pR / (1 + τ)``.

The result per vertex is the von Mises stress of the plane-stress state, area-weighted over the incident
triangles, in units of pressure × length / thickness. On the aneurysm data set
(:func:`zernet.data.regression.load_aneurysm`), whose targets are finite-element wall stresses, this
estimate's rank correlation with the target is 0.93 per case on average at ``τ ≈ 0.02`` (mean curvature at
the best scale: 0.75).

Public API: :func:`membrane_stress`.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import warnings
from pathlib import Path

import numpy as np
import potpourri3d as pp3d
import scipy.sparse
import scipy.sparse.csgraph
import scipy.sparse.linalg

from zernet.geometry.surface import Surface, SurfaceError
from zernet.io_utils import atomic_write_bytes

__all__ = ["membrane_stress"]

# Bump when the computation changes, so cached results are not reused.
_FORMAT_VERSION = "zernet-membrane-1"


def membrane_stress(
    surface: Surface,
    prestress: float = 0.02,
    poisson_ratio: float = 0.45,
    cache_dir: str | os.PathLike | None = None,
) -> np.ndarray:
    """Von Mises membrane stress per vertex under unit inner pressure, shape (N,) float64, >= 0.

    Args:
        surface: a triangle mesh (a point cloud has no wall to solve on: :class:`SurfaceError`).
        prestress: stabilising pre-tension τ >= 0, relative to the plane-stress modulus (see the module
            docstring); 0 solves the pure membrane, which is singular on flat or folded regions.
        poisson_ratio: ν in [0, 0.5); soft tissue is nearly incompressible (0.45-0.49).
        cache_dir: folder for cached results (``membrane/<key>.npy``, keyed by the geometry hash and the
            parameters); None computes every time.
    """
    if surface.is_point_cloud:
        raise SurfaceError(f"{surface.name}: membrane stress needs a triangle mesh, got a point cloud")
    if not 0.0 <= poisson_ratio < 0.5:
        raise ValueError(f"poisson_ratio must be in [0, 0.5), got {poisson_ratio}")
    if prestress < 0:
        raise ValueError(f"prestress must be >= 0, got {prestress}")
    path = None if cache_dir is None else _cache_path(surface, float(prestress), float(poisson_ratio), cache_dir)
    cached = None if path is None else _read_cache(path, surface.n_vertices)
    if cached is not None:
        return cached
    stress = _solve(surface, float(prestress), float(poisson_ratio))
    if path is not None:
        buffer = io.BytesIO()
        np.save(buffer, stress)
        atomic_write_bytes(path, buffer.getvalue())
    return stress


def _cache_path(surface: Surface, prestress: float, nu: float, cache_dir: str | os.PathLike) -> Path:
    text = json.dumps(
        {"geometry": surface.geometry_hash(), "prestress": prestress, "poisson_ratio": nu, "version": _FORMAT_VERSION},
        sort_keys=True,
    )
    return Path(cache_dir) / "membrane" / f"{hashlib.sha256(text.encode()).hexdigest()}.npy"


def _read_cache(path: Path, n_vertices: int) -> np.ndarray | None:
    """The cached stresses, or None when there are none or the file is unreadable (then it is recomputed)."""
    if not path.is_file():
        return None
    try:
        cached = np.load(path, allow_pickle=False)
    except (OSError, ValueError):
        return None  # unreadable (e.g. truncated by hand): recompute and overwrite
    return cached if cached.shape == (n_vertices,) else None


def _solve(surface: Surface, prestress: float, nu: float) -> np.ndarray:
    """Assemble and solve the membrane's equilibrium; the von Mises stress per vertex."""
    area, normal = surface.face_areas(), surface.face_normals()
    if np.any(area <= 0):
        bad = int(np.flatnonzero(area <= 0)[0])
        raise SurfaceError(f"{surface.name}: face {bad} has zero area; run validate_surface(repair=True) first")
    strain = _element_strains(surface.vertices[surface.faces], normal, area)
    modulus = np.array([[1.0, nu, 0.0], [nu, 1.0, 0.0], [0.0, 0.0, (1.0 - nu) / 2]]) / (1.0 - nu * nu)
    dofs = (3 * surface.faces[:, :, None] + np.arange(3)).reshape(len(surface.faces), 9)
    stiffness = _stiffness(surface, strain, modulus, area, dofs, prestress, nu)
    load = np.zeros((surface.n_vertices, 3))
    for corner in range(3):
        np.add.at(load, surface.faces[:, corner], (area / 3)[:, None] * normal)
    displacement = _solve_displacement(surface, stiffness, load.ravel(), prestress)
    sxx, syy, sxy = np.einsum("ab,tbj,tj->at", modulus, strain, displacement[dofs])
    von_mises = np.sqrt(np.maximum(sxx**2 + syy**2 - sxx * syy + 3 * sxy**2, 0.0))
    return _area_weighted_vertex_average(surface, area, von_mises)


def _element_strains(corners: np.ndarray, normal: np.ndarray, area: np.ndarray) -> np.ndarray:
    """(T, 3, 9) constant strain of every triangle (components xx, yy, xy in its own frame) as a linear map of
    the 3-D displacements of its three corners."""
    n_faces = len(corners)
    double_area = 2 * area
    edge1 = corners[:, 1] - corners[:, 0]
    # Element frame (e1 along the first edge, e2 in plane) and in-plane corner coordinates (x, y).
    e1 = edge1 / np.linalg.norm(edge1, axis=1, keepdims=True)
    e2 = np.cross(normal, e1)
    local = corners - corners[:, :1]
    x, y = np.einsum("tki,ti->tk", local, e1), np.einsum("tki,ti->tk", local, e2)
    # Constant-strain gradients: strain = Σ_k (b_k u_k, c_k v_k, c_k u_k + b_k v_k) with u, v the in-plane
    # displacements of corner k, i.e. U_k · e1 and U_k · e2 of its 3-D displacement U_k.
    b = np.stack([y[:, 1] - y[:, 2], y[:, 2] - y[:, 0], y[:, 0] - y[:, 1]], axis=1) / double_area[:, None]
    c = np.stack([x[:, 2] - x[:, 1], x[:, 0] - x[:, 2], x[:, 1] - x[:, 0]], axis=1) / double_area[:, None]
    strain = np.empty((n_faces, 3, 3, 3))  # (triangle, strain component, corner, xyz)
    strain[:, 0] = b[:, :, None] * e1[:, None, :]
    strain[:, 1] = c[:, :, None] * e2[:, None, :]
    strain[:, 2] = c[:, :, None] * e1[:, None, :] + b[:, :, None] * e2[:, None, :]
    return strain.reshape(n_faces, 3, 9)


def _stiffness(surface, strain, modulus, area, dofs, prestress, nu) -> scipy.sparse.csr_matrix:
    """(3N, 3N) membrane stiffness, plus the prestress's geometric stiffness when ``prestress > 0``."""
    n = surface.n_vertices
    element = np.einsum("t,tai,ab,tbj->tij", area, strain, modulus, strain)
    rows, cols = np.repeat(dofs, 9, axis=1).ravel(), np.tile(dofs, (1, 9)).ravel()
    stiffness = scipy.sparse.coo_matrix((element.ravel(), (rows, cols)), shape=(3 * n, 3 * n)).tocsr()
    if prestress > 0:
        laplacian = pp3d.cotan_laplacian(surface.vertices, surface.faces)
        stiffness = stiffness + scipy.sparse.kron(laplacian * (prestress / (1.0 - nu * nu)), scipy.sparse.identity(3))
    return stiffness


def _solve_displacement(surface: Surface, stiffness, load: np.ndarray, prestress: float) -> np.ndarray:
    """(3N,) displacements with the clamped vertices held at zero; SurfaceError when the system is singular."""
    n = surface.n_vertices
    # Clamped: the cut boundaries, and vertices no face uses (nothing holds or loads them).
    unused = np.ones(n, dtype=bool)
    unused[surface.faces.ravel()] = False
    clamped = np.flatnonzero(surface.boundary_vertices() | unused)
    free = np.ones(3 * n, dtype=bool)
    free[(3 * clamped[:, None] + np.arange(3)).ravel()] = False
    # A closed part (no clamped vertex) is free to translate and its load has no net force: a vanishing
    # shift (1e-9 of the stiffness) on its unknowns pins the translation without changing the stresses.
    edges = surface.edges()
    graph = scipy.sparse.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, part = scipy.sparse.csgraph.connected_components(graph, directed=False)
    held_parts = np.unique(part[clamped])
    unheld = np.repeat(~np.isin(part, held_parts), 3)
    shift = scipy.sparse.diags(unheld * (1e-9 * stiffness.diagonal().mean()))
    system = (stiffness + shift)[free][:, free].tocsc()
    with warnings.catch_warnings():
        warnings.simplefilter("error", scipy.sparse.linalg.MatrixRankWarning)
        try:
            solution = scipy.sparse.linalg.spsolve(system, load[free])
        except scipy.sparse.linalg.MatrixRankWarning:
            solution = np.full(int(free.sum()), np.nan)
    if not np.all(np.isfinite(solution)):
        raise SurfaceError(
            f"{surface.name}: the membrane system is singular (a flat or folded region can move "
            f"freely); use a prestress > 0 (got {prestress})"
        )
    displacement = np.zeros(3 * n)
    displacement[free] = solution
    return displacement


def _area_weighted_vertex_average(surface: Surface, area: np.ndarray, per_face: np.ndarray) -> np.ndarray:
    """(N,) average of a per-face value over each vertex's triangles, weighted by area; 0 for unused vertices."""
    n = surface.n_vertices
    total, weight = np.zeros(n), np.zeros(n)
    for corner in range(3):
        np.add.at(total, surface.faces[:, corner], area * per_face)
        np.add.at(weight, surface.faces[:, corner], area)
    return np.divide(total, weight, out=np.zeros(n), where=weight > 0)
