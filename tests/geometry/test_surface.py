"""Tests for zernet.geometry: reading, validation and repair, area normalisation, normals, curvature and
sampling of surfaces.

Every test builds its own small surfaces (tests/meshes.py); nothing here needs a data set.
"""

import warnings

import numpy as np
import pytest
import scipy.io
import trimesh
from meshes import grid, icosphere, random_sphere_points

from zernet.geometry import (
    FixedScale,
    Surface,
    SurfaceError,
    SurfaceWarning,
    load_surface,
    normalize_area,
    repair_surface,
    sample_surface,
    validate_surface,
)


# ---------------------------------------------------------------------------------------------- helpers
def shuffled_mesh(seed: int = 0) -> trimesh.Trimesh:
    """An icosphere with its vertices in a random order, so that preserved order is a real check."""
    mesh = trimesh.creation.icosphere(subdivisions=1)
    rng = np.random.default_rng(seed)
    permutation = rng.permutation(len(mesh.vertices))
    inverse = np.argsort(permutation)
    return trimesh.Trimesh(mesh.vertices[permutation], inverse[mesh.faces], process=False)


TWO_TRIANGLES = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype=float)
TWO_FACES = np.array([[0, 1, 2], [1, 3, 2]])


# ---------------------------------------------------------------------------------------------- reading
@pytest.mark.parametrize("extension", ["ply", "obj", "off"])
def test_mesh_round_trip_keeps_vertex_order(tmp_path, extension):
    mesh = shuffled_mesh()
    path = tmp_path / f"shape.{extension}"
    mesh.export(path)
    surface = load_surface(path)
    assert surface.name == str(path)
    assert not surface.is_point_cloud
    np.testing.assert_allclose(surface.vertices, mesh.vertices, atol=1e-6)
    np.testing.assert_array_equal(surface.faces, mesh.faces)
    assert surface.vertices.dtype == np.float64 and surface.faces.dtype == np.int64


def test_stl_round_trip_merges_corners_and_keeps_triangles(tmp_path):
    mesh = shuffled_mesh()
    path = tmp_path / "shape.stl"
    mesh.export(path)
    surface = load_surface(path)
    # STL stores 3 corners per face; after merging, the vertex count and every triangle are recovered.
    assert surface.n_vertices == len(mesh.vertices)
    assert surface.n_faces == len(mesh.faces)
    np.testing.assert_allclose(surface.vertices[surface.faces], mesh.vertices[mesh.faces], atol=1e-6)


def test_obj_keeps_unreferenced_vertices_and_warns(tmp_path):
    path = tmp_path / "extra.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nv 5 5 5\nf 4 2 3\nf 1 2 3\n")
    with pytest.warns(SurfaceWarning, match=r"extra\.obj.*vertex 4"):
        surface = load_surface(path)
    assert surface.n_vertices == 5
    np.testing.assert_array_equal(surface.faces, [[3, 1, 2], [0, 1, 2]])


def test_ply_point_cloud_with_normals_and_extra_property(tmp_path):
    points = random_sphere_points(20)
    rows = "\n".join(" ".join(f"{v:.9f}" for v in (*p, *p, i * 0.5)) for i, p in enumerate(points))
    header = (
        "ply\nformat ascii 1.0\nelement vertex 20\nproperty double x\nproperty double y\nproperty double z\n"
        "property double nx\nproperty double ny\nproperty double nz\nproperty double quality\nend_header\n"
    )
    path = tmp_path / "cloud.ply"
    path.write_text(header + rows + "\n")
    surface = load_surface(path)
    assert surface.is_point_cloud and surface.faces is None and surface.n_faces == 0
    np.testing.assert_allclose(surface.vertices, points, atol=1e-8)
    np.testing.assert_allclose(surface.normals, points, atol=1e-8)
    np.testing.assert_allclose(surface.fields["quality"], np.arange(20) * 0.5)


def test_mat_round_trip_one_based_faces_and_field(tmp_path):
    mesh = shuffled_mesh()
    stress = np.linspace(0.01, 0.3, len(mesh.vertices))[:, None]  # (V, 1) as in the authors' files
    path = tmp_path / "TP_Ia1I.mat"
    scipy.io.savemat(
        path,
        {"X": mesh.vertices, "F": (mesh.faces + 1).astype(np.uint16), "J2m": stress, "note": np.array([[1.0, 2.0]])},
    )
    surface = load_surface(path)
    np.testing.assert_array_equal(surface.vertices, mesh.vertices)
    np.testing.assert_array_equal(surface.faces, mesh.faces)
    assert set(surface.fields) == {"J2m"}  # "note" has no per-vertex length
    assert surface.fields["J2m"].shape == (len(mesh.vertices),)
    np.testing.assert_array_equal(surface.fields["J2m"], stress[:, 0])

    only = load_surface(path, fields=["J2m"])
    assert set(only.fields) == {"J2m"}
    with pytest.raises(SurfaceError, match=r"TP_Ia1I\.mat.*'wss'"):
        load_surface(path, fields=["wss"])


def test_mat_zero_based_faces_are_rejected(tmp_path):
    mesh = shuffled_mesh()
    path = tmp_path / "zero.mat"
    scipy.io.savemat(path, {"X": mesh.vertices, "F": mesh.faces.astype(np.uint16)})
    with pytest.raises(SurfaceError, match=r"zero\.mat.*face \d+.*1-based"):
        load_surface(path)


def test_mat_without_x_names_keys(tmp_path):
    path = tmp_path / "nox.mat"
    scipy.io.savemat(path, {"V": np.zeros((3, 3))})
    with pytest.raises(SurfaceError, match=r"nox\.mat.*'X'.*\['V'\]"):
        load_surface(path)


def test_point_cloud_arrays_npy_and_text(tmp_path):
    points = random_sphere_points(30)
    np.save(tmp_path / "a.npy", points)
    cloud = load_surface(tmp_path / "a.npy")
    assert cloud.is_point_cloud and cloud.normals is None
    np.testing.assert_array_equal(cloud.vertices, points)

    np.savetxt(tmp_path / "b.xyz", np.hstack([points, points]), header="x y z nx ny nz")
    with_normals = load_surface(tmp_path / "b.xyz")
    np.testing.assert_allclose(with_normals.normals, points)

    np.savetxt(tmp_path / "c.txt", np.zeros((4, 4)))
    with pytest.raises(SurfaceError, match=r"c\.txt.*\(N, 3\) or \(N, 6\)"):
        load_surface(tmp_path / "c.txt")


def test_file_errors_name_the_file(tmp_path):
    with pytest.raises(SurfaceError, match=r"missing\.ply: no such file"):
        load_surface(tmp_path / "missing.ply")
    (tmp_path / "shape.vtk").write_text("x")
    with pytest.raises(SurfaceError, match=r"shape\.vtk.*unknown.*'\.vtk'"):
        load_surface(tmp_path / "shape.vtk")
    (tmp_path / "garbage.ply").write_text("this is not a ply file")
    with pytest.raises(SurfaceError, match=r"garbage\.ply: cannot read"):
        load_surface(tmp_path / "garbage.ply")
    (tmp_path / "garbage.mat").write_bytes(b"\x00\x01 not matlab")
    with pytest.raises(SurfaceError, match=r"garbage\.mat"):
        load_surface(tmp_path / "garbage.mat")


def test_load_validates_and_repairs(tmp_path):
    path = tmp_path / "degenerate.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3\nf 2 4 3\nf 1 2 2\n")
    with pytest.raises(SurfaceError, match=r"degenerate\.obj: face 2 = \[0, 1, 1\] repeats a vertex"):
        load_surface(path)
    repaired = load_surface(path, repair=True)
    np.testing.assert_array_equal(repaired.faces, [[0, 1, 2], [1, 3, 2]])


# ---------------------------------------------------------------------------------------------- validation
def mesh_error(vertices, faces, repair=False, **fields):
    surface = Surface(
        np.asarray(vertices, dtype=float), None if faces is None else np.asarray(faces), fields=fields, name="bumpy.ply"
    )
    with pytest.raises(SurfaceError) as info:
        validate_surface(surface, repair=repair)
    message = str(info.value)
    assert message.startswith("bumpy.ply: ")
    return message


def test_empty_surfaces():
    assert "0 vertices" in mesh_error(np.zeros((0, 3)), None)
    assert "0 faces" in mesh_error(TWO_TRIANGLES, np.zeros((0, 3), dtype=int))


@pytest.mark.parametrize("repair", [False, True])
def test_non_finite_vertex_is_named_and_never_repaired(repair):
    vertices = TWO_TRIANGLES.copy()
    vertices[3, 1] = np.nan
    message = mesh_error(vertices, TWO_FACES, repair=repair)
    assert "vertex 3" in message and "nan" in message and "cannot be repaired" in message
    vertices[3, 1] = np.inf
    assert "vertex 3" in mesh_error(vertices, None, repair=repair)


def test_face_index_out_of_range():
    message = mesh_error(TWO_TRIANGLES, [[0, 1, 2], [1, 7, 2]])
    assert "face 1 = [1, 7, 2]" in message and "vertex 7" in message and "0..3" in message
    assert "vertex -1" in mesh_error(TWO_TRIANGLES, [[0, 1, -1]])


def test_degenerate_and_zero_area_faces():
    message = mesh_error(TWO_TRIANGLES, [[0, 1, 2], [3, 3, 2]])
    assert "face 1 = [3, 3, 2] repeats a vertex index" in message
    collinear = np.vstack([TWO_TRIANGLES, [[2.0, 0.0, 0.0]]])
    message = mesh_error(collinear, [[0, 1, 2], [0, 1, 4]])
    assert "face 1 = [0, 1, 4] has zero area" in message


def test_duplicate_vertices_name_both():
    vertices = np.vstack([TWO_TRIANGLES, TWO_TRIANGLES[1]])
    message = mesh_error(vertices, [[0, 1, 2], [4, 3, 2]])
    assert "vertices 1 and 4" in message and "[1.0, 0.0, 0.0]" in message and "repair=True" in message
    cloud = random_sphere_points(10)
    assert "vertices 2 and 10" in mesh_error(np.vstack([cloud, cloud[2]]), None)


@pytest.mark.parametrize("repair", [False, True])
def test_non_manifold_edge_is_kept_with_a_warning(repair):
    vertices = np.vstack([TWO_TRIANGLES, [[0.5, 0.5, 1.0]]])
    # Edge (1, 2) is used by three faces.
    surface = Surface(vertices, np.array([[0, 1, 2], [1, 3, 2], [1, 2, 4]]), name="bumpy.ply")
    with pytest.warns(
        SurfaceWarning,
        match=r"bumpy.ply: 1 non-manifold edges \(first: between vertices 1 and 2, "
        r"shared by 3 faces \[0, 1, 2\]\)",
    ):
        assert validate_surface(surface, repair=repair) is surface


def test_repair_surface_maps_every_input_vertex():
    # Vertex 4 duplicates vertex 1; face 2 is degenerate.
    vertices = np.vstack([TWO_TRIANGLES, TWO_TRIANGLES[1]])
    surface = Surface(vertices, np.array([[0, 1, 2], [4, 3, 2], [0, 0, 2]]), fields={"f": np.arange(5.0)})
    repaired = repair_surface(surface)
    assert repaired.surface.n_vertices == 4 and repaired.surface.n_faces == 2
    np.testing.assert_array_equal(repaired.vertex_map, [0, 1, 2, 3, 1])
    np.testing.assert_array_equal(repaired.surface.vertices[repaired.vertex_map], vertices)
    assert repaired.describe() == "merged 1 duplicate vertices, dropped 1 degenerate faces"
    clean = repair_surface(Surface(TWO_TRIANGLES, TWO_FACES))
    np.testing.assert_array_equal(clean.vertex_map, np.arange(4))
    assert clean.describe() == ""


def test_field_length_mismatch():
    message = mesh_error(TWO_TRIANGLES, TWO_FACES, J2m=np.zeros(3))
    assert "field 'J2m'" in message and "expected 4" in message and "got 3" in message


def test_wrong_shapes_rejected_at_construction():
    with pytest.raises(SurfaceError, match=r"vertices must have shape \(N, 3\)"):
        Surface(np.zeros((4, 2)))
    with pytest.raises(SurfaceError, match=r"face 0 has non-integer"):
        Surface(TWO_TRIANGLES, np.array([[0, 1, 2.5]]))


def test_valid_surface_is_returned_unchanged():
    surface = icosphere(1)
    assert validate_surface(surface) is surface


def test_repair_merges_duplicates_and_drops_degenerate_faces():
    # Vertex 4 duplicates vertex 1; face [1, 4, 2] collapses after the merge; face [0, 2, 2] is degenerate.
    vertices = np.vstack([TWO_TRIANGLES, TWO_TRIANGLES[1], [[-1.0, -1.0, 0.0]]])
    faces = np.array([[0, 1, 2], [4, 3, 2], [1, 4, 2], [0, 2, 2], [5, 1, 0]])
    labels = np.array([10.0, 11.0, 12.0, 13.0, 14.0, 15.0])
    surface = Surface(vertices, faces, fields={"label": labels}, name="fix.ply")
    repaired = validate_surface(surface, repair=True)
    np.testing.assert_array_equal(repaired.vertices, vertices[[0, 1, 2, 3, 5]])
    np.testing.assert_array_equal(repaired.faces, [[0, 1, 2], [1, 3, 2], [4, 1, 0]])
    np.testing.assert_array_equal(repaired.fields["label"], [10.0, 11.0, 12.0, 13.0, 15.0])
    assert repaired.name == "fix.ply"
    assert validate_surface(repaired) is repaired  # the result is valid
    assert surface.n_vertices == 6  # the input is not modified


# ---------------------------------------------------------------------------------------------- geometry
def test_icosphere_area_normals_and_closedness():
    sphere = icosphere(4)
    assert abs(sphere.area - 4 * np.pi) / (4 * np.pi) < 0.01
    np.testing.assert_allclose(sphere.vertex_areas().sum(), sphere.area, rtol=1e-12)
    normals = sphere.vertex_normals()
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0)
    assert np.min(np.einsum("ij,ij->i", normals, sphere.vertices)) > 0.999
    assert not sphere.boundary_vertices().any()
    edges = sphere.edges()
    assert sphere.n_vertices - len(edges) + sphere.n_faces == 2  # Euler characteristic of a sphere
    assert np.all(edges[:, 0] < edges[:, 1])


def test_grid_boundary_edges_and_area(grid_surface):
    surface = grid_surface
    expected = np.zeros((4, 4), dtype=bool)
    expected[[0, -1], :] = expected[:, [0, -1]] = True
    np.testing.assert_array_equal(surface.boundary_vertices(), expected.ravel())
    assert len(surface.edges()) == 3 * 4 * 2 + 9  # 24 axis-aligned edges and one diagonal per cell
    assert surface.area == pytest.approx(9.0, rel=1e-14)
    np.testing.assert_allclose(surface.face_normals(), np.tile([0.0, 0.0, 1.0], (18, 1)))


def test_point_cloud_properties():
    cloud = Surface(random_sphere_points(500))
    assert cloud.is_point_cloud and cloud.n_faces == 0
    assert cloud.edges().shape == (0, 2)
    assert not cloud.boundary_vertices().any()
    with pytest.raises(SurfaceError, match="point cloud"):
        cloud.face_areas()


def test_point_cloud_normals_point_outward_on_every_component():
    first = random_sphere_points(800, seed=1)
    second = 0.5 * random_sphere_points(400, seed=2) + [4.0, 0.0, 0.0]  # a separate, smaller sphere
    cloud = Surface(np.vstack([first, second]))
    normals = cloud.vertex_normals()
    outward = np.vstack([first, (second - [4.0, 0.0, 0.0]) / 0.5])
    assert np.min(np.einsum("ij,ij->i", normals, outward)) > 0.9
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0)


def test_given_normals_win():
    points = random_sphere_points(50)
    cloud = Surface(points, normals=-2.0 * points)
    np.testing.assert_allclose(cloud.vertex_normals(), -points)


def test_point_cloud_area_estimate():
    for points in (random_sphere_points(3000), np.asarray(trimesh.creation.icosphere(subdivisions=3).vertices)):
        area = Surface(points).area
        assert abs(area - 4 * np.pi) / (4 * np.pi) < 0.03


def test_geometry_hash_is_stable_and_sensitive():
    surface = Surface(TWO_TRIANGLES, TWO_FACES, fields={"a": np.zeros(4)}, name="x")
    # Pinned: caches on disk are keyed by this value; changing the hash silently invalidates them.
    assert surface.geometry_hash() == "76ef1cef55f3bfa7bc06fda2c57e06fb3e9d1b1c725c1265f9194e0a59129057"
    assert surface.copy().geometry_hash() == surface.geometry_hash()
    assert surface.with_fields(b=np.ones(4)).geometry_hash() == surface.geometry_hash()
    moved = surface.copy()
    moved.vertices[2, 2] = 1e-9
    assert moved.geometry_hash() != surface.geometry_hash()
    assert Surface(TWO_TRIANGLES).geometry_hash() != surface.geometry_hash()


def test_copy_and_with_fields():
    surface = Surface(TWO_TRIANGLES, TWO_FACES, fields={"a": np.zeros(4)})
    copied = surface.copy()
    copied.vertices[0, 0] = 5.0
    copied.fields["a"][0] = 5.0
    assert surface.vertices[0, 0] == 0.0 and surface.fields["a"][0] == 0.0
    extended = surface.with_fields({"b": np.ones(4)}, a=np.full(4, 2.0))
    assert set(extended.fields) == {"a", "b"} and extended.fields["a"][0] == 2.0
    assert set(surface.fields) == {"a"}


# ---------------------------------------------------------------------------------------------- normalisation
def test_normalize_area_exact_with_field_scaling():
    sphere = icosphere(2)
    n = sphere.n_vertices
    sphere = Surface(
        sphere.vertices * 3.0 + [1.0, -2.0, 5.0],
        sphere.faces,
        fields={"J2m": np.linspace(0.1, 0.3, n), "label": np.arange(n)},
    )
    area = sphere.area
    scaled, scale = normalize_area(sphere, 100.0, {"J2m": 0.5})
    assert scaled.area == pytest.approx(100.0, rel=1e-12)
    assert scale == pytest.approx(np.sqrt(100.0 / area), rel=1e-15)
    np.testing.assert_allclose(scaled.fields["J2m"], sphere.fields["J2m"] * np.sqrt(100.0 / area), rtol=1e-15)
    np.testing.assert_array_equal(scaled.fields["label"], sphere.fields["label"])
    # Scaling is about the area-weighted centroid, which stays where it was.
    centroid = sphere.vertex_areas() @ sphere.vertices / area
    new_centroid = scaled.vertex_areas() @ scaled.vertices / scaled.area
    np.testing.assert_allclose(new_centroid, centroid, atol=1e-12)
    np.testing.assert_allclose(scaled.vertices - centroid, scale * (sphere.vertices - centroid), atol=1e-12)
    # Exponent 1 scales like area itself.
    doubled, _ = normalize_area(sphere, 2 * area, {"J2m": 1.0})
    np.testing.assert_allclose(doubled.fields["J2m"], 2 * sphere.fields["J2m"], rtol=1e-15)


def test_a_fixed_scale_ignores_the_area():
    """FixedScale(f): positions times f about the centroid, fields times f^(2e), whatever the area: a
    hemisphere and its whole sphere get the same factor (partial scans keep their size)."""
    sphere = icosphere(2)
    sphere = Surface(sphere.vertices * 3.0, sphere.faces, fields={"J2m": np.linspace(0.1, 0.3, sphere.n_vertices)})
    upper = sphere.faces[(sphere.vertices[sphere.faces].mean(axis=1)[:, 2] > 0)]
    half = Surface(sphere.vertices, upper, fields=sphere.fields)
    for surface in (sphere, half):
        scaled, scale = normalize_area(surface, FixedScale(2.5), {"J2m": 0.5})
        assert scale == 2.5
        assert scaled.area == pytest.approx(6.25 * surface.area, rel=1e-12)
        np.testing.assert_allclose(scaled.fields["J2m"], 2.5 * surface.fields["J2m"], rtol=1e-15)
    with pytest.raises(ValueError, match="positive"):
        FixedScale(0.0)


def test_normalize_area_point_cloud_and_errors():
    cloud = Surface(random_sphere_points(600))
    scaled, scale = normalize_area(cloud, 50.0)
    assert scaled.area == pytest.approx(50.0, rel=1e-9)
    assert scale == pytest.approx(np.sqrt(50.0 / cloud.area))
    with pytest.raises(SurfaceError, match="target area"):
        normalize_area(cloud, -1.0)
    with pytest.raises(SurfaceError, match=r"missing field\(s\) \['J2m'\]"):
        normalize_area(cloud, 1.0, {"J2m": 0.5})


# ---------------------------------------------------------------------------------------------- sampling
def test_sampling_is_reproducible_and_seed_dependent(sphere_surface):
    sphere = sphere_surface
    a = sample_surface(sphere, 2000, seed=7)
    b = sample_surface(sphere, 2000, seed=7)
    c = sample_surface(sphere, 2000, seed=8)
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.face_index, b.face_index)
    assert (a.interpolation != b.interpolation).nnz == 0
    assert not np.allclose(a.points, c.points)
    assert a.n_samples == 2000 and a.points.shape == (2000, 3) and a.barycentric.shape == (2000, 3)


def test_samples_lie_on_the_sphere_mesh():
    sphere = icosphere(3)
    samples = sample_surface(sphere, 5000, seed=0)
    # A point on a flat triangle of the unit icosphere is between the triangle's plane distance and 1.
    corners = sphere.vertices[sphere.faces]
    plane_distance = np.abs(np.einsum("fi,fi->f", sphere.face_normals(), corners[:, 0]))
    radius = np.linalg.norm(samples.points, axis=1)
    assert np.all(radius <= 1.0 + 1e-12)
    assert np.all(radius >= plane_distance[samples.face_index] - 1e-12)
    # Each sample is inside its face: non-negative barycentric weights reproducing the point.
    assert np.all(samples.barycentric >= 0)
    np.testing.assert_allclose(samples.barycentric.sum(axis=1), 1.0, atol=1e-15)
    np.testing.assert_allclose(
        np.einsum("mc,mcd->md", samples.barycentric, corners[samples.face_index]), samples.points, atol=1e-15
    )
    np.testing.assert_allclose(samples.normals, sphere.face_normals()[samples.face_index])


def test_face_counts_are_proportional_to_area():
    # Triangles whose areas differ by up to 40x, plus one zero-area face that must never be picked.
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [4, 0, 0], [0, 4, 0], [0, 0, 0.5], [8, 0, 0]], float)
    faces = np.array([[0, 1, 2], [1, 3, 4], [0, 2, 5], [1, 4, 2], [0, 1, 6]])
    surface = Surface(vertices, faces)
    m = 40000
    samples = sample_surface(surface, m, seed=3)
    areas = surface.face_areas()
    counts = np.bincount(samples.face_index, minlength=len(faces))
    assert counts[4] == 0 and areas[4] == 0
    expected = m * areas[:4] / areas.sum()
    chi_square = np.sum((counts[:4] - expected) ** 2 / expected)
    assert chi_square < 16.3  # 99.9 % quantile of chi-square with 3 degrees of freedom


def test_samples_are_uniform_inside_a_triangle():
    triangle = Surface(np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [0.0, 1.0, 0.0]]), np.array([[0, 1, 2]]))
    m = 20000
    samples = sample_surface(triangle, m, seed=5)
    # The midpoint subdivision splits the triangle into four parts of equal area: three corner triangles
    # (one barycentric weight above 1/2) and the middle one.
    corner = np.argmax(samples.barycentric > 0.5, axis=1)
    part = np.where((samples.barycentric > 0.5).any(axis=1), corner, 3)
    counts = np.bincount(part, minlength=4)
    chi_square = np.sum((counts - m / 4) ** 2 / (m / 4))
    assert chi_square < 16.3  # 99.9 % quantile of chi-square with 3 degrees of freedom
    np.testing.assert_allclose(samples.points.mean(axis=0), [1.0, 1.0 / 3.0, 0.0], atol=0.02)


def test_interpolation_reproduces_linear_functions(sphere_surface):
    sphere = sphere_surface
    samples = sample_surface(sphere, 3000, seed=1)
    matrix = samples.interpolation
    assert matrix.shape == (3000, sphere.n_vertices)
    assert matrix.format == "csr"
    np.testing.assert_allclose(np.asarray(matrix.sum(axis=1)).ravel(), 1.0, atol=1e-15)
    a, b = np.array([0.3, -1.7, 2.2]), 0.8
    values = matrix @ (sphere.vertices @ a + b)
    np.testing.assert_allclose(values, samples.points @ a + b, atol=1e-12)
    # Multi-channel fields go through the same matrix.
    np.testing.assert_allclose(matrix @ sphere.vertices, samples.points, atol=1e-12)


def test_point_cloud_samples_are_the_points():
    points = random_sphere_points(300)
    cloud = Surface(points)
    samples = sample_surface(cloud, 5000, seed=4)  # n_samples is ignored for clouds
    np.testing.assert_array_equal(samples.points, points)
    assert samples.face_index is None
    assert (samples.interpolation != np.eye(300)).sum() == 0
    np.testing.assert_array_equal(samples.barycentric, np.tile([1.0, 0.0, 0.0], (300, 1)))
    np.testing.assert_allclose(samples.normals, cloud.vertex_normals())


def test_sampling_rejects_bad_counts():
    with pytest.raises(SurfaceError, match="n_samples"):
        sample_surface(icosphere(1), 0)


def test_no_warning_for_clean_meshes(sphere_surface):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        validate_surface(sphere_surface)


# ---------------------------------------------------------------------------------------------- curvature
def test_mean_curvature_sphere_mesh_and_cloud():
    radius = 2.0
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=radius)
    # All but the 12 valence-5 vertices of the icosphere (a known ~15 % bias of the cotan estimate with
    # barycentric areas) are within 3 %.
    for surface in (Surface(mesh.vertices, mesh.faces, name="sphere"), Surface(mesh.vertices, name="cloud")):
        error = np.abs(surface.mean_curvature() * radius - 1.0)
        assert np.sort(error)[-13] < 0.03 and error.max() < 0.2
    # Flipping the orientation flips the sign.
    flipped = Surface(mesh.vertices, mesh.faces[:, ::-1], name="flipped")
    np.testing.assert_allclose(flipped.mean_curvature(), -Surface(mesh.vertices, mesh.faces).mean_curvature())


def test_mean_curvature_cylinder_and_plane(cylinder_surface):
    cylinder = cylinder_surface  # radius 1.5
    inside = np.abs(cylinder.vertices[:, 2]) < 2.5  # away from the cut ends
    np.testing.assert_allclose(cylinder.mean_curvature()[inside], 1.0 / (2 * 1.5), rtol=0.02)
    plane = grid(6)
    assert np.abs(plane.mean_curvature()).max() < 1e-12
    rng = np.random.default_rng(0)
    cloud = Surface(np.column_stack([rng.uniform(0, 5, (400, 2)), np.zeros(400)]), name="flat cloud")
    assert np.abs(cloud.mean_curvature()).max() < 1e-9


def test_mean_curvature_smoothing_keeps_constants_and_follows_reindexing():
    surface = icosphere(3)
    np.testing.assert_allclose(surface.mean_curvature(smoothing_steps=3), surface.mean_curvature().mean(), rtol=0.02)
    bumpy = Surface(surface.vertices * (1 + 0.05 * np.sin(5 * surface.vertices[:, :1])), surface.faces, name="bumpy")
    permutation = np.random.default_rng(1).permutation(bumpy.n_vertices)
    inverse = np.argsort(permutation)
    shuffled = Surface(bumpy.vertices[permutation], inverse[bumpy.faces], name="shuffled")
    for steps in (0, 2):
        np.testing.assert_allclose(shuffled.mean_curvature(steps), bumpy.mean_curvature(steps)[permutation], atol=1e-12)
    # Smoothing reduces the spread of a noisy field but not its area-weighted mean.
    raw, smooth = bumpy.mean_curvature(), bumpy.mean_curvature(smoothing_steps=2)
    assert smooth.std() < raw.std()
