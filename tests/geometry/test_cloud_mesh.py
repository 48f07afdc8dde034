"""The triangulation of a point cloud through its own points, and the front geodesics it gives clouds."""

import numpy as np
import pytest
import trimesh
from meshes import grid_mesh, icosphere
from scipy.spatial import Delaunay

from zernet.geometry import Surface, compute_polar, mesh_from_cloud, sample_surface
from zernet.geometry.cloud_mesh import triangulate_cloud
from zernet.operators import PatchConfig, build_patch_operator

pytestmark = pytest.mark.timeout(120)


def edge_face_counts(faces):
    pairs = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    return np.unique(pairs, axis=0, return_counts=True)[1]


def sphere_cloud(n=2000, seed=0) -> Surface:
    """Random (Poisson) points on the unit sphere: uneven spacing, as a scanner gives."""
    points = np.random.default_rng(seed).normal(size=(n, 3))
    return Surface(points / np.linalg.norm(points, axis=1, keepdims=True), None, name="sphere cloud")


def test_sphere_cloud_becomes_a_closed_consistently_oriented_mesh():
    cloud = sphere_cloud()
    mesh = mesh_from_cloud(cloud)
    assert mesh.vertices is cloud.vertices and mesh.name == cloud.name
    counts = edge_face_counts(mesh.faces)
    assert counts.max() <= 2  # edge-manifold by construction
    assert (counts == 1).mean() < 0.03  # small holes only where the local rings disagree
    used = np.zeros(cloud.n_vertices, dtype=bool)
    used[mesh.faces.ravel()] = True
    assert used.all()
    assert mesh.area == pytest.approx(4 * np.pi, rel=0.05)
    centroid = mesh.vertices[mesh.faces].mean(axis=1)
    assert (np.einsum("fi,fi->f", mesh.face_normals(), centroid) > 0).all()  # outward, like the cloud normals


def test_jittered_plane_gives_its_delaunay_triangulation():
    vertices, _ = grid_mesh(12, jitter=0.3, seed=1)
    faces = triangulate_cloud(vertices, np.tile([0.0, 0.0, 1.0], (len(vertices), 1)))
    delaunay = Delaunay(vertices[:, :2]).simplices
    # Away from the rim (where k nearest neighbours do not see the whole Delaunay ring) the two agree.
    inner = np.all(np.abs(vertices[:, :2]).max(axis=1)[delaunay] < 3.5, axis=1)
    ours = {tuple(sorted(f)) for f in faces}
    assert {tuple(sorted(f)) for f in delaunay[inner]} <= ours
    assert (np.cross(*(vertices[faces[:, 1:]] - vertices[faces[:, :1]]).transpose(1, 0, 2))[:, 2] > 0).all()


def test_facing_sheets_of_a_thin_part_are_not_joined():
    # A flat closed ellipsoid (half thickness 0.1, point spacing about 0.1): near its middle a point's
    # nearest neighbours include points of the other sheet, which face the other way.
    mesh = trimesh.creation.icosphere(subdivisions=5)
    points = np.asarray(mesh.vertices) * [2.0, 2.0, 0.1]
    faces = mesh_from_cloud(Surface(points, None)).faces
    middle = np.all(np.linalg.norm(points[faces][:, :, :2], axis=2) < 1.5, axis=1)
    sides = np.sign(points[faces][middle][:, :, 2])
    assert len(sides) > 1000 and (np.abs(sides.sum(axis=1)) == 3).all()


def test_cloud_geodesics_by_the_front_are_surface_distances():
    cloud = sphere_cloud(3000, seed=2)
    mesh = mesh_from_cloud(cloud)
    samples = sample_surface(mesh, 6000, seed=0)
    r0 = 0.6
    polar = compute_polar(mesh, samples, r0, backend="front")
    on_sphere = samples.points / np.linalg.norm(samples.points, axis=1, keepdims=True)
    great_circle = np.arccos(
        np.clip(np.einsum("pi,pi->p", cloud.vertices[polar.center], on_sphere[polar.sample]), -1, 1)
    )
    error = np.abs(polar.radius - great_circle) / r0
    assert np.percentile(error, 95) < 0.03  # chords of a sphere this size would be 1.5 % short at r0: fine
    assert great_circle.max() < 1.1 * r0


def test_cloud_operator_matches_the_mesh_operator_on_a_smooth_field():
    sphere = icosphere(4)  # 2,562 vertices
    cloud = Surface(sphere.vertices, None)
    config = PatchConfig(r0=0.5, n_samples=8000, n_max=3)
    field = np.stack([sphere.vertices[:, 0], sphere.vertices[:, 1] * sphere.vertices[:, 2]], axis=1)
    mesh_coefficients = build_patch_operator(sphere, config).matrix @ field
    cloud_coefficients = build_patch_operator(cloud, config).matrix @ field
    scale = np.abs(mesh_coefficients).max()
    difference = np.abs(mesh_coefficients - cloud_coefficients) / scale
    # Different sample draws and tangent frames (the angle origin) move the non-radial coefficients
    # somewhat; the piston (the mean over the patch) must agree closely.
    pistons = slice(0, None, config.k)
    assert np.median(difference[pistons]) < 0.01
    assert np.percentile(difference, 50) < 0.05
