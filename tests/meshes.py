"""Small analytic meshes shared by the tests: builders that return a :class:`Surface` (or vertex and face
arrays where a test needs them before a surface exists).

Importable from any test module as ``from meshes import ...`` (tests/conftest.py puts this folder on
``sys.path``); tests/conftest.py also offers the common cases as fixtures.
"""

from __future__ import annotations

import numpy as np
import trimesh

from zernet.geometry import Surface


def icosphere(
    subdivisions: int = 2, radius: float = 1.0, noise: float = 0.0, seed: int = 0, name: str = "sphere"
) -> Surface:
    """trimesh's icosphere with outward normals; ``noise`` > 0 scales each vertex radially by
    ``1 + noise * N(0, 1)`` (seeded), which removes exact distance ties between vertices."""
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    if noise:
        vertices = vertices * (1 + noise * np.random.default_rng(seed).standard_normal((len(vertices), 1)))
    return Surface(vertices, np.asarray(mesh.faces, dtype=np.int64), name=name)


#: Distinct axes of :func:`ellipsoid`: its only symmetries are the reflections of the coordinates.
ELLIPSOID_AXES = np.array([1.0, 1.4, 1.9])


def ellipsoid(subdivisions: int = 3, noise: float = 0.0, seed: int = 0) -> Surface:
    """An :func:`icosphere` stretched along :data:`ELLIPSOID_AXES`; ``noise`` and ``seed`` as there."""
    sphere = icosphere(subdivisions, noise=noise, seed=seed)
    return Surface(sphere.vertices * ELLIPSOID_AXES, sphere.faces, name=f"ellipsoid{seed}")


def grid_mesh(nx: int, ny: int | None = None, spacing: float = 1.0, jitter: float = 0.0, seed: int = 0):
    """Triangulated nx × ny vertex grid in the z = 0 plane centred at the origin, normals +z; (V, F).

    ``jitter`` moves every vertex by a uniform in-plane offset of up to ``jitter * spacing`` (seeded).
    """
    ny = nx if ny is None else ny
    x, y = np.meshgrid((np.arange(nx) - (nx - 1) / 2) * spacing, (np.arange(ny) - (ny - 1) / 2) * spacing)
    vertices = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    if jitter:
        vertices[:, :2] += np.random.default_rng(seed).uniform(-jitter, jitter, (len(vertices), 2)) * spacing
    index = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = index[:-1, :-1].ravel(), index[:-1, 1:].ravel(), index[1:, :-1].ravel(), index[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    return vertices, faces


def grid(n: int = 4, spacing: float = 1.0, name: str = "grid") -> Surface:
    """A flat n × n vertex grid (an open disk-like surface of area ((n - 1) spacing)²), see :func:`grid_mesh`."""
    vertices, faces = grid_mesh(n, n, spacing)
    return Surface(vertices, faces, name=name)


def cylinder_mesh(radius: float, height: float, around: int, along: int):
    """Open cylinder around the z axis (boundary loops at z = ±height/2); (V, F)."""
    phi = 2 * np.pi * np.arange(around) / around
    z = np.linspace(-height / 2, height / 2, along)
    P, Z = np.meshgrid(phi, z)
    vertices = np.stack([radius * np.cos(P).ravel(), radius * np.sin(P).ravel(), Z.ravel()], axis=1)
    index = np.arange(around * along).reshape(along, around)
    nxt = np.roll(index, -1, axis=1)
    a, b, c, d = index[:-1].ravel(), nxt[:-1].ravel(), index[1:].ravel(), nxt[1:].ravel()
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    return vertices, faces


def open_cylinder(
    radius: float = 1.5, height: float = 6.0, around: int = 64, along: int = 25, name: str = "cylinder"
) -> Surface:
    """:func:`cylinder_mesh` as a surface oriented with outward normals."""
    vertices, faces = cylinder_mesh(radius, height, around, along)
    surface = Surface(vertices, faces, name=name)
    radial = vertices * [1.0, 1.0, 0.0]
    if np.einsum("ij,ij->i", surface.vertex_normals(), radial).mean() < 0:
        surface = Surface(vertices, faces[:, ::-1], name=name)
    return surface


def tetrahedron(name: str = "tetrahedron") -> Surface:
    """The unit corner tetrahedron (0, e_x, e_y, e_z) with outward normals: 4 vertices, 4 faces."""
    vertices = [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)]
    faces = [(0, 2, 1), (0, 1, 3), (0, 3, 2), (1, 2, 3)]
    return Surface(np.array(vertices), np.array(faces), name=name)


def random_sphere_points(n: int, seed: int = 0) -> np.ndarray:
    """(n, 3) points uniformly distributed on the unit sphere (seeded)."""
    points = np.random.default_rng(seed).normal(size=(n, 3))
    return points / np.linalg.norm(points, axis=1, keepdims=True)


def random_frames(rng, n):
    """``n`` random right-handed orthonormal frames (rows e1, e2, normal), normals near +z."""
    normals = rng.normal(size=(n, 3)) + np.array([0.0, 0.0, 2.5])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    e1 = np.cross(normals, rng.normal(size=(n, 3)))
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return np.stack([e1, np.cross(normals, e1), normals], axis=1)


def patch_like_operator(k: int, n: int = 15, seed: int = 0, per_patch: int = 5):
    """A random ``(n k, n)`` operator (``zernet.nn.reference.MatrixOperator`` with random frames) whose ``k``
    rows per vertex read the same few vertices: the block layout of a real patch fit."""
    import scipy.sparse as sp

    from zernet.nn.reference import MatrixOperator

    rng = np.random.default_rng(seed)
    rows, cols = [], []
    for p in range(n):
        neighbours = np.sort(rng.choice(n, size=per_patch, replace=False))
        for j in range(k):
            rows += [p * k + j] * per_patch
            cols += list(neighbours)
    matrix = sp.csr_matrix((rng.normal(size=len(rows)), (rows, cols)), shape=(n * k, n))
    return MatrixOperator(matrix, k, random_frames(rng, n))


def write_faust_layout(root, surfaces) -> None:
    """Write ``surfaces`` as ``root/MPI-FAUST/training/registrations/tr_reg_XXX.ply`` (the FAUST layout)."""
    folder = root / "MPI-FAUST" / "training" / "registrations"
    folder.mkdir(parents=True)
    for i, surface in enumerate(surfaces):
        trimesh.Trimesh(surface.vertices, surface.faces, process=False).export(folder / f"tr_reg_{i:03d}.ply")


def labelled_sphere(seed: int, name: str = "sphere") -> tuple[Surface, np.ndarray]:
    """A 42-vertex sphere (radial noise 0.05, seeded) stretched 1.5 times along x, and its part labels: 1 on
    the upper half (y > 0), else 0. The labels are a plane through the shape, so a small model reading xyz
    learns them in a few seconds."""
    sphere = icosphere(subdivisions=1, noise=0.05, seed=seed)
    vertices = sphere.vertices * np.array([1.5, 1.0, 1.0])
    return Surface(vertices, sphere.faces, name=name), (vertices[:, 1] > 0).astype(np.int64)


def write_labelled_sphere(folder, name: str, seed: int) -> tuple[str, str]:
    """:func:`labelled_sphere` as ``folder/name.obj`` with its labels in ``folder/name.txt`` (one per line,
    the layout of the segmentation loader); returns the two files' texts."""
    surface, labels = labelled_sphere(seed, name)
    folder.mkdir(parents=True, exist_ok=True)
    mesh_text = trimesh.Trimesh(surface.vertices, surface.faces, process=False).export(file_type="obj")
    label_text = "\n".join(str(label) for label in labels) + "\n"
    (folder / f"{name}.obj").write_text(mesh_text)
    (folder / f"{name}.txt").write_text(label_text)
    return mesh_text, label_text


def write_labelled_spheres(root, n: int = 6, test: tuple[str, ...] = ("shape5",)) -> None:
    """Spheres ``shape0``.. ``shape{n-1}`` (seed i) under ``root/train`` or, for those named in ``test``,
    ``root/test``."""
    for i in range(n):
        name = f"shape{i}"
        write_labelled_sphere(root / ("test" if name in test else "train"), name, seed=i)


def majority_fraction(labels: np.ndarray) -> float:
    """The fraction of ``labels`` in their most frequent class: the accuracy of answering that class everywhere,
    the baseline a model that has learnt its task must beat."""
    return float(np.bincount(np.asarray(labels).reshape(-1)).max() / np.size(labels))
