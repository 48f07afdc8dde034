"""The "front" geodesic backend: surface distances where chords cut across folds, thin tubes the shorter
way round, and the invariances of polar coordinates; the exact (MMP) reference on analytic surfaces."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from meshes import cylinder_mesh, grid_mesh
from test_polar import hairpin_mesh

from zernet.geometry import Surface, compute_polar, sample_surface, tangent_frames
from zernet.geometry.polar.front import front_polar


def wrap(angle):
    return (angle + np.pi) % (2 * np.pi) - np.pi


def test_tight_fold_is_measured_along_the_surface():
    # Two sheets 0.4 apart joined by a bend, r0 = 2: through the air the other sheet is 0.4 away, along
    # the surface at least 0.63 + the distances to the bend. Every kept pair must be within r0 along the
    # strip (unrolled: arclength s and width y), and every true pair must be kept.
    vertices, faces, arclength = hairpin_mesh(length=6.0, gap=0.4, width=3.0, spacing=0.25)
    surface = Surface(vertices, faces)
    samples = sample_surface(surface, 4000, seed=0)
    r0 = 2.0
    polar = compute_polar(surface, samples, r0, backend="front")
    s_sample = samples.interpolation @ arclength
    unrolled = np.hypot(
        s_sample[polar.sample] - arclength[polar.center], samples.points[polar.sample, 1] - vertices[polar.center, 1]
    )
    # (The bend is only two faces wide, so its unrolled arclength is approximate; the exact comparison is
    # test_front_agrees_with_the_exact_reference_on_a_fold.)
    assert unrolled.max() < 1.05 * r0
    assert np.median(np.abs(polar.radius - unrolled)) < 1e-9
    assert np.percentile(np.abs(polar.radius - unrolled), 95) < 0.03 * r0
    # A chord-based radius would have taken the other sheet for the vertices near the bend.
    lower = np.flatnonzero((arclength > 2.5) & (arclength < 3.5) & (np.abs(vertices[:, 1] - 1.5) < 0.5))
    picked = np.isin(polar.center, lower)
    assert np.all(samples.points[polar.sample[picked], 2] < 1e-9)  # the lower sheet only (the bend is > r0 away)
    truth = (
        np.hypot(s_sample[None, :] - arclength[lower, None], samples.points[None, :, 1] - vertices[lower, None, 1])
        <= 0.95 * r0
    )
    kept = np.zeros_like(truth)
    rows = np.searchsorted(lower, polar.center[picked])
    kept[rows, polar.sample[picked]] = True
    assert np.all(kept[truth])


def test_thin_tube_is_measured_the_shorter_way_round():
    # Circumference 2πR ≈ 3.1 < 2 r0: the cut locus lies inside every patch.
    radius, r0 = 0.5, 2.0
    vertices, faces = cylinder_mesh(radius, 10.0, 48, 81)
    surface = Surface(vertices, faces)
    samples = sample_surface(surface, 6000, seed=3)
    polar = compute_polar(surface, samples, r0, backend="front")
    inner = np.abs(vertices[polar.center, 2]) < 5.0 - r0
    p, q = vertices[polar.center[inner]], samples.points[polar.sample[inner]]
    dphi = wrap(np.arctan2(q[:, 1], q[:, 0]) - np.arctan2(p[:, 1], p[:, 0]))  # the shorter way: |dphi| <= π
    shorter = np.hypot(radius * dphi, q[:, 2] - p[:, 2])
    assert np.percentile(np.abs(polar.radius[inner] - shorter), 95) < 0.01 * r0
    assert np.all(polar.radius[inner] <= shorter + 0.03 * r0)  # never the longer way round


def test_turning_the_frames_shifts_every_angle_by_the_turn():
    vertices, faces = grid_mesh(13, 13, spacing=0.5, jitter=0.15, seed=2)
    vertices = vertices + np.c_[np.zeros((len(vertices), 2)), 0.1 * np.sin(vertices[:, 0])]  # not flat
    surface = Surface(vertices, faces)
    samples = sample_surface(surface, 1500, seed=1)
    frames = tangent_frames(surface)
    delta = np.random.default_rng(0).uniform(-np.pi, np.pi, len(vertices))
    turned = frames.copy()
    turned[:, 0] = np.cos(delta)[:, None] * frames[:, 0] + np.sin(delta)[:, None] * frames[:, 1]
    turned[:, 1] = np.cross(frames[:, 2], turned[:, 0])
    c0, s0, r_0, a0 = front_polar(surface, samples, frames, 1.5)
    c1, s1, r_1, a1 = front_polar(surface, samples, turned, 1.5)
    np.testing.assert_array_equal(c0, c1)
    np.testing.assert_array_equal(s0, s1)
    np.testing.assert_allclose(r_0, r_1, atol=1e-12)
    far = r_0 > 1e-6
    assert np.abs(wrap(a1 - (a0 - delta[c0])))[far].max() < 1e-9


def test_reindexing_and_rigid_motion_leave_the_coordinates_unchanged():
    mesh = trimesh.creation.icosphere(2, radius=3.0)
    surface = Surface(np.asarray(mesh.vertices), np.asarray(mesh.faces))
    samples = sample_surface(surface, 1200, seed=0)
    frames = tangent_frames(surface)
    reference = front_polar(surface, samples, frames, 1.2)
    # Re-index the vertices (and move the mesh rigidly): the same samples in space, the same frames.
    perm = np.random.default_rng(1).permutation(len(surface.vertices))
    inverse = np.argsort(perm)
    rotation = trimesh.transformations.random_rotation_matrix(np.random.default_rng(2).random(3))[:3, :3]
    moved = Surface(surface.vertices[perm] @ rotation.T + [1.0, -2.0, 0.5], inverse[surface.faces])
    moved_samples = samples.__class__(
        **{
            **samples.__dict__,
            "points": samples.points @ rotation.T + [1.0, -2.0, 0.5],
            "normals": samples.normals @ rotation.T,
            "interpolation": samples.interpolation[:, inverse],
        }
    )
    moved_frames = frames[perm] @ rotation.T
    center, sample, radius, angle = front_polar(moved, moved_samples, moved_frames, 1.2)
    original = perm[center]
    order = np.lexsort((sample, original))
    ref_order = np.lexsort((reference[1], reference[0]))
    np.testing.assert_array_equal(original[order], reference[0][ref_order])
    np.testing.assert_array_equal(sample[order], reference[1][ref_order])
    np.testing.assert_allclose(radius[order], reference[2][ref_order], atol=1e-9)
    np.testing.assert_allclose(wrap(angle[order] - reference[3][ref_order]), 0.0, atol=1e-7)


def test_point_clouds_are_refused_with_the_name():
    cloud = Surface(np.random.default_rng(0).normal(size=(50, 3)), None, name="cloud.xyz")
    samples = sample_surface(cloud, 50)
    with pytest.raises(Exception, match="cloud.xyz"):
        compute_polar(cloud, samples, 1.0, backend="front")


# ---------------------------------------------------------------------- the exact reference
def test_exact_reference_matches_analytic_plane_and_sphere():
    pytest.importorskip("pygeodesic")
    from zernet.geometry.polar.exact import ExactGeodesics

    vertices, faces = grid_mesh(9, 9, spacing=0.5, jitter=0.1, seed=4)
    plane = Surface(vertices, faces)
    samples = sample_surface(plane, 400, seed=0)
    frames = tangent_frames(plane)
    exact = ExactGeodesics(plane, samples, frames)
    center = int(np.argmin(np.linalg.norm(vertices, axis=1)))
    c, s, distance, angle = exact.polar([center], 1.5)
    offset = samples.points[s] - vertices[center]
    inside = np.isfinite(distance)
    np.testing.assert_allclose(distance[inside], np.linalg.norm(offset, axis=1)[inside], atol=1e-9)
    has_angle = np.isfinite(angle) & (distance > 0.05)
    expected = np.arctan2(offset @ frames[center, 1], offset @ frames[center, 0])
    assert np.abs(wrap(angle - expected))[has_angle].max() < 1e-6

    mesh = trimesh.creation.icosphere(3, radius=4.0)
    sphere = Surface(np.asarray(mesh.vertices), np.asarray(mesh.faces))
    samples = sample_surface(sphere, 800, seed=0)
    exact = ExactGeodesics(sphere, samples, tangent_frames(sphere))
    c, s, distance, _ = exact.polar([0, 17], 1.5, limit=1.5)
    a, b = sphere.vertices[c] / 4.0, samples.points[s] / np.linalg.norm(samples.points[s], axis=1, keepdims=True)
    great_circle = 4.0 * np.arccos(np.clip((a * b).sum(1), -1, 1))
    inside = np.isfinite(distance)
    # The polyhedron's geodesics are slightly shorter than the sphere's (its faces cut the chords).
    assert np.abs(distance[inside] - great_circle[inside]).max() < 0.01 * 1.5


def test_front_agrees_with_the_exact_reference_on_a_fold():
    pytest.importorskip("pygeodesic")
    from zernet.geometry.polar.exact import ExactGeodesics

    vertices, faces, _ = hairpin_mesh(length=3.0, gap=0.4, width=2.0, spacing=0.25)
    surface = Surface(vertices, faces)
    samples = sample_surface(surface, 600, seed=0)
    frames = tangent_frames(surface)
    centers = np.flatnonzero(np.isclose(vertices[:, 2], 0.0) & (vertices[:, 0] > 2.0))[::3]
    c, s, distance, _ = ExactGeodesics(surface, samples, frames).polar(centers, 1.0, limit=1.5)
    center, sample, radius, _ = front_polar(surface, samples, frames, 1.0)
    front = dict(zip(zip(center.tolist(), sample.tolist()), radius))
    exact = dict(zip(zip(c.tolist(), s.tolist()), distance))
    kept = [key for key in front if key[0] in set(centers.tolist())]
    assert kept and all(exact.get(key, np.inf) <= 1.1 for key in kept)  # nothing from across the fold
    true_pairs = [key for key, d in exact.items() if d < 0.95]
    assert sum(key in front for key in true_pairs) >= 0.995 * len(true_pairs)
    errors = np.array([abs(front[key] - exact[key]) for key in true_pairs if key in front])
    assert np.median(errors) < 0.003 and np.percentile(errors, 95) < 0.02


# ---------------------------------------------------------------------- fans and long edges
def test_fan_angles_scale_the_corner_angles_around_a_cone_apex():
    # A cone apex with total angle 5 (not 2π): intrinsic angles are corner angles × 2π / 5, and mapping
    # an edge's intrinsic angle back gives that edge's tangent-plane angle.
    from zernet.geometry.polar.fans import tangent_angle_of, vertex_fans

    around = 10
    phi = np.linspace(0, 2 * np.pi, around, endpoint=False)
    height = 0.8
    vertices = np.vstack([[0.0, 0.0, height], np.c_[np.cos(phi), np.sin(phi), np.zeros(around)]])
    faces = np.array([[0, 1 + i, 1 + (i + 1) % around] for i in range(around)])
    surface = Surface(vertices, faces)
    frames = tangent_frames(surface)
    fans = vertex_fans(vertices, faces, frames)
    total = fans.corner[:, 0].sum()
    assert fans.ordered[0]
    np.testing.assert_allclose(fans.scale[0], 2 * np.pi / total)
    wedges = np.arange(fans.wedge_start[0], fans.wedge_start[1])
    for w in wedges:
        a = faces[fans.wedge_face[w], (fans.wedge_corner[w] + 1) % 3]
        edge = vertices[a] - vertices[0]
        expected = np.arctan2(edge @ frames[0, 1], edge @ frames[0, 0])
        mapped = tangent_angle_of(
            0,
            fans.start_angle[w],
            vertices,
            faces,
            frames,
            fans.wedge_start,
            fans.wedge_face,
            fans.wedge_corner,
            fans.start_angle,
            fans.scale,
            fans.corner,
            fans.reversed,
        )
        assert abs(wrap(mapped - expected)) < 1e-9
    steps = np.sort(wrap(fans.start_angle[wedges] - fans.start_angle[wedges[0]]) % (2 * np.pi))
    np.testing.assert_allclose(np.diff(steps), 2 * np.pi / around, atol=1e-9)  # equal corners, evenly spread


def test_faces_with_edges_longer_than_r0_keep_their_samples():
    # Four huge triangles (edges 10 and 14) and r0 = 1: every sample within r0 of a vertex lies in a face
    # whose other corners are far beyond r0; all of them must be found, at their straight-line distance.
    vertices = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0], [0, 10, 0], [5, 5, 0]], dtype=float)
    faces = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    surface = Surface(vertices, faces)
    samples = sample_surface(surface, 4000, seed=0)
    r0 = 1.0
    center, sample, radius, angle = front_polar(surface, samples, tangent_frames(surface), r0)
    distance = np.linalg.norm(samples.points[None] - vertices[:, None], axis=2)
    expected = set(zip(*np.nonzero(distance <= r0 * (1 - 1e-9))))
    found = set(zip(center.tolist(), sample.tolist()))
    assert expected and expected <= found
    np.testing.assert_allclose(radius, distance[center, sample], atol=1e-12)


def test_a_flipped_face_falls_back_to_tangent_angles_and_plane_angles_stay_exact():
    # A flat grid with one face's orientation flipped: the fans of its corners are no single ordered walk
    # and fall back to tangent-plane wedges; on a plane every angle must still be the exact planar angle.
    from zernet.geometry.polar.fans import vertex_fans

    vertices, faces = grid_mesh(9, 9, spacing=0.5, jitter=0.1, seed=5)
    faces = faces.copy()
    faces[27] = faces[27, [0, 2, 1]]  # a face next to the centre vertex
    surface = Surface(vertices, faces)
    frames = tangent_frames(surface)
    frames[:, 2] = [0.0, 0.0, 1.0]  # one consistent up direction, whatever the flipped face did to the normals
    frames[:, 1] = np.cross(frames[:, 2], frames[:, 0])
    fans = vertex_fans(vertices, faces, frames)
    assert not fans.ordered[faces[27]].any() and fans.ordered.sum() >= len(vertices) - 3
    samples = sample_surface(surface, 800, seed=2)
    center, sample, radius, angle = front_polar(surface, samples, frames, 1.2)
    inner = np.abs(vertices[center, :2]).max(axis=1) < 2.0 - 1.3  # a jittered border is not convex
    center, sample, radius, angle = center[inner], sample[inner], radius[inner], angle[inner]
    assert np.isin(faces[27], center).all()
    offset = samples.points[sample] - vertices[center]
    np.testing.assert_allclose(radius, np.linalg.norm(offset, axis=1), atol=1e-9)
    expected = np.arctan2(
        np.einsum("pi,pi->p", offset, frames[center, 1]), np.einsum("pi,pi->p", offset, frames[center, 0])
    )
    assert np.abs(wrap(angle - expected))[radius > 0.05].max() < 1e-6
