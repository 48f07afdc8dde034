"""The global consistency stage: a map with a limb sent to the wrong side is repaired from the vertices whose
map comes back, on meshes and point clouds, against the known answer."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from tests.meshes import ellipsoid
from zernet.geometry import Surface
from zernet.matching.consistency import TRUST_THRESHOLD, landmark_distances, repair_map
from zernet.matching.fmap import cycle_confidence


def _shuffled_copy(surface: Surface, rng, noise: float = 0.0, cloud: bool = False) -> tuple[Surface, np.ndarray]:
    """A copy of ``surface`` in another vertex order (optionally jittered, optionally without faces), and the
    true map: source vertex i is copy vertex ``truth[i]``."""
    order = rng.permutation(surface.n_vertices)  # copy vertex j is source vertex order[j]
    truth = np.argsort(order)
    vertices = surface.vertices[order] + noise * rng.standard_normal((surface.n_vertices, 3))
    faces = None if cloud else truth[surface.faces]
    return Surface(vertices, faces, name="copy"), truth


def _swapped_end(source: Surface, target: Surface, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(a map that sends the +x end of the shape to its mirror image, the -x end, as a limb sent to the other
    limb; the true reverse map; the swapped vertices)."""
    x = source.vertices[:, 0]
    swapped = np.flatnonzero(x > 0.5 * x.max())
    mirror = source.vertices[swapped] * [-1.0, 1.0, 1.0]
    nearest_mirror = np.argmin(((source.vertices[None, :, :] - mirror[:, None, :]) ** 2).sum(axis=2), axis=1)
    vertex_map = truth.copy()
    vertex_map[swapped] = truth[nearest_mirror]
    reverse_map = np.argsort(truth)
    return vertex_map, reverse_map, swapped


def _mean_error(target: Surface, predicted: np.ndarray, truth: np.ndarray, among: np.ndarray) -> float:
    return float(np.linalg.norm(target.vertices[predicted[among]] - target.vertices[truth[among]], axis=1).mean())


@pytest.fixture(scope="module")
def shape() -> Surface:
    # An ellipsoid of three different axes (3 x 2 x 1 after scaling): intrinsically symmetric, like a body.
    surface = ellipsoid(subdivisions=3)
    extent = np.ptp(surface.vertices, axis=0)
    return Surface(surface.vertices * ([3.0, 2.0, 1.0] / extent), surface.faces, name="ellipsoid")


def _edge_length(surface: Surface) -> float:
    faces = surface.faces
    return float(np.linalg.norm(surface.vertices[faces[:, 0]] - surface.vertices[faces[:, 1]], axis=1).mean())


def test_a_limb_sent_to_the_other_side_is_brought_back_exactly_on_the_same_surface(shape):
    target, truth = _shuffled_copy(shape, np.random.default_rng(0))
    vertex_map, reverse_map, swapped = _swapped_end(shape, target, truth)
    confidence = cycle_confidence(vertex_map, reverse_map, shape.vertices, 0.1)
    # The swapped end does not come back; the rest does.
    assert confidence[swapped].max() < 0.01
    assert np.delete(confidence, swapped).min() == 1.0
    before = _mean_error(target, vertex_map, truth, swapped)
    assert before > 2.0  # the end went to the other end, about 4 away
    repaired, n_repaired = repair_map(shape, target, vertex_map, confidence)
    assert n_repaired == len(swapped)
    # Distances to the landmarks are the same on the same surface: every vertex finds itself.
    np.testing.assert_array_equal(repaired, truth)


def test_a_swapped_limb_is_repaired_on_a_jittered_copy_and_on_a_point_cloud(shape):
    edge = _edge_length(shape)
    for cloud in (False, True):
        target, truth = _shuffled_copy(shape, np.random.default_rng(1), noise=0.1 * edge, cloud=cloud)
        vertex_map, reverse_map, swapped = _swapped_end(shape, target, truth)
        confidence = cycle_confidence(vertex_map, reverse_map, shape.vertices, 0.1)
        repaired, _ = repair_map(shape, target, vertex_map, confidence)
        # Within about an edge of the true vertex (graph distances on a jittered mesh or a neighbour graph
        # differ a little from the source's), against the other end of the shape before.
        assert _mean_error(target, repaired, truth, swapped) < 1.5 * edge, cloud
        assert _mean_error(target, vertex_map, truth, swapped) > 10 * edge
        # Trusted vertices are left as they were.
        keep = np.setdiff1d(np.arange(shape.n_vertices), swapped)
        np.testing.assert_array_equal(repaired[keep], vertex_map[keep])


def test_two_limbs_swapped_both_ways_come_back_but_are_repaired_by_their_distances(shape):
    # Both ends swapped, in both directions: the round trip comes back everywhere, only the distances to the
    # rest of the shape tell the swap.
    edge = _edge_length(shape)
    target, truth = _shuffled_copy(shape, np.random.default_rng(3), noise=0.1 * edge)
    x = shape.vertices[:, 0]
    swapped = np.flatnonzero(np.abs(x) > 0.75 * x.max())  # a quarter of the vertices
    mirror = shape.vertices[swapped] * [-1.0, 1.0, 1.0]
    partner = np.argmin(((shape.vertices[None, :, :] - mirror[:, None, :]) ** 2).sum(axis=2), axis=1)
    vertex_map = truth.copy()
    vertex_map[swapped] = truth[partner]
    reverse_map = np.argsort(vertex_map)  # the swap is a bijection where the mirror partners are unique
    confidence = cycle_confidence(vertex_map, reverse_map, shape.vertices, 0.1)
    assert np.median(confidence[swapped]) == 1.0
    assert _mean_error(target, vertex_map, truth, swapped) > 10 * edge
    kept, _ = repair_map(shape, target, vertex_map, confidence, distortion_factor=np.inf)
    assert _mean_error(target, kept, truth, swapped) > 5 * edge  # the round trip alone cannot see it
    repaired, n_repaired = repair_map(shape, target, vertex_map, confidence)
    assert n_repaired >= 0.9 * len(swapped)
    assert _mean_error(target, repaired, truth, swapped) < 1.5 * edge


def test_a_trusted_map_is_returned_as_it_is(shape):
    target, truth = _shuffled_copy(shape, np.random.default_rng(2))
    repaired, n_repaired = repair_map(shape, target, truth, np.ones(shape.n_vertices))
    assert n_repaired == 0 and np.array_equal(repaired, truth)
    # Too few trusted vertices to place landmarks on: nothing to locate the others by.
    confidence = np.zeros(shape.n_vertices)
    confidence[:10] = 1.0
    repaired, n_repaired = repair_map(shape, target, truth, confidence, landmarks=64)
    assert n_repaired == 0 and np.array_equal(repaired, truth)


def test_landmark_distances_follow_the_surface_and_call_another_piece_far():
    # Two unit squares of a grid, 10 apart: from a corner of the first, the opposite corner is sqrt(2)
    # along the diagonal edges, and every vertex of the second piece twice the largest distance found.
    vertices = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=float)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    both = Surface(np.vstack([vertices, vertices + [10.0, 0, 0]]), np.vstack([faces, faces + 4]))
    distances = landmark_distances(both, np.array([0]))
    np.testing.assert_allclose(distances[:4, 0], [0.0, 1.0, np.sqrt(2.0), 1.0])
    np.testing.assert_allclose(distances[4:, 0], 2 * np.sqrt(2.0))


@pytest.mark.skipif(
    importlib.util.find_spec("anny") is None or importlib.util.find_spec("pymeshlab") is None,
    reason="needs the bodies extra (anny, pymeshlab)",
)
def test_zernet_match_repairs_only_the_vertices_whose_template_match_does_not_come_back(tmp_path, one_torch_thread):
    from zernet.matching import match_surfaces
    from zernet.matching.bodies import body_forms, ground_truth_map

    forms, body_vertices, faces = body_forms(
        range(2), "test", {"remeshed": 1.0}, 0, "coarse-615", "varied", 0, tmp_path
    )
    source, target = forms[0].surface, forms[1].surface
    kept, _, _ = match_surfaces(source, target, repair=False)
    repaired, _, _ = match_surfaces(source, target)
    # Only the vertices the template map's own round trip or distances flag are mapped again: on a generated
    # pair, which the template model reads well, few; most of them did not come back.
    changed = repaired.vertex_map != kept.vertex_map
    assert 0 < changed.sum() < 0.2 * source.n_vertices
    assert np.mean(kept.confidence[changed] < TRUST_THRESHOLD) > 0.5
    truth = ground_truth_map(forms[0], forms[1], body_vertices[forms[1].body], faces)

    def error(vertex_map):
        return np.linalg.norm(target.vertices[vertex_map] - target.vertices[truth], axis=1).mean()

    # On a generated pair the template map is already right almost everywhere: the repair costs nothing.
    assert error(repaired.vertex_map) < error(kept.vertex_map) + 0.01 * np.sqrt(target.area)

    # A part of a body (its front half, in the same units) is left as the template model maps it: distances
    # along it cannot cross the missing side.
    front_vertices = np.flatnonzero(source.vertices[:, 2] > np.median(source.vertices[:, 2]))
    inside = np.isin(source.faces, front_vertices).all(axis=1)
    renumber = np.full(source.n_vertices, -1)
    renumber[front_vertices] = np.arange(len(front_vertices))
    front = Surface(source.vertices[front_vertices], renumber[source.faces[inside]], name="front")
    part, _, _ = match_surfaces(front, target, same_scale=True)
    part_kept, _, _ = match_surfaces(front, target, same_scale=True, repair=False)
    np.testing.assert_array_equal(part.vertex_map, part_kept.vertex_map)


@pytest.mark.parametrize("flags, repair", [([], True), (["--no-repair"], False)])
def test_zernet_match_repairs_by_default_and_not_with_no_repair(tmp_path, monkeypatch, shape, flags, repair):
    import trimesh

    import zernet.matching.match as match_module
    from zernet.cli import main
    from zernet.matching.match import MatchResult

    asked = {}

    def recording_match(source, target, model, cache_dir=None, same_scale=False, repair=True):
        asked["repair"] = repair
        n_source, n_target = source.n_vertices, target.n_vertices
        identity = np.arange(n_source)
        return MatchResult(identity, np.arange(n_target), np.eye(2), np.ones(n_source)), None, None

    monkeypatch.setattr(match_module, "match_surfaces", recording_match)
    path = tmp_path / "shape.ply"
    trimesh.Trimesh(shape.vertices, shape.faces, process=False).export(path)
    assert main(["match", str(path), str(path), "--out", str(tmp_path / "ab"), "--no-picture", *flags]) == 0
    assert asked["repair"] is repair
    np.testing.assert_array_equal(np.load(tmp_path / "ab.npy"), np.arange(shape.n_vertices))
