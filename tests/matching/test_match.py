"""The shipped descriptor model matches small held-out generated bodies, each remeshed on its own; the
matcher answers per input vertex of a repaired file; ``zernet match`` writes its files."""

from __future__ import annotations

import dataclasses
import importlib.util

import numpy as np
import pytest
import trimesh

from zernet.cli import main
from zernet.geometry import Surface
from zernet.matching import PRETRAINED_MODEL, load_matching_model, match_surfaces
from zernet.matching.match import load_matcher, match_shapes
from zernet.matching.shapes import prepare_shape

needs_bodies = pytest.mark.skipif(
    importlib.util.find_spec("anny") is None or importlib.util.find_spec("pymeshlab") is None,
    reason="needs the bodies extra (anny, pymeshlab)",
)

#: Mean Euclidean error x100 / sqrt(target area) the shipped model must stay under on the two test pairs
#: below (coarse-615 test bodies remeshed independently; 1.65 and 3.79, mean 2.7, when the model was
#: shipped).
ERROR_BOUND = 6.0

#: Bound on the shipped template model's error (same unit) for a body's vertices given as a point cloud,
#: matched to another body's mesh: measured 2.86 on the pair below (2.82 without the map repair; per point:
#: median 2.9, 90th percentile 6.5); pairs whose limbs go to the wrong limb score 10 to 19 (issue 51).
CLOUD_ERROR_BOUND = 4.5

#: Bound on the template model's error (same unit) when a shape is matched to itself turned: measured 0.06
#: (99 % of the vertices onto themselves). The blob's mean edge is 5.2 in this unit, so the bound is a fifth of
#: an edge on average; a map one ring off or flipped is far above it.
TURNED_ERROR_BOUND = 1.0


def _error(target: Surface, vertex_map: np.ndarray, truth: np.ndarray) -> float:
    """Mean Euclidean distance between the mapped and the true target vertices, x100 / sqrt(target area)."""
    vertices = target.vertices
    return 100 * np.linalg.norm(vertices[vertex_map] - vertices[truth], axis=1).mean() / np.sqrt(target.area)


@pytest.fixture(scope="module")
def held_out_bodies(tmp_path_factory):
    from zernet.matching.bodies import body_forms

    cache = tmp_path_factory.mktemp("cache")
    return body_forms(range(3), "test", {"remeshed": 1.0}, 0, "coarse-615", "varied", 0, cache)


def test_shipped_model_is_in_the_package_with_its_provenance():
    model, provenance = load_matching_model()
    assert PRETRAINED_MODEL.is_file() and PRETRAINED_MODEL.stat().st_size < 8 * 2**20
    assert {"command", "commit", "config"} <= set(provenance)
    assert model.spec.descriptor_size > 0 and not model.training


@needs_bodies
def test_shipped_model_matches_held_out_remeshed_bodies(held_out_bodies, one_torch_thread):
    from zernet.matching.bodies import ground_truth_map

    forms, body_vertices, faces = held_out_bodies
    model, _ = load_matching_model()
    spec = model.spec
    errors = []
    for a, b in ((0, 1), (1, 2)):
        source, target = (
            prepare_shape(
                forms[i].surface,
                spec.patch_config_objects(),
                spec.area,
                spec.feature_kind,
                spec.n_eigen,
                name=forms[i].name,
            )
            for i in (a, b)
        )
        result = match_shapes(model, source, target)
        truth = ground_truth_map(forms[a], forms[b], body_vertices[forms[b].body], faces)
        errors.append(_error(target.surface, result.vertex_map, truth))
        assert result.vertex_map.shape == (source.n_vertices,) and result.reverse_map.shape == (target.n_vertices,)
        assert result.fmap.shape == (spec.zoomout_end, spec.zoomout_end)
        assert 0 <= result.confidence.min() and result.confidence.max() <= 1
    assert np.mean(errors) < ERROR_BOUND, errors


def _small_body(subdivisions: int = 3) -> Surface:
    """A small asymmetric closed mesh (bumpy ellipsoid), no anny needed."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    vertices = np.asarray(sphere.vertices) * [0.3, 0.9, 0.2]
    vertices *= 1 + 0.05 * np.sin(5 * vertices[:, :1] + 3 * vertices[:, 1:2])
    return Surface(vertices, np.asarray(sphere.faces), name="blob")


def test_match_answers_per_input_vertex_of_a_repaired_file(one_torch_thread):
    """A duplicated vertex (merged by the repair) still gets an answer, and is answered for."""
    body = _small_body()
    duplicated = Surface(np.vstack([body.vertices, body.vertices[:1]]), body.faces, name="dup")
    result, source, target = match_surfaces(duplicated, body)
    assert result.vertex_map.shape == (body.n_vertices + 1,)
    assert result.vertex_map[-1] == result.vertex_map[0]
    assert result.reverse_map.shape == (body.n_vertices,) and result.reverse_map.max() < body.n_vertices + 1
    assert source.n_vertices == body.n_vertices


def test_cli_match_writes_the_map_the_fmap_the_confidence_and_a_picture(tmp_path, one_torch_thread):
    body = _small_body()
    rotated = Surface(body.vertices @ np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]).T, body.faces)
    paths = []
    for name, vertices in (("a", body.vertices), ("b", rotated.vertices)):
        paths.append(tmp_path / f"{name}.ply")
        trimesh.Trimesh(vertices, body.faces, process=False).export(paths[-1])
    prefix = tmp_path / "out" / "ab"
    assert main(["match", str(paths[0]), str(paths[1]), "--out", str(prefix)]) == 0
    vertex_map = np.load(prefix.with_name("ab.npy"))
    assert vertex_map.shape == (body.n_vertices,) and vertex_map.dtype == np.int64
    # The target is the source turned: each vertex belongs on itself.
    assert _error(rotated, vertex_map, np.arange(body.n_vertices)) < TURNED_ERROR_BOUND
    np.testing.assert_array_equal(np.loadtxt(prefix.with_name("ab.txt"), dtype=np.int64), vertex_map)
    assert np.load(prefix.with_name("ab_fmap.npy")).ndim == 2
    assert np.load(prefix.with_name("ab_confidence.npy")).shape == (body.n_vertices,)
    assert prefix.with_name("ab.png").stat().st_size > 10_000
    assert main(["match", str(paths[0]), str(tmp_path / "missing.ply"), "--out", str(prefix)]) == 2


@needs_bodies
def test_cli_match_maps_a_point_cloud_onto_a_mesh(held_out_bodies, tmp_path, one_torch_thread):
    """A body's vertices without their faces (a cloud file) matched to another body: against the ground truth."""
    from zernet.matching.bodies import ground_truth_map

    forms, body_vertices, faces = held_out_bodies
    source, target = forms[0].surface, forms[1].surface
    cloud, mesh, prefix = tmp_path / "cloud.ply", tmp_path / "mesh.ply", tmp_path / "out"
    cloud.write_bytes(trimesh.PointCloud(source.vertices).export(file_type="ply"))
    trimesh.Trimesh(target.vertices, target.faces, process=False).export(mesh)
    assert main(["match", str(cloud), str(mesh), "--out", str(prefix), "--no-picture"]) == 0
    vertex_map = np.load(prefix.with_name("out.npy"))
    assert vertex_map.shape == (source.n_vertices,)
    truth = ground_truth_map(forms[0], forms[1], body_vertices[forms[1].body], faces)
    assert _error(target, vertex_map, truth) < CLOUD_ERROR_BOUND


def test_a_fine_surface_is_read_through_a_coarse_copy_and_answered_per_vertex(one_torch_thread):
    # descriptor_vertices: the model reads a copy of about that many vertices (its training resolution);
    # the eigenbasis, the map and the answer stay on the surface itself.
    model, _ = load_matching_model()
    spec = dataclasses.replace(model.spec, descriptor_vertices=800)
    model.spec = spec
    fine = _small_body(4)  # 2,562 vertices
    turned = Surface(fine.vertices @ np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]).T, fine.faces)
    source, target = (
        prepare_shape(
            s, spec.patch_config_objects(), spec.area, spec.feature_kind, spec.n_eigen, descriptor_vertices=800
        )
        for s in (fine, turned)
    )
    assert source.n_vertices == fine.n_vertices and source.descriptor_index.shape == (fine.n_vertices,)
    assert 700 <= len(source.features) <= 900 and source.basis.eigenvectors.shape[0] == fine.n_vertices
    assert abs(source.surface.area / spec.area - 1) < 0.03  # scaled by the copy's factor
    result = match_shapes(model, source, target)
    distance = np.linalg.norm(source.surface.vertices[result.vertex_map] - source.surface.vertices, axis=1)
    assert distance.mean() < 0.05 * np.sqrt(spec.area)


@pytest.mark.parametrize("kind", ["template", "descriptors"])
def test_same_scale_keeps_a_part_at_its_size(tmp_path, one_torch_thread, kind):
    model = load_matcher() if kind == "template" else load_matching_model()[0]
    area = model.area if kind == "template" else model.spec.area
    body = _small_body()
    kept = np.flatnonzero(body.vertices[:, 1] > 0)
    inside = np.isin(body.faces, kept).all(axis=1)
    renumber = np.full(body.n_vertices, -1)
    renumber[kept] = np.arange(len(kept))
    half = Surface(body.vertices[kept], renumber[body.faces[inside]], name="half")
    result, source, target = match_surfaces(half, body, model, same_scale=True)
    assert abs(source.surface.area / target.surface.area - half.area / body.area) < 1e-6
    assert abs(target.surface.area - area) < 1e-6 * target.surface.area
    assert result.vertex_map.shape == (half.n_vertices,)
    _, source, _ = match_surfaces(half, body, model)  # without: each at the model's area
    assert abs(source.surface.area / target.surface.area - 1) < 1e-6
    paths = [tmp_path / "half.ply", tmp_path / "body.ply"]
    for path, surface in zip(paths, (half, body)):
        trimesh.Trimesh(surface.vertices, surface.faces, process=False).export(path)
    prefix = tmp_path / "hb"
    options = ["--same-scale", "--no-picture"] + (["--descriptors"] if kind == "descriptors" else [])
    assert main(["match", *map(str, paths), "--out", str(prefix), *options]) == 0
    assert np.load(prefix.with_name("hb.npy")).shape == (half.n_vertices,)
