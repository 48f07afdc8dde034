"""Bodies in the forms scans come in (zernet.data.bodies.forms, write_forms, `zernet bodies --forms`).

Small procedural meshes (an ellipsoid with 8 height bands as its "parts") stand in for bodies, so only the
command-line test needs anny.
"""

import importlib.util

import numpy as np
import pytest
import trimesh

from zernet.cli import main
from zernet.data import DatasetError
from zernet.data.bodies import (
    FORMS,
    closest_points,
    cloud_form,
    decimated_form,
    ground_truth,
    make_forms,
    noisy_cloud_form,
    nonmanifold_edge_count,
    partial_form,
    remeshed_form,
    resolve_forms,
    write_forms,
)
from zernet.data.bodies.forms import duplicate_face_count
from zernet.data.bodies.generator import Body
from zernet.data.options import LoaderOptions
from zernet.data.segmentation import load_segmentation, read_labels
from zernet.geometry import load_surface
from zernet.operators import PatchConfig

needs_pymeshlab = pytest.mark.skipif(
    importlib.util.find_spec("pymeshlab") is None, reason="needs pymeshlab (the bodies extra)"
)


def _ellipsoid(subdivisions: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices, faces, labels): an ellipsoid 1.6 high, outward faces, labels 0-7 in height bands."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    vertices = np.asarray(sphere.vertices) * [0.3, 0.8, 0.2]
    faces = np.asarray(sphere.faces, dtype=np.int64)
    height = (vertices[:, 1] - vertices[:, 1].min()) / np.ptp(vertices[:, 1])
    labels = np.minimum((height * 8).astype(np.int64), 7)
    return vertices, faces, labels


def _normals(vertices, faces):
    triangles = vertices[faces]
    return np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])


def _assert_ground_truth_consistent(form, vertices, faces, labels):
    """Labels are the template vertex's, and the template vertex is a corner of the face nearest the point."""
    assert form.labels.shape == form.template_vertex.shape == (len(form.vertices),)
    np.testing.assert_array_equal(form.labels, labels[form.template_vertex])
    face_index, _, _, _ = closest_points(vertices, faces, form.vertices)
    assert np.isin(form.template_vertex, faces[face_index]).mean() > 0.99


def test_closest_points_match_brute_force():
    vertices, faces, _ = _ellipsoid(2)
    points = np.random.default_rng(0).normal(scale=0.5, size=(60, 3))
    face_index, barycentric, closest, distance = closest_points(vertices, faces, points)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    # Brute force: every triangle, densely sampled, can only be farther than the exact answer.
    samples, _ = trimesh.sample.sample_surface_even(mesh, 20000, seed=1)
    dense = np.linalg.norm(points[:, None] - samples[None], axis=2).min(axis=1)
    assert np.all(distance <= dense + 1e-12)
    assert np.all(dense - distance < 0.02)
    np.testing.assert_allclose(np.linalg.norm(points - closest, axis=1), distance)
    assert np.all(barycentric >= -1e-12) and np.allclose(barycentric.sum(axis=1), 1.0)
    np.testing.assert_allclose(np.einsum("mc,mcd->md", barycentric, vertices[faces[face_index]]), closest)


def test_ground_truth_of_original_vertices_is_themselves():
    vertices, faces, labels = _ellipsoid(2)
    face_index, barycentric, _, distance = closest_points(vertices, faces, vertices)
    parts, template = ground_truth(faces, labels, face_index, barycentric)
    assert distance.max() == 0.0
    np.testing.assert_array_equal(template, np.arange(len(vertices)))
    np.testing.assert_array_equal(parts, labels)


@needs_pymeshlab
def test_remeshed_is_a_new_triangulation_on_the_surface():
    vertices, faces, labels = _ellipsoid(3)
    form = remeshed_form(vertices, faces, labels, np.random.default_rng(0))
    assert form.faces is not None and len(form.vertices) != len(vertices)
    assert form.faces.min() >= 0 and form.faces.max() < len(form.vertices)
    _, _, _, distance = closest_points(vertices, faces, form.vertices)
    diagonal = np.linalg.norm(np.ptp(vertices, axis=0))
    # MeshLab reprojects every vertex on the input surface: measured 1e-16 of the diagonal.
    assert distance.max() < 1e-9 * diagonal
    assert form.details["max_distance"] == pytest.approx(distance.max(), abs=1e-15)
    _assert_ground_truth_consistent(form, vertices, faces, labels)
    other = remeshed_form(vertices, faces, labels, np.random.default_rng(1))
    assert len(other.vertices) != len(form.vertices)  # per-body targets: triangulations differ


def test_cloud_has_no_faces_and_exact_ground_truth():
    vertices, faces, labels = _ellipsoid(3)
    form = cloud_form(vertices, faces, labels, np.random.default_rng(0))
    assert form.faces is None and form.is_cloud and form.vertices.shape == vertices.shape
    _, _, _, distance = closest_points(vertices, faces, form.vertices)
    assert distance.max() < 1e-12
    _assert_ground_truth_consistent(form, vertices, faces, labels)
    # The template vertex is the nearest corner of the face the point lies in (largest barycentric weight
    # on a triangle that is close to equilateral): never farther than the other corners.
    near = np.linalg.norm(form.vertices - vertices[form.template_vertex], axis=1)
    edge = np.linalg.norm(vertices[faces[:, 0]] - vertices[faces[:, 1]], axis=1).max()
    assert near.max() < edge


def test_noisy_cloud_noise_density_and_clean_ground_truth():
    vertices, faces, labels = _ellipsoid(4)
    noisy = noisy_cloud_form(vertices, faces, labels, np.random.default_rng(3), noise=0.01)
    clean = noisy_cloud_form(vertices, faces, labels, np.random.default_rng(3), noise=0.0)
    assert noisy.faces is None and len(noisy.vertices) == round(0.5 * len(vertices))
    # Same draws but the noise: the ground truth is the noise-free position's.
    np.testing.assert_array_equal(noisy.labels, clean.labels)
    np.testing.assert_array_equal(noisy.template_vertex, clean.template_vertex)
    noise = noisy.vertices - clean.vertices
    assert noise.std() == pytest.approx(0.01, rel=0.2)
    assert abs(noise.mean()) < 0.002
    # Denser where the random field is high: its mean over the points exceeds its mean over a uniform cloud.
    details = clean.details
    assert details["contrast"] == 3.0

    def field(points):
        return np.cos(
            2 * np.pi * (points @ details["field_directions"].T) / details["field_wavelengths"]
            + details["field_phases"]
        ).sum(axis=1)

    uniform = cloud_form(vertices, faces, labels, np.random.default_rng(4), n_points=20000)
    assert field(clean.vertices).mean() > field(uniform.vertices).mean() + 0.1 * field(uniform.vertices).std()


def test_partial_keeps_the_side_facing_the_camera():
    vertices, faces, labels = _ellipsoid(3)
    direction = np.array([0.0, 0.0, 1.0])
    form = partial_form(vertices, faces, labels, np.random.default_rng(0), direction=direction)
    assert np.all(_normals(form.vertices, form.faces) @ direction > 0)
    assert 0.4 < len(form.faces) / len(faces) < 0.6  # a convex shape: about half
    np.testing.assert_array_equal(np.unique(form.faces), np.arange(len(form.vertices)))  # renumbered, all used
    np.testing.assert_array_equal(form.vertices, vertices[form.template_vertex])
    np.testing.assert_array_equal(form.labels, labels[form.template_vertex])
    # Drawn directions are horizontal within 20 degrees (y up).
    drawn = partial_form(vertices, faces, labels, np.random.default_rng(1)).details["direction"]
    assert abs(drawn[1]) <= np.sin(np.radians(20)) + 1e-12


def test_partial_hides_what_is_behind():
    front = trimesh.creation.icosphere(subdivisions=2)
    back = trimesh.creation.icosphere(subdivisions=2)
    back.apply_scale(0.8)
    back.apply_translation([0.0, 0.0, -3.0])
    vertices = np.concatenate([front.vertices, back.vertices])
    faces = np.concatenate([front.faces, back.faces + len(front.vertices)]).astype(np.int64)
    labels = np.repeat([0, 1], [len(front.vertices), len(back.vertices)])
    form = partial_form(vertices, faces, labels, np.random.default_rng(0), direction=[0.0, 0.0, 1.0])
    assert set(form.labels.tolist()) == {0}  # the sphere behind is hidden whole
    seen_from_behind = partial_form(vertices, faces, labels, np.random.default_rng(0), direction=[0.0, 0.0, -1.0])
    assert set(seen_from_behind.labels.tolist()) == {0, 1}  # the smaller one in front hides part of the other


def test_partial_occlusion_uses_the_depth_of_the_occluder_at_the_ray():
    # A large triangle sloping in depth (z = y + 1 above (x, y)) and two small ones seen through it along +z
    # at (x, y) = (-0.5, -0.5), where the slope is at z = 0.5: one just in front (kept), one just behind.
    slope = [[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [-1.0, 1.0, 2.0]]
    small = np.array([[0.0, 0.0, 0.0], [0.02, 0.0, 0.0], [0.0, 0.02, 0.0]]) - [0.02 / 3, 0.02 / 3, 0.0]
    vertices = np.concatenate([slope, small + [-0.5, -0.5, 0.55], small + [-0.5, -0.5, 0.45]])
    faces = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8]])
    labels = np.repeat([0, 1, 2], 3)
    form = partial_form(vertices, faces, labels, np.random.default_rng(0), direction=[0.0, 0.0, 1.0])
    assert sorted(set(form.labels.tolist())) == [0, 1]


def test_nonmanifold_edges_counted_on_a_hand_made_mesh():
    # Three triangles on edge (0, 1) (non-manifold), a fourth sharing only edge (1, 2) with the first.
    faces = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4], [2, 1, 5]])
    assert nonmanifold_edge_count(faces) == 1
    # A triangle (0, 3, 4) three times over: its edges have 3, 4 and 4 faces (with (1, 0, 3) and (0, 1, 4)).
    assert nonmanifold_edge_count(np.concatenate([faces, [[3, 0, 4], [4, 0, 3], [3, 4, 0]]])) == 4
    tetrahedron = np.array([[0, 1, 2], [0, 3, 1], [1, 3, 2], [2, 3, 0]])
    assert nonmanifold_edge_count(tetrahedron) == 0
    assert nonmanifold_edge_count(np.array([[0, 0, 1]])) == 0  # a repeated corner is no edge
    assert duplicate_face_count(np.array([[0, 1, 2], [2, 1, 0], [1, 2, 0], [0, 1, 3]])) == 2


def test_decimated_is_what_the_simplifier_returns():
    import fast_simplification

    vertices, faces, labels = _ellipsoid(3)
    form = decimated_form(vertices, faces, labels, np.random.default_rng(0))
    raw_vertices, raw_faces = fast_simplification.simplify(vertices, faces, target_reduction=0.5)
    # Nothing cleaned: the same vertices (shuffled) and the same number of faces.
    assert len(form.faces) == len(raw_faces) and len(form.vertices) == len(raw_vertices)
    np.testing.assert_allclose(np.sort(form.vertices, axis=0), np.sort(raw_vertices, axis=0))
    assert form.details["nonmanifold_edges"] == nonmanifold_edge_count(raw_faces)
    _assert_ground_truth_consistent(form, vertices, faces, labels)


def test_forms_are_seeded_and_independent_of_the_others_asked_for():
    vertices, faces, labels = _ellipsoid(2)
    body = Body("body_000", "test", vertices, faces, labels)
    cheap = ("decimated", "cloud", "cloud-noisy", "partial")
    first = make_forms(body, cheap, np.random.default_rng(7))
    again = make_forms(body, cheap, np.random.default_rng(7))
    alone = make_forms(body, "cloud-noisy", np.random.default_rng(7))
    other = make_forms(body, cheap, np.random.default_rng(8))
    assert list(first) == list(cheap)
    for name in cheap:
        for key in ("vertices", "labels", "template_vertex"):
            np.testing.assert_array_equal(getattr(first[name], key), getattr(again[name], key))
    np.testing.assert_array_equal(alone["cloud-noisy"].vertices, first["cloud-noisy"].vertices)
    assert not np.array_equal(other["cloud"].vertices, first["cloud"].vertices)


def test_resolve_forms():
    assert resolve_forms(None) == resolve_forms("") == ()
    assert resolve_forms("all") == FORMS
    assert resolve_forms("partial, cloud") == ("cloud", "partial")
    assert resolve_forms(["cloud-noisy"]) == ("cloud-noisy",)
    with pytest.raises(DatasetError, match="unknown body form"):
        resolve_forms("cloud,scan")


def test_write_forms_layout_reads_with_the_segmentation_loader(tmp_path):
    vertices, faces, labels = _ellipsoid(2)
    bodies = [
        Body(f"body_{i:03d}", split, vertices * (1 + 0.1 * i), faces, labels)
        for i, split in enumerate(["train", "train", "test"])
    ]
    layout = write_forms(tmp_path, bodies, ["cloud", "partial"], seed=0, split="test")
    assert layout.root == tmp_path / "forms" and layout.details.is_file()
    assert not (layout.meshes("cloud") / "train").exists()  # test bodies only
    cloud = load_surface(layout.meshes("cloud") / "test" / "body_002.ply")
    assert cloud.is_point_cloud and cloud.n_vertices == len(vertices)
    assert len(read_labels(layout.correspondence("cloud") / "test" / "body_002.txt")) == len(vertices)
    assert layout.summary["partial"]["body_002"]["n_faces"] > 0
    again = write_forms(tmp_path / "again", bodies, ["cloud"], seed=0, split="all")
    assert (again.meshes("cloud") / "train" / "body_001.ply").is_file()
    assert (again.meshes("cloud") / "test" / "body_002.ply").read_bytes() == (
        layout.meshes("cloud") / "test" / "body_002.ply"
    ).read_bytes()

    options = LoaderOptions(
        patch_configs=[PatchConfig(r0=0.5, n_samples=600, patch_size=16, n_max=2)],
        cache_dir=tmp_path / "cache",
        workers=0,
        progress=False,
        n_val=0,
    )
    for form in ("cloud", "partial"):
        data = load_segmentation(layout.meshes(form), layout.labels(form), area=None, options=options)
        assert data.info["class_names"][0] == "head" and [data.names[i] for i in data.splits["test"]] == [
            "test/body_002"
        ]
        np.testing.assert_array_equal(data[0].target, read_labels(layout.labels(form) / "test" / "body_002.txt"))


def test_cli_bodies_forms(tmp_path):
    if importlib.util.find_spec("anny") is None:
        pytest.skip("needs the bodies extra (anny)")
    out = tmp_path / "bodies"
    assert (
        main(
            [
                "bodies",
                str(out),
                "--count",
                "3",
                "--n-test",
                "1",
                "--topology",
                "coarse-369",
                "--forms",
                "cloud,decimated",
                "--cache-dir",
                str(tmp_path / "cache"),
            ]
        )
        == 0
    )
    for form in ("cloud", "decimated"):
        assert (out / "forms" / form / "meshes" / "test" / "body_002.ply").is_file()
        assert (out / "forms" / form / "labels" / "class_names.txt").is_file()
    assert not (out / "forms" / "partial").exists()
    readme = (out / "README.txt").read_text()
    assert "forms/<form>/correspondence" in readme and "non-manifold edges" in readme
    with pytest.raises(SystemExit):
        main(["bodies", str(out), "--forms-split", "some"])
    assert (
        main(
            [
                "bodies",
                str(out),
                "--count",
                "3",
                "--n-test",
                "1",
                "--topology",
                "coarse-369",
                "--forms",
                "scan",
                "--cache-dir",
                str(tmp_path / "cache"),
            ]
        )
        == 2
    )
